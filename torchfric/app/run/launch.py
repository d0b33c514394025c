"""`fit`: the CLI's ``train`` as one Python call, with the same defaults and the same run.

    result = torchfric.fit("experiments/configs/arm_tanh_ekf.toml", estimator={"passes": 3})
    result.model.inertia, result.metrics["parameters"]["inertia"], result.run_dir

Nothing here imports torch at module level: the CLI imports `torch_settings` before torch.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from ...environment import torch_settings
from ...errors import TorchfricError

if TYPE_CHECKING:
    from ..config import Config
    from .runner import TrainResult

__all__ = ["fit", "override_strings", "progress_printer", "torch_settings", "train_on_stderr"]


def override_strings(overrides: Mapping[str, Any]) -> list[str]:
    """Keyword overrides as ``--set`` strings: ``estimator={"passes": 3}`` (a section as a
    dict), ``**{"estimator.passes": 3}`` (dotted keys) and top-level keys (``name="x"``)."""
    from ..config import SECTIONS, toml_value

    out: list[str] = []
    for key, value in overrides.items():
        if key in SECTIONS and isinstance(value, Mapping):
            out += override_strings({f"{key}.{k}": v for k, v in value.items()})
            continue
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        if isinstance(value, tuple):
            value = list(value)
        out.append(f"{key}={toml_value(value)}")
    return out


def progress_printer(quiet: bool, bars: bool = False) -> Callable[[str], None]:
    """The run's progress lines on stderr (nothing when `quiet`); with `bars` (a terminal) through
    tqdm, above its bars. A line starting with ``\\r`` is in-pass progress that only a terminal
    without bars shows."""

    def say(msg: str) -> None:
        if quiet:
            return
        if msg.startswith("\r"):
            if sys.stderr.isatty() and not bars:
                sys.stderr.write(msg)
                sys.stderr.flush()
                return
            if not msg.endswith("\n"):
                return  # in-pass progress only on a terminal
            msg = msg[1:]
        if bars:
            from tqdm import tqdm

            tqdm.write(msg.rstrip("\n"), file=sys.stderr)
            return
        sys.stderr.write(msg if msg.endswith("\n") else msg + "\n")
        sys.stderr.flush()

    return say


def fit(
    config: str | os.PathLike[str] | Config,
    /,
    *,
    out: str | os.PathLike[str] | None = None,
    resume: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    checkpoint: str | os.PathLike[str] | None = None,
    quiet: bool = False,
    device: str | None = None,
    **overrides: Any,
) -> TrainResult:
    """Identify a model from a config, as ``torchfric train`` does: the same defaults, the same
    checks, the same run directory (``runs/NAME``, or ``runs/NAME-2``, …), checkpoint,
    ``metrics.json``, ``report.html`` and TensorBoard logs.

    Args:
        config: a TOML config file, or a `Config`.
        out: the run directory (``--out``); resume: an interrupted run to continue
            (``--resume``); overwrite, checkpoint: as ``--overwrite`` and ``--checkpoint``.
        quiet: no progress on stderr (``--quiet``).
        device: ``"cuda"`` (``--device``) filters ensembles and ``model.size = "auto"`` on
            the GPU; None: the CPU.
        **overrides: config keys, as ``--set`` does: a section as a dict
            (``estimator={"passes": 3}``), dotted keys (``**{"estimator.passes": 3}``) or
            top-level keys (``name="trial"``). Paths are relative to the working directory.

    Returns:
        `TrainResult`: ``.model`` (the kept model), ``.metrics`` (as in ``metrics.json``),
        ``.history`` (per pass or epoch), ``.run_dir`` and ``.checkpoint``.

    Raises:
        TorchfricError: a bad config, bad data or a diverged filter, with the message the CLI
            prints (nothing is written before the config and data are checked).
    """
    from ..config import Config

    sets = override_strings(overrides)
    if isinstance(config, Config):
        cfg = config.with_overrides(sets) if sets else config
    elif isinstance(config, str | os.PathLike):
        cfg = Config.load(config, sets)
    else:
        raise TorchfricError(
            f"fit() takes a config file path or a torchfric.Config, got {type(config).__name__}"
        )
    return train_on_stderr(  # `train` runs under `torch_settings` itself
        cfg, out=out, resume=resume, overwrite=overwrite, checkpoint=checkpoint, quiet=quiet,
        device=device,
    )  # fmt: skip


def train_on_stderr(
    cfg: Config,
    *,
    out: str | os.PathLike[str] | None = None,
    resume: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    checkpoint: str | os.PathLike[str] | None = None,
    quiet: bool = False,
    device: str | None = None,
) -> TrainResult:
    """`torchfric.app.run.runner.train` with the CLI's progress on stderr (bars on a terminal,
    lines elsewhere, nothing when `quiet`): what ``torchfric train`` and `fit` both run."""
    from .runner import train

    bars = not quiet and sys.stderr.isatty()
    return train(
        cfg,
        run_dir=resume if resume is not None else out,
        resume=resume is not None,
        overwrite=overwrite,
        checkpoint=checkpoint,
        say=progress_printer(quiet, bars),
        bars=sys.stderr if bars else None,
        device=device,
    )
