"""The ± σ that ``torchfric track`` shows, made from its filter's ``P_θθ`` (issue 31).

The tracking filter's own σ are as narrow as a run's filter's were: on a record whose noise is
coloured, or whose friction the class draws approximately, 3–60 times too narrow. A run
measures by how much: its reported σ (`torchfric.app.run.confidence`: the prediction-error
sandwich plus the offset between its two estimates) over its filter's, per parameter
(`band_scale`). The tracker shows its filter's σ times that ratio; the filter itself keeps its
own belief.

After a change the run's ratio describes the machine before it. Once the hold-off has gathered
the changed machine's samples, the same stage runs again over them at the tracked θ
(`remeasured_scale`), and the ratio becomes the larger of the run's and the new one, per
parameter. Why: the EMPS-like axis pins b several times less after a 40 % rise of its dry
friction (a run on the changed machine: ±3.0 % against ±0.56 % before), and with the run's
ratio its tracked b, settled on the class's compromise with the new friction, stayed inside
±2σ in 6–30 % of the rows after the change (100 % since). Why the larger: a window of seconds
measures the changed machine, not every regime the identification record saw; on the
stick-slip carriage the window's ratio of M was half the run's, and its tracked M, drifting
+20 % after the change, left the narrower band in 39 % of the rows.

Tried and not kept: the run's covariance split into the sandwich, scaled with the filter's σ,
and the offset, held beside it as a bias that data do not shrink. On the rig it changed
nothing (b inside ±2σ in 35 against 41 % of ten unchanged minutes); on the carriage, where
the random walk of θ widens the filter's σ of M over a minute and the ratio widens it 56
times, the split held M in 18 % of the rows before the change against 100 %.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ...errors import TorchfricError

__all__ = ["band_scale", "remeasured_scale"]


def band_scale(reported: Any, own: Any) -> Tensor:
    """Per parameter ``sqrt(diag(reported) / diag(own))``, at least 1: the tracker never shows
    σ narrower than its filter's."""
    reported = torch.as_tensor(reported, dtype=torch.float64)
    ratio = torch.diagonal(reported) / torch.diagonal(torch.as_tensor(own, dtype=torch.float64))
    ratio = torch.where(torch.isfinite(ratio) & (ratio > 1.0), ratio, torch.ones_like(ratio))
    return ratio.sqrt()


def remeasured_scale(model: Any, exp: Any, tuning: Any, change: float, row: Any) -> tuple[Tensor | None, dict]:  # fmt: skip
    """The ratio measured on the changed machine: the run's prediction-error stage
    (`torchfric.app.run.covariance_at`: noise model, sandwich, polish) at the tracked θ over
    `exp`'s samples from the `change` to `row` (its hold-off), the sandwich there plus the
    offset to that window's optimum, over the tracker's ``P_θθ`` at `row`. Returns
    ``(scale or None, entry)``, the entry for events.json (``failed``: why there is none)."""
    from ..run import covariance_at

    t = exp.t
    first = int(torch.searchsorted(t, torch.tensor(change, dtype=t.dtype)))
    last = int(torch.searchsorted(t, torch.tensor(row.t, dtype=t.dtype), right=True))
    entry: dict[str, Any] = {"change": change, "t": row.t, "samples": last - first}
    try:
        cov = covariance_at(model, [exp.slice(first, last)], tuning, row.theta)
    except TorchfricError as err:
        entry["failed"] = str(err)
        return None, entry
    scale = band_scale(cov, row.P_theta)
    entry["band_scale"] = dict(zip(model.theta_names, scale.tolist(), strict=True))
    return scale, entry
