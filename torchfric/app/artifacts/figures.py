"""The run's figures of a model: the friction curve with its ±2σ band, a simulated response,
its residuals and their autocorrelation, and the parameters over the passes.

Each ``*_spec`` turns the model, a record and its scores into plain data (numpy arrays and
text) that `torchfric.app.artifacts.drawing` draws without torch, here or in the helper process
of `torchfric.app.artifacts.painter`; each ``*_figure`` is the two together and returns a
matplotlib figure (for `png_bytes` or `pixels`). Positions are in the SI unit that
`data.position_unit` converts to.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from ...data import Experiment
from ...data.units import force_unit, si_unit
from ...estimators.metrics import SimulationScore
from ...estimators.uncertainty import friction_band
from ...models.arm import ArmModel
from .drawing import (
    MAX_PANELS,
    autocorrelation,
    draw,
    envelope,
    pixels,
    png_bytes,
    png_from_pixels,
    subplots,
    trajectory_figure,
    whiteness_bound,
)

__all__ = [
    "friction_spec",
    "response_spec",
    "residual_spec",
    "trajectory_spec",
    "model_specs",
    "friction_figure",
    "response_figure",
    "residual_figure",
    "trajectory_figure",
    "autocorrelation",
    "envelope",
    "whiteness_bound",
    "png_bytes",
    "pixels",
    "png_from_pixels",
    "subplots",
    "MAX_PANELS",
]

Spec = tuple[str, dict[str, Any]]
"""A figure as `drawing.draw` takes it: its kind and its data."""


def friction_spec(
    model: ArmModel,
    v_max: float,
    title: str,
    unit: str = "rad",
    P_theta: Tensor | None = None,
) -> Spec:
    """The model's friction torque (viscous, Coulomb-like and offset terms) over ±`v_max`, with
    the ±2σ band of `P_theta` (θ's covariance in estimation coordinates) when one is given.

    The band's widest half-width is in its legend entry: after many passes it can be thinner
    than the line, and the legend then still says how wide it is."""
    v = torch.linspace(-v_max, v_max, 801, dtype=torch.float64)
    band = None
    if P_theta is not None and bool(torch.isfinite(torch.as_tensor(P_theta)).all()):
        mean, std = friction_band(model, P_theta, v)
        band = (mean.numpy(), 2.0 * std.numpy())
    with torch.no_grad():
        f = model.friction_torque(v).numpy()
    return "friction", {
        "v": v.numpy(), "f": f, "band": band, "title": title, "force": force_unit(unit),
        "v_label": f"velocity q̇ [{si_unit(unit)}/s]",
        "offset": "offset" in model.physical_parameters(),
    }  # fmt: skip


def _qdot(exp: Experiment) -> Tensor:
    if exp.qdot is None:  # loaded records always have one (measured or reconstructed)
        raise ValueError(f"{exp.name}: no velocity to compare with; load it with load_data")
    return exp.qdot


def response_spec(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Spec:
    """Measured against open-loop simulated q and q̇ of one record, titled with the FITs."""
    return "response", {
        "t": exp.t.numpy(), "q": exp.q.numpy(), "q_sim": score.states[:, 0].numpy(),
        "qdot": _qdot(exp).numpy(), "qdot_sim": score.states[:, 1].numpy(),
        "unit": si_unit(unit), "name": exp.name, "fit_q": score.fit_q,
        "fit_qdot": score.fit_qdot,
    }  # fmt: skip


def residual_spec(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Spec:
    """Residuals (measured − simulated) of q and q̇ over time, and their autocorrelation over
    lags 0 … min(200, N/4) with the white-noise bounds ±1.96/√N."""
    return "residuals", {
        "t": exp.t.numpy(), "e_q": exp.q.numpy() - score.states[:, 0].numpy(),
        "e_qdot": _qdot(exp).numpy() - score.states[:, 1].numpy(), "unit": si_unit(unit),
        "name": exp.name, "dt": exp.dt,
    }  # fmt: skip


def trajectory_spec(history: Sequence[Any], best: int | None = None) -> Spec:
    """Each physical parameter over the passes (or epochs) of `history` (`trajectory_figure`),
    the records as plain dictionaries."""

    def plain(record: Any) -> dict[str, Any]:
        if isinstance(record, Mapping):
            return dict(record)
        out = {"index": record.index, "parameters": dict(record.parameters),
               "rolled_back": bool(getattr(record, "rolled_back", False))}  # fmt: skip
        if hasattr(record, "loss"):
            out["loss"] = record.loss
        return out

    return "trajectory", {"history": [plain(r) for r in history], "best": best}


def model_specs(
    model: ArmModel,
    v_max: float,
    title: str,
    unit: str,
    P_theta: Tensor | None,
    validation: Sequence[Experiment],
    scores: Mapping[str, SimulationScore],
) -> dict[str, Spec]:
    """A model's figures by TensorBoard tag: ``friction_curve`` (with the ±2σ band of
    `P_theta` when given) and, per validation record, ``validation/NAME`` (`response_spec`)
    and ``residuals/NAME`` (`residual_spec`) from its open-loop `scores`."""
    specs = {"friction_curve": friction_spec(model, v_max, title, unit, P_theta)}
    for e in validation:
        specs[f"validation/{e.name}"] = response_spec(e, scores[e.name], unit)
        specs[f"residuals/{e.name}"] = residual_spec(e, scores[e.name], unit)
    return specs


def friction_figure(
    model: ArmModel,
    v_max: float,
    title: str,
    unit: str = "rad",
    P_theta: Tensor | None = None,
) -> Any:
    """`friction_spec`'s figure."""
    return draw(*friction_spec(model, v_max, title, unit, P_theta))


def response_figure(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Any:
    """`response_spec`'s figure."""
    return draw(*response_spec(exp, score, unit))


def residual_figure(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Any:
    """`residual_spec`'s figure."""
    return draw(*residual_spec(exp, score, unit))
