"""The run's figures (matplotlib, drawn off-screen): the friction curve with its ±2σ band, a
simulated response, its residuals and their autocorrelation, and the parameters over the passes.

Each returns a matplotlib figure (for TensorBoard's ``add_figure`` or `png_bytes`); positions
are in the SI unit that `data.position_unit` converts to. Margins are fixed: `tight_layout`
measured every label and cost as much as the drawing.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...data import Experiment
from ...data.units import force_unit, si_unit
from ...estimators.metrics import SimulationScore
from ...estimators.uncertainty import friction_band
from ...models.arm import ArmModel

__all__ = [
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
    "model_figures",
    "MAX_PANELS",
]

# At most this many parameters get a panel in `trajectory_figure` (the arm's first).
MAX_PANELS = 12
# The arm's physical parameters, shown before the friction curve's own elements.
_ARM_FIRST = ("inertia", "viscous", "offset", "gravity", "asymmetric", "c_m")


def subplots(*args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """A new off-screen figure and its axes, like ``pyplot.subplots`` but without pyplot: a
    bare `matplotlib.figure.Figure` on an Agg canvas (no global figure list to close, and no
    0.4 s pyplot import at the first figure)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=kwargs.pop("figsize", None))
    FigureCanvasAgg(fig)
    return fig, fig.subplots(*args, **kwargs)


def pixels(fig: Any) -> np.ndarray:
    """`fig` drawn to `(3, H, W)` uint8 RGB pixels, exactly as TensorBoard's ``add_figure``
    renders it (so ``add_image(tag, pixels(fig), step, dataformats="CHW")`` writes the same
    image). One drawing then serves TensorBoard and `png_from_pixels`."""
    fig.canvas.draw()
    w, h = fig.canvas.get_width_height()
    rgba = np.frombuffer(fig.canvas.buffer_rgba(), dtype=np.uint8).reshape(h, w, 4)
    return np.ascontiguousarray(np.moveaxis(rgba[:, :, :3], 2, 0))


def png_from_pixels(chw: np.ndarray) -> bytes:
    """`(3, H, W)` pixels (`pixels`) as PNG bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(np.moveaxis(chw, 0, 2))).save(buf, format="PNG")
    return buf.getvalue()


def model_figures(
    model: ArmModel,
    v_max: float,
    title: str,
    unit: str,
    P_theta: Tensor | None,
    validation: Sequence[Experiment],
    scores: Mapping[str, SimulationScore],
) -> dict[str, Any]:
    """A model's figures by TensorBoard tag: ``friction_curve`` (with the ±2σ band of
    `P_theta` when given) and, per validation record, ``validation/NAME`` (`response_figure`)
    and ``residuals/NAME`` (`residual_figure`) from its open-loop `scores`."""
    figs = {"friction_curve": friction_figure(model, v_max, title, unit, P_theta)}
    for e in validation:
        figs[f"validation/{e.name}"] = response_figure(e, scores[e.name], unit)
        figs[f"residuals/{e.name}"] = residual_figure(e, scores[e.name], unit)
    return figs


def png_bytes(fig: Any, dpi: int = 100) -> bytes:
    """`fig` as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def friction_figure(
    model: ArmModel,
    v_max: float,
    title: str,
    unit: str = "rad",
    P_theta: Tensor | None = None,
) -> Any:
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
    force = force_unit(unit)
    if band is None:
        fig, ax = subplots(figsize=(6, 4))
        fig.subplots_adjust(left=0.15, right=0.97, bottom=0.12, top=0.92)
    else:  # a second panel with the band's width: readable however thin the band is
        fig, (ax, width) = subplots(
            2, 1, figsize=(6, 5.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
        )
        mean, two_sd = band
        ax.fill_between(v.numpy(), mean - two_sd, mean + two_sd, color="C1", alpha=0.4, lw=0,
                        label=f"±2σ (at most ±{two_sd.max():.3g} {force})")  # fmt: skip
        width.plot(v.numpy(), two_sd, color="C1")
        width.set_ylim(0.0, 1.1 * float(two_sd.max()) or 1.0)
        width.set_ylabel(f"2σ [{force}]")
        width.set_xlabel(f"velocity q̇ [{si_unit(unit)}/s]")
        width.grid(True, alpha=0.3)
        fig.subplots_adjust(left=0.15, right=0.97, bottom=0.1, top=0.93, hspace=0.08)
    ax.plot(v.numpy(), f, color="C0", label="friction")
    if band is not None:
        # the curve sets the scale: a band that is wide where the data never went (a polytopic
        # model's outer slopes reached ±754 N on EMPS) is cut at the frame, not allowed to
        # flatten the curve into a line; its width is in the panel below
        span = float(f.max() - f.min()) or 1.0
        ax.set_ylim(float(f.min()) - 0.3 * span, float(f.max()) + 0.3 * span)
        ax.legend(loc="upper left")
    else:
        ax.set_xlabel(f"velocity q̇ [{si_unit(unit)}/s]")
    offset = " + offset" if "offset" in model.physical_parameters() else ""
    ax.set_ylabel(f"friction b·q̇ + C(q̇){offset} [{force}]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    return fig


def envelope(t: Any, y: Any, buckets: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """`(t, y)` thinned for drawing: each of `buckets` equal runs of samples becomes its minimum
    and its maximum, in time order, so that every peak a screen could show is kept. A record
    of ≤ 2·`buckets` samples is returned whole. (A 30 000-sample line drew in 50 ms; its
    envelope draws in a few, and looks the same at a figure's 800 pixels.)"""
    t, y = np.asarray(t), np.asarray(y)
    n = y.shape[0]
    if n <= 2 * buckets:
        return t, y
    edges = np.linspace(0, n, buckets + 1).astype(int)
    runs = list(zip(edges[:-1], edges[1:], strict=True))
    i_lo = np.array([a + int(np.argmin(y[a:b])) for a, b in runs])
    i_hi = np.array([a + int(np.argmax(y[a:b])) for a, b in runs])
    first = i_lo <= i_hi
    idx = np.empty(2 * buckets, dtype=int)
    idx[0::2] = np.where(first, i_lo, i_hi)
    idx[1::2] = np.where(first, i_hi, i_lo)
    return t[idx], y[idx]


def response_figure(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Any:
    """Measured against open-loop simulated q and q̇ of one record, titled with the FITs."""
    t = exp.t.numpy()
    fig, ax = subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].plot(*envelope(t, exp.q.numpy()), label="measured")
    ax[0].plot(*envelope(t, score.states[:, 0].numpy()), "--", label="simulated")
    ax[0].set_ylabel(f"q [{si_unit(unit)}]")
    # a fixed corner: "best" tests every placement against every point drawn
    ax[0].legend(loc="upper right")
    ax[1].plot(*envelope(t, _qdot(exp).numpy()), label="reconstructed")
    ax[1].plot(*envelope(t, score.states[:, 1].numpy()), "--", label="simulated")
    ax[1].set_ylabel(f"q̇ [{si_unit(unit)}/s]")
    ax[1].set_xlabel("t [s]")
    ax[0].set_title(f"{exp.name}: FIT q {score.fit_q:.1f} %, q̇ {score.fit_qdot:.1f} %")
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.1, top=0.93, hspace=0.08)
    return fig


def _qdot(exp: Experiment) -> Tensor:
    if exp.qdot is None:  # loaded records always have one (measured or reconstructed)
        raise ValueError(f"{exp.name}: no velocity to compare with; load it with load_data")
    return exp.qdot


def autocorrelation(x: Any, max_lag: int) -> np.ndarray:
    """Normalised autocorrelation ``r[k]``, k = 0 … `max_lag`, of the 1-D signal `x`.

    ``r[k] = Σ_n d[n] d[n+k] / Σ_n d[n]²`` with ``d = x − mean(x)`` (the biased estimate that
    whiteness tests use; r[0] = 1). Computed through the FFT, zero-padded so that it is the
    linear, not the circular, correlation. A constant signal has r = [1, 0, 0, …].
    """
    d = np.asarray(x, dtype=np.float64).reshape(-1)
    n = d.size
    if not isinstance(max_lag, int) or isinstance(max_lag, bool) or not 0 <= max_lag < n:
        raise ValueError(f"max_lag must be an integer in [0, {n - 1}], got {max_lag!r}")
    d = d - d.mean()
    energy = float(d @ d)
    if energy == 0.0:
        return np.eye(1, max_lag + 1).reshape(-1)
    size = 1 << (2 * n - 1).bit_length()
    spectrum = np.fft.rfft(d, size)
    acf = np.fft.irfft(spectrum * spectrum.conj(), size)[: max_lag + 1]
    return acf / energy


def whiteness_bound(n: int) -> float:
    """``1.96/√n``: white noise's autocorrelation at a lag ≥ 1 stays inside ± this with ≈ 95 %
    probability (n samples)."""
    return 1.96 / math.sqrt(n)


def residual_figure(exp: Experiment, score: SimulationScore, unit: str = "rad") -> Any:
    """Residuals (measured − simulated) of q and q̇ over time, and their autocorrelation over
    lags 0 … min(200, N/4) with the white-noise bounds ±1.96/√N."""
    t = exp.t.numpy()
    residuals = (
        ("q", exp.q.numpy() - score.states[:, 0].numpy(), si_unit(unit)),
        ("q̇", _qdot(exp).numpy() - score.states[:, 1].numpy(), f"{si_unit(unit)}/s"),
    )
    max_lag = max(1, min(200, exp.n // 4))
    bound = whiteness_bound(exp.n)
    lags = np.arange(max_lag + 1)
    fig, ax = subplots(2, 2, figsize=(10, 5.5), gridspec_kw={"width_ratios": [3, 2]})
    for row, (name, e, u) in enumerate(residuals):
        ax[row, 0].plot(*envelope(t, e), lw=0.8)
        ax[row, 0].set_ylabel(f"{name} residual [{u}]")
        ax[row, 0].grid(True, alpha=0.3)
        r = autocorrelation(e, max_lag)
        outside = float(np.mean(np.abs(r[1:]) > bound)) * 100.0
        ax[row, 1].axhspan(-bound, bound, color="C2", alpha=0.25, lw=0, label="±1.96/√N")
        ax[row, 1].vlines(lags, 0.0, r, color="C0", lw=1.0)
        ax[row, 1].axhline(0.0, color="k", lw=0.5)
        ax[row, 1].set_ylim(min(-0.2, float(r.min()) - 0.05), 1.05)
        ax[row, 1].set_title(f"{name}: {outside:.0f} % of lags 1–{max_lag} outside", fontsize=9)
        ax[row, 1].legend(loc="upper right", fontsize=8)
    ax[0, 0].sharex(ax[1, 0])
    ax[0, 0].tick_params(labelbottom=False)
    ax[0, 1].tick_params(labelbottom=False)
    ax[1, 0].set_xlabel("t [s]")
    ax[1, 1].set_xlabel(f"lag [samples of {exp.dt * 1e3:.3g} ms]")
    ax[0, 0].set_title(f"{exp.name}: residuals, measured − simulated (open loop)", fontsize=10)
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.1, top=0.93, hspace=0.22, wspace=0.18)
    return fig


def _field(record: Any, name: str, default: Any = None) -> Any:
    if isinstance(record, Mapping):
        return record.get(name, default)
    return getattr(record, name, default)


def trajectory_figure(history: Sequence[Any], best: int | None = None) -> Any:
    """Each physical parameter over the passes (or epochs) of `history`, one panel each.

    `history` holds records with ``index`` and ``parameters`` (`PassRecord`, `EpochRecord` or
    their dictionaries). At most `MAX_PANELS` panels: the arm's parameters first (inertia,
    viscous, …), then the friction curve's elements in order; the rest of a large network's
    weights are left out (the title says how many; TensorBoard has them all). `best`, the
    kept pass or epoch, is marked in every panel, and a pass that was undone (rolled back) by
    a grey cross."""
    from matplotlib.ticker import MaxNLocator

    if not history:
        raise ValueError("history is empty: no pass or epoch to draw")
    steps = np.array([int(_field(r, "index")) for r in history])
    params = [_field(r, "parameters") for r in history]
    undone = np.array([bool(_field(r, "rolled_back", False)) for r in history])
    names = list(params[-1])
    ordered = [n for n in _ARM_FIRST if n in names] + [n for n in names if n not in _ARM_FIRST]
    shown = ordered[:MAX_PANELS]
    first = history[0]
    what = (
        "epoch"
        if ("loss" in first if isinstance(first, Mapping) else hasattr(first, "loss"))
        else "pass"
    )
    cols = min(4, len(shown))
    rows = math.ceil(len(shown) / cols)
    fig, axes = subplots(rows, cols, figsize=(2.6 * cols + 0.6, 2.0 * rows + 0.9), squeeze=False)
    for ax, name in zip(axes.flat, shown, strict=False):
        values = np.array([float(p.get(name, math.nan)) for p in params])
        ax.plot(steps, values, "-o", ms=3, lw=1.2)
        if undone.any():
            ax.plot(steps[undone], values[undone], "x", color="0.4", ms=7, mew=1.5)
        if best is not None and best in steps:
            ax.axvline(best, color="C3", ls="--", lw=1.0)
            ax.plot([best], values[steps == best][:1], "o", color="C3", ms=6)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
        # few ticks: each is a handful of artists, and eight panels' ticks were most of the
        # figure's drawing time
        ax.xaxis.set_major_locator(MaxNLocator(nbins=5, integer=True))
        ax.yaxis.set_major_locator(MaxNLocator(nbins=4))
        ax.yaxis.get_offset_text().set_fontsize(7)
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(shown) :]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel(what, fontsize=8)
    left_out = len(ordered) - len(shown)
    plural = "epochs" if what == "epoch" else "passes"
    title = f"parameters over the {plural}"
    if best is not None:
        title += f" (kept: {what} {best}, " + (
            "dashed)" if best in steps else "the starting values)" if best == 0 else "not shown)"
        )
    if left_out:
        title += f"; {left_out} more friction weights not shown"
    fig.suptitle(title, fontsize=10)
    height = 2.0 * rows + 0.9
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.5 / height, top=1 - 0.5 / height,
                        hspace=0.6, wspace=0.35)  # fmt: skip
    return fig
