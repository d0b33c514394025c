"""What a user looks at after a run, and the run's observers as one list.

- `ReportPage`: writes report.html when the run ends, with the kept model's figures that
  TensorBoard shows too (`torchfric.app.run.monitors.KeptFigures`, drawn once);
- `run_observers`: the run's observers, in the order they must see each step.
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence
from typing import TextIO

from ...data import Experiment
from ...estimators.observers import Callback, CallbackList, RunEnd
from ...models.arm import ArmModel
from ..artifacts import write_report
from ..config import Config
from .monitors import KeptFigures, Printer, ProgressLines, ValidationScores
from .snapshots import Snapshots
from .tensorboard_log import TensorBoardLog

__all__ = ["ReportPage", "run_observers"]


class ReportPage(Callback):
    """Writes ``report.html`` in the run directory when the run ends, with the kept model's
    figures from `drawing` (the PNGs TensorBoard shows) and its parameter trajectories."""

    def __init__(self, cfg: Config, run_dir: pathlib.Path, drawing: KeptFigures) -> None:
        self.cfg, self.run_dir, self.drawing = cfg, run_dir, drawing

    def on_estimate(self, end: RunEnd) -> None:
        self.drawing.early(end)

    def on_run_end(self, end: RunEnd) -> None:
        images = self.drawing.pngs(self.drawing.kept(end))
        if (trajectory := self.drawing.trajectory()) is not None:
            images["trajectory"] = trajectory
        write_report(
            self.run_dir / "report.html", title=self.cfg.name, model=end.model,
            metrics=dict(end.metrics), history=list(end.history),
            validation=self.drawing.validation, scores=dict(end.scores),
            v_max=self.drawing.v_max, unit=self.cfg.data.axis_unit, P_theta=end.covariance,
            images=images,
        )  # fmt: skip


def run_observers(
    cfg: Config,
    run_dir: pathlib.Path,
    data: tuple[Sequence[Experiment], Sequence[Experiment]],
    model: ArmModel,
    say: Printer,
    *,
    bars: TextIO | None = None,
    snapshot_info: tuple[dict[str, str], str, float | None],
    extra: Sequence[Callback] = (),
) -> tuple[ValidationScores, CallbackList]:
    """The validation scorer and the run's observers of `model`'s estimation, in the order
    each step needs: the scores first (the others read them), TensorBoard, the progress lines,
    the snapshots, the report, then the caller's own `extra`.

    `data` is (identification, validation) records; `snapshot_info` is the data fingerprints,
    how the run started and its initial inertia (what each snapshot records)."""
    from torch.utils.tensorboard import SummaryWriter

    train, validation = data
    v_max = 1.2 * max(float(e.qdot.abs().max()) for e in train if e.qdot is not None)
    scores = ValidationScores(cfg, list(validation))
    drawing = KeptFigures(cfg, validation, v_max)
    fingerprints, init_kind, initial_inertia = snapshot_info
    own: list[Callback] = [
        scores,
        TensorBoardLog(cfg, SummaryWriter(log_dir=str(run_dir)), scores, drawing, model),
        ProgressLines(cfg, say, scores, model, bars),
        Snapshots(cfg, run_dir, fingerprints, scores, model, init_kind, initial_inertia),
        ReportPage(cfg, run_dir, drawing),
    ]
    return scores, CallbackList(own + list(extra))
