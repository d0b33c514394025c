"""Resumable snapshots of a run: the `Snapshots` observer and reading them back.

After each pass (single EKF: ``passes/pass_NNN.pt``; ensemble: ``passes/ensemble_NNN.pt``) or
validated output-error epoch (``passes/epoch_NNNNN.pt``) the run writes an incomplete checkpoint
holding the estimator's whole state, so that ``--resume`` continues exactly where it stopped.
Only the two newest are kept. A diverged single filter's last good pass goes to
``last_good.pt`` through the same writer.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ...errors import DivergenceError, TorchfricError
from ...estimators.identify import EKFResult, PassRecord
from ...estimators.observers import Callback
from ...estimators.output_error import EpochRecord, OEResult
from ...files import json_safe
from ...models.arm import ArmModel
from ..artifacts import build_checkpoint, read_checkpoint, save_checkpoint
from ..config import Config
from .monitors import ValidationScores

__all__ = [
    "EKFResume",
    "EnsembleResume",
    "OEResume",
    "Resume",
    "resume_from",
    "Snapshots",
    "ekf_payload",
    "oe_payload",
    "latest_snapshot",
    "snapshot_index",
    "snapshot_label",
    "resume_state",
]


def ekf_payload(result: EKFResult, pass_index: int) -> dict[str, Any]:
    """The single filter's state after `pass_index` (θ, P_θ, history): a checkpoint's
    ``estimator.state``, enough to resume from."""
    return {
        "method": "ekf",
        "pass": pass_index,
        "theta": result.theta.clone(),
        "P_theta": result.P_theta.clone(),
        "history": [r.to_dict() for r in result.history],
        "converged": result.converged,
    }


def oe_payload(result: OEResult, epoch: int) -> dict[str, Any]:
    """The output-error state after `epoch` (θ, history, optimizer and shooting states): a
    checkpoint's ``estimator.state``, enough to resume from."""
    state: dict[str, Any] = {
        "method": "output_error",
        "epoch": epoch,
        "theta": result.theta.clone(),
        "best_epoch": result.best_epoch,
        "history": [r.to_dict() for r in result.history],
    }
    if result.optimizer_state is not None:
        state["optimizer_state"] = result.optimizer_state
    if result.shooting is not None:
        state["shooting"] = result.shooting.clone()
    if result.initial_theta is not None:
        state["initial_theta"] = result.initial_theta.clone()
    return state


@dataclass(frozen=True)
class EKFResume:
    """Where a single filter's interrupted run continues: after pass `pass_index`, from its
    θ, ``P_θθ`` and pass history (`identify_ekf`'s ``start``)."""

    pass_index: int
    theta: Tensor
    P_theta: Tensor
    history: list[PassRecord]

    @property
    def start(self) -> tuple[Tensor, Tensor, list[PassRecord]]:
        return self.theta, self.P_theta, self.history


@dataclass(frozen=True)
class EnsembleResume:
    """Where an ensemble's interrupted run continues: after pass `pass_index`, from the whole
    batch's state in the ensemble's own format (`identify_ekf_ensemble`'s ``start``)."""

    pass_index: int
    state: dict[str, Any]


@dataclass(frozen=True)
class OEResume:
    """Where an output-error run continues: after epoch `epoch`, from the latest θ (the last
    record's, not the best-validated θ the snapshot's model holds), the optimizer's and the
    shooting states (`identify_output_error`'s ``start``), and the θ it started from."""

    epoch: int
    theta: Tensor
    history: list[EpochRecord]
    optimizer_state: dict[str, Any] | None = None
    shooting: Tensor | None = None
    initial_theta: Tensor | None = None

    @property
    def start(self) -> tuple[Tensor, list[EpochRecord], dict[str, Any] | None, Tensor | None]:
        latest = self.theta
        if self.history:
            latest = torch.tensor(self.history[-1].theta, dtype=torch.float64)
        return latest, self.history, self.optimizer_state, self.shooting


Resume = EKFResume | EnsembleResume | OEResume


def resume_from(state: dict[str, Any]) -> Resume:
    """A snapshot's ``estimator.state`` (the checkpoint's form, `ekf_payload`, `oe_payload`, an
    ensemble's state) as the typed form of its method."""
    method = state.get("method")
    if method == "ekf_ensemble":
        return EnsembleResume(int(state["pass"]), state)
    if method == "output_error":
        records = [
            EpochRecord(**{k: v for k, v in r.items() if k != "val_score"})
            for r in state["history"]
        ]
        return OEResume(
            int(state["epoch"]), state["theta"], records, state.get("optimizer_state"),
            state.get("shooting"), state.get("initial_theta"),
        )  # fmt: skip
    if method == "ekf":
        history = [PassRecord(**r) for r in state["history"]]
        return EKFResume(int(state["pass"]), state["theta"], state["P_theta"], history)
    raise TorchfricError(
        f"--resume: the snapshot's estimator state has method {method!r}, which this version "
        "cannot continue; start the run without --resume"
    )


def snapshot_index(path: pathlib.Path) -> int:
    """The pass or epoch number in a snapshot's name (``pass_012.pt`` → 12)."""
    digits = path.stem.rpartition("_")[2]
    return int(digits) if digits.isdigit() else -1


def latest_snapshot(run_dir: pathlib.Path) -> pathlib.Path | None:
    """The newest pass, epoch or ensemble snapshot in ``run_dir/passes``, if any."""
    folder = run_dir / "passes"
    snaps = (
        sorted(folder.glob("pass_*.pt"), key=snapshot_index)
        or sorted(folder.glob("epoch_*.pt"), key=snapshot_index)
        or sorted(folder.glob("ensemble_*.pt"), key=snapshot_index)
    )
    return snaps[-1] if snaps else None


def snapshot_label(snap: pathlib.Path | None) -> str | None:
    """What a snapshot holds, in words: ``pass 3`` or ``epoch 40``."""
    if snap is None:
        return None
    kind, _, index = snap.stem.partition("_")
    return f"{'pass' if kind in ('pass', 'ensemble') else kind} {int(index)}"


def resume_state(run: pathlib.Path, cfg: Config) -> dict[str, Any]:
    """The newest snapshot of the run in `run`, refused when `cfg` is not the run's config."""
    snap = latest_snapshot(run)
    if snap is None:
        raise TorchfricError(
            f"--resume: no pass snapshots in {run / 'passes'}; start the run without --resume"
        )
    saved = read_checkpoint(snap)
    if saved["config"] != cfg.to_dict():
        raise TorchfricError(
            f"--resume: the config differs from the one saved in {run}; resume with the same "
            "config and --set values"
        )
    return saved


class Snapshots(Callback):
    """Writes a resumable snapshot after each pass, ensemble pass or validated epoch, and
    ``last_good.pt`` when a single filter diverges (`on_exception`).

    Each snapshot's metrics hold how the run started (`init_kind`, `initial_inertia`) and the
    pass's validation FITs (from `scores`, which must observe before this one).
    """

    def __init__(
        self,
        cfg: Config,
        run_dir: pathlib.Path,
        fingerprints: dict[str, str],
        scores: ValidationScores,
        model: ArmModel,
        init_kind: str,
        initial_inertia: float | None,
    ) -> None:
        self.cfg, self.run_dir, self.fingerprints, self.scores = cfg, run_dir, fingerprints, scores
        self.model = model  # the starting model: an ensemble snapshot's model
        self.init_kind, self.initial_inertia = init_kind, initial_inertia

    def save(
        self, path: pathlib.Path, model: ArmModel, state: dict[str, Any], metrics: dict[str, Any]
    ) -> None:
        """An incomplete checkpoint (pass/epoch snapshot, last good pass), written atomically."""
        run_info = {"init": self.init_kind, "initial_inertia": self.initial_inertia}
        payload = build_checkpoint(
            model,
            config=self.cfg,
            estimator_state=state,
            metrics=json_safe({**run_info, **metrics})[0],
            data_fingerprints=self.fingerprints,
            name=self.cfg.name,
            complete=False,
        )
        save_checkpoint(path, payload)
        if path.parent.name == "passes":
            # Keep the two newest pass/epoch snapshots (the newest, and one before it in case
            # the newest is damaged): each holds the whole history, so keeping all of them would
            # grow with the square of the number of passes.
            for older in sorted(path.parent.glob("*.pt"), key=snapshot_index)[:-2]:
                older.unlink(missing_ok=True)

    def on_exception(self, error: BaseException) -> None:
        """A diverged filter's last good pass as ``last_good.pt``, named in the error."""
        last = getattr(error, "last_good", None)
        if isinstance(error, DivergenceError) and isinstance(last, EKFResult) and last.history:
            path = self.run_dir / "last_good.pt"
            self.save(path, last.model, ekf_payload(last, last.passes), {"diverged": str(error)})
            error.args = (f"{error} (last good pass saved to {path})",)

    def on_pass_end(self, record: PassRecord, result: EKFResult) -> bool | None:
        self.save(
            self.run_dir / "passes" / f"pass_{record.index:03d}.pt",
            result.model,
            ekf_payload(result, record.index),
            {"validation": self.scores.fits},
        )
        return None

    def on_ensemble_pass_end(self, pass_index: int, state: dict[str, Any]) -> bool | None:
        path = self.run_dir / "passes" / f"ensemble_{pass_index:03d}.pt"
        self.save(path, self.model, state, {})
        return None

    def on_epoch_end(self, record: EpochRecord, result: OEResult) -> bool | None:
        if record.val_fit is not None:
            self.save(
                self.run_dir / "passes" / f"epoch_{record.index:05d}.pt",
                result.model,
                oe_payload(result, record.index),
                {"validation": record.val_fit, "init": self.init_kind},
            )
        return None
