"""The run's figures drawn from plain data (numpy arrays, numbers and text): no torch here, so a
helper process can draw them (`serve`, started by `torchfric.app.artifacts.painter`) while the
run goes on. This module imports nothing of torchfric: the helper loads it from its file.

`torchfric.app.artifacts.figures` turns a model, a record and its scores into the *specs* drawn
here (`draw`: a kind and a dict); `render` draws one to PNG bytes. Figures are matplotlib's,
off-screen, with fixed margins (`tight_layout` measured every label and cost as much as the
drawing).

`serve`'s frames: a request is an 8-byte length (`HEAD`) and a pickle of ``(id, kind, spec)``
(the parent's own data, to its own child); an answer is the id, a status byte (0: PNG, 1: an
error's text) and the payload's length (`ANSWER`), then the payload: the parent reads bytes,
never a pickle, from the helper.
"""

from __future__ import annotations

import io
import math
import os
import pickle
import struct
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import IO, Any

import numpy as np

__all__ = [
    "subplots",
    "pixels",
    "png_from_pixels",
    "png_bytes",
    "envelope",
    "autocorrelation",
    "whiteness_bound",
    "draw_friction",
    "draw_response",
    "draw_residuals",
    "trajectory_figure",
    "draw",
    "render",
    "serve",
    "read_exact",
    "HEAD",
    "ANSWER",
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


def png_bytes(fig: Any, dpi: int = 100) -> bytes:
    """`fig` as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


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


def draw_friction(spec: Mapping[str, Any]) -> Any:
    """The friction curve: ``v``, ``f`` (the model's friction over the velocities), ``band``
    (None, or the band's mean and 2σ half-width at ``v``), ``title``, ``force`` (its unit),
    ``v_label`` (the velocity axis's label) and ``offset`` (whether the model has one)."""
    v, f, band, force = spec["v"], spec["f"], spec["band"], spec["force"]
    if band is None:
        fig, ax = subplots(figsize=(6, 4))
        fig.subplots_adjust(left=0.15, right=0.97, bottom=0.12, top=0.92)
    else:  # a second panel with the band's width: readable however thin the band is
        fig, (ax, width) = subplots(
            2, 1, figsize=(6, 5.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
        )
        mean, two_sd = band
        ax.fill_between(v, mean - two_sd, mean + two_sd, color="C1", alpha=0.4, lw=0,
                        label=f"±2σ (at most ±{two_sd.max():.3g} {force})")  # fmt: skip
        width.plot(v, two_sd, color="C1")
        width.set_ylim(0.0, 1.1 * float(two_sd.max()) or 1.0)
        width.set_ylabel(f"2σ [{force}]")
        width.set_xlabel(spec["v_label"])
        width.grid(True, alpha=0.3)
        fig.subplots_adjust(left=0.15, right=0.97, bottom=0.1, top=0.93, hspace=0.08)
    ax.plot(v, f, color="C0", label="friction")
    if band is not None:
        # the curve sets the scale: a band that is wide where the data never went (a polytopic
        # model's outer slopes reached ±754 N on EMPS) is cut at the frame, not allowed to
        # flatten the curve into a line; its width is in the panel below
        span = float(f.max() - f.min()) or 1.0
        ax.set_ylim(float(f.min()) - 0.3 * span, float(f.max()) + 0.3 * span)
        ax.legend(loc="upper left")
    else:
        ax.set_xlabel(spec["v_label"])
    offset = " + offset" if spec["offset"] else ""
    ax.set_ylabel(f"friction b·q̇ + C(q̇){offset} [{force}]")
    ax.set_title(spec["title"])
    ax.grid(True, alpha=0.3)
    return fig


def draw_response(spec: Mapping[str, Any]) -> Any:
    """Measured against open-loop simulated q and q̇ of one record: ``t``, ``q``, ``q_sim``,
    ``qdot``, ``qdot_sim``, ``unit`` (of q), ``name``, ``fit_q`` and ``fit_qdot`` (%)."""
    t, unit = spec["t"], spec["unit"]
    fig, ax = subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].plot(*envelope(t, spec["q"]), label="measured")
    ax[0].plot(*envelope(t, spec["q_sim"]), "--", label="simulated")
    ax[0].set_ylabel(f"q [{unit}]")
    # a fixed corner: "best" tests every placement against every point drawn
    ax[0].legend(loc="upper right")
    ax[1].plot(*envelope(t, spec["qdot"]), label="reconstructed")
    ax[1].plot(*envelope(t, spec["qdot_sim"]), "--", label="simulated")
    ax[1].set_ylabel(f"q̇ [{unit}/s]")
    ax[1].set_xlabel("t [s]")
    ax[0].set_title(f"{spec['name']}: FIT q {spec['fit_q']:.1f} %, q̇ {spec['fit_qdot']:.1f} %")
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.1, top=0.93, hspace=0.08)
    return fig


def draw_residuals(spec: Mapping[str, Any]) -> Any:
    """Residuals (measured − simulated) of q and q̇ over time, and their autocorrelation over
    lags 0 … min(200, N/4) with the white-noise bounds ±1.96/√N: ``t``, ``e_q``, ``e_qdot``,
    ``unit`` (of q), ``name`` and ``dt`` (s)."""
    t, unit = spec["t"], spec["unit"]
    residuals = (("q", spec["e_q"], unit), ("q̇", spec["e_qdot"], f"{unit}/s"))
    n = t.shape[0]
    max_lag = max(1, min(200, n // 4))
    bound = whiteness_bound(n)
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
    ax[1, 1].set_xlabel(f"lag [samples of {spec['dt'] * 1e3:.3g} ms]")
    ax[0, 0].set_title(f"{spec['name']}: residuals, measured − simulated (open loop)", fontsize=10)
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.1, top=0.93, hspace=0.22, wspace=0.18)
    return fig


def _trajectory(spec: Mapping[str, Any]) -> Any:
    return trajectory_figure(spec["history"], spec["best"])


DRAWERS: dict[str, Callable[[Mapping[str, Any]], Any]] = {
    "friction": draw_friction,
    "response": draw_response,
    "residuals": draw_residuals,
    "trajectory": _trajectory,
}
"""The figure of each spec kind."""


def draw(kind: str, spec: Mapping[str, Any]) -> Any:
    """The matplotlib figure of the spec `spec` of `kind` (a key of `DRAWERS`)."""
    return DRAWERS[kind](spec)


def render(kind: str, spec: Mapping[str, Any]) -> bytes:
    """`draw`'s figure as PNG bytes: the pixels TensorBoard's ``add_figure`` would show
    (`pixels`), encoded once for TensorBoard and report.html alike."""
    return png_from_pixels(pixels(draw(kind, spec)))


HEAD = struct.Struct("<Q")
"""A request's frame header: the pickle's length."""
ANSWER = struct.Struct("<QBQ")
"""An answer's frame header: the figure's id, 0 (PNG) or 1 (an error's text), the length."""


def read_exact(stream: IO[bytes], n: int) -> bytes | None:
    """`n` bytes from `stream`, or None at its end."""
    data = bytearray()
    while len(data) < n:
        chunk = stream.read(n - len(data))
        if not chunk:
            return None
        data += chunk
    return bytes(data)


_WARM_UP: dict[str, Any] = {
    "v": np.linspace(-1.0, 1.0, 3), "f": np.zeros(3), "band": None, "title": "", "force": "",
    "v_label": "", "offset": False,
}  # fmt: skip


def serve() -> None:
    """The helper's loop: `render` each request from stdin to stdout until stdin closes, then
    leave at once (`os._exit`)."""
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    render("friction", _WARM_UP)  # matplotlib's import and its fonts, before the first request
    while (head := read_exact(stdin, HEAD.size)) is not None:
        payload = read_exact(stdin, HEAD.unpack(head)[0])
        if payload is None:
            break
        fid, kind, spec = pickle.loads(payload)
        try:
            data, status = render(kind, spec), 0
        except Exception as err:  # noqa: BLE001 - the parent draws it again and reports
            data, status = f"{type(err).__name__}: {err}".encode(), 1
        stdout.write(ANSWER.pack(fid, status, len(data)) + data)
        stdout.flush()
    os._exit(0)  # every answer is written: no teardown of matplotlib to wait for
