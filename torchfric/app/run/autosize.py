"""``model.size = "auto"`` and ``model.dynamic = "auto"``: the run's friction size and class,
chosen from its identification data.

Size:

`choose_size` runs before the run proper (`torchfric.app.run.runner`, ``_Run.prepare``; it writes
nothing): it builds the starting model of every candidate size (``model.sizes``, by default
`AUTO_SIZES`) the way a run builds its own (`config_model`, `initial_model`: the pre-fit or the
config's values), hands them to `torchfric.estimators.sizing.compare_sizes` with the run's EKF
tuning and ensemble grid, and returns the config with the chosen size, which the run then trains
like any other. The table of sizes goes into ``metrics.json`` (key ``sizes``), ``report.html``
and the summary (`size_lines`).

The run's own ``config.toml`` keeps ``size = "auto"`` (what was asked; ``--resume`` compares
it); the checkpoint's model has the chosen size. A resumed run chooses again, the same way (the
same size and table), before it continues from its snapshot.

Class (after the size, which is chosen for the static model):

`choose_dynamic` runs before the run proper (`torchfric.app.run.runner`, ``_Run.prepare``, after
``model.size = "auto"``, which sizes the static model; it writes nothing). It builds the static
and the LuGre model of the config the way a run builds its start (`config_model`,
`initial_model`), from the first 70 % of every identification record only, and hands them to
`torchfric.estimators.sizing.compare_dynamics`: both are identified there with the run's
tuning and ensemble, and each predicts the held-out last 30 % in open-loop windows of 0.05 s
started from its own filter. LuGre is kept only when its windows predict the position better
by more than two standard errors and its bristles travel at least one position step through a
reversal (``2 g(0)/σ0``; stiffer bristles are, for this record, the limit σ0 → ∞: a static
model that sticks) and less than the records' position span (softer ones never slide in the
record: σ0 → 0, a spring and a damper), and the axis stuck on them settles slowly enough for
the samples to see it (`stick_rate` × the sample time ≤ 1; faster is σ0 → ∞ in time);
otherwise the static model is kept. The run then trains the chosen
class on the whole records like any other run. The comparison goes into ``metrics.json`` (key
``dynamics``), ``report.html`` and the summary (`dynamic_lines`).

The run's own ``config.toml`` keeps ``dynamic = "auto"``; the checkpoint's model has the chosen
class. A resumed run chooses again, the same way, before it continues from its snapshot.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

from ...estimators.sizing import (
    HOLDOUT,
    WINDOW_SECONDS,
    compare_dynamics,
    compare_sizes,
    held_out_heads,
    nests,
)
from ...models.lugre import CLASS_NAMES, bristles_seen, bristles_timed
from ...resources import ekf_bytes, fewest_passes, require_memory
from ..config import AUTO_SIZES, Config
from .inputs import RunEstimate, check_resources, config_model, estimate_run, initial_model

__all__ = [
    "auto_estimate",
    "choose_dynamic",
    "choose_size",
    "choose_size_and_start",
    "candidate_sizes",
    "dynamic_lines",
    "size_lines",
    "sized",
    "with_dynamic",
]


def candidate_sizes(cfg: Config) -> tuple[int, ...]:
    """The sizes ``model.size = "auto"`` tries: ``model.sizes``, else the friction's default."""
    return tuple(cfg.model.sizes) or AUTO_SIZES[cfg.model.friction]


def sized(cfg: Config, size: int) -> Config:
    """`cfg` with ``model.size = size`` (and no ``model.sizes``)."""
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, size=size, sizes=()))


def choose_size(
    cfg: Config, train: list[Any], say: Callable[[str], None] | None = None
) -> tuple[Config, dict[str, Any] | None]:
    """`cfg` with its size chosen from the identification records `train`, and the table of
    sizes (`SizingResult.to_dict`); `cfg` itself and None when ``model.size`` is an integer
    (`choose_size_and_start` without the start)."""
    return choose_size_and_start(cfg, train, say)[:2]


def choose_size_and_start(
    cfg: Config,
    train: list[Any],
    say: Callable[[str], None] | None = None,
    *,
    device: Any = None,
) -> tuple[Config, dict[str, Any] | None, tuple[Any, str] | None]:
    """`choose_size`, and the chosen size's start (`initial_model`'s model and kind, already
    built for the comparison, so a run need not pre-fit it again); None when ``model.size`` is
    an integer. `device`: a CUDA `torch.device` filters the sizes there (None: the CPU).

    Raises `TorchfricError` before any filter runs when a size's model or the batch of all
    sizes' filters does not fit in memory, and when every filter of every size diverges."""
    if cfg.model.size != "auto":
        return cfg, None, None
    say = say or (lambda _: None)
    sizes = candidate_sizes(cfg)
    starts = {}
    for size in sizes:
        one = sized(cfg, size)
        base = config_model(one, train)
        check_resources(one, train, base)
        starts[size] = initial_model(one, train, base)
    est = cfg.estimator
    spec = est.ensemble_spec(cfg.seed) if est.ensemble > 0 else None
    per_size = spec.size if spec is not None else 1
    models = {size: start[0] for size, start in starts.items()}
    batched = len(sizes) > 1 and nests(models)
    filters = per_size * (len(sizes) if batched else 1)
    largest = max(m.num_parameters for m in models.values())
    require_memory(
        ekf_bytes(largest, filters),
        f'model.size = "auto": {filters} filters of up to {largest} parameters',
        "give model.sizes fewer or smaller sizes, or lower estimator.ensemble",
    )
    how = "in one batch" if batched else "size by size"
    listed = ", ".join(map(str, sizes))
    say(
        f'  model.size = "auto": {cfg.model.friction} sizes {listed} ({per_size} filter(s) '
        f"each, {how}); the lowest BIC on the identification data's innovations is kept"
    )
    result = compare_sizes(models, train, est.ekf_tuning(), spec, device=device).to_dict()
    result["friction"] = cfg.model.friction
    for line in size_lines(result):
        say("  " + line)
    return sized(cfg, result["chosen"]), result, starts[result["chosen"]]


def size_lines(sizes: Mapping[str, Any]) -> list[str]:
    """The table of sizes (metrics' ``sizes``) as text lines: the summary's and the progress
    output's."""
    kind = f"{sizes['friction']} " if sizes.get("friction") else ""
    lines = [
        f"model size {kind}{sizes['chosen']} chosen by BIC = −2 ℓ + k ln N on the fixed-θ "
        f"innovations (N = {sizes['samples']}, {sizes['seconds']:.1f} s; lowest wins):",
        f"  {'size':>4}  {'k':>3}  {'log-likelihood ℓ':>16}  {'BIC':>14}",
    ]
    for row in sizes["table"]:
        ll_text = _cell(row["loglik"], 16, ".1f", "diverged")
        mark = "  ← chosen" if row["chosen"] else ""
        lines.append(
            f"  {row['size']:>4}  {row['parameters']:>3}  {ll_text}  "
            f"{_cell(row['bic'], 14, '.1f', '–')}{mark}"
        )
    return lines


def _cell(value: float, width: int, fmt: str, missing: str) -> str:
    """`value` right-aligned in `width` characters, or `missing` when it is not finite."""
    return f"{value:{width}{fmt}}" if math.isfinite(value) else f"{missing:>{width}}"


def with_dynamic(cfg: Config, dynamic: str) -> Config:
    """`cfg` with ``model.dynamic = dynamic``."""
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, dynamic=dynamic))


def choose_dynamic(
    cfg: Config,
    train: list[Any],
    say: Callable[[str], None] | None = None,
    *,
    device: Any = None,
) -> tuple[Config, dict[str, Any] | None]:
    """`cfg` with its friction class chosen from the identification records `train`, and the
    comparison (`DynamicsResult.to_dict`); `cfg` itself and None unless ``model.dynamic`` is
    "auto". `device`: a CUDA `torch.device` filters the ensembles there (None: the CPU)."""
    if cfg.model.dynamic != "auto":
        return cfg, None
    say = say or (lambda _: None)
    excerpts = comparison_heads(train)
    heads = held_out_heads(train, HOLDOUT)
    whole = sum(h.n for h in heads)
    ident = heads if excerpts is None else excerpts
    used = sum(h.n for h in ident)
    starts = {}
    for dynamic in ("none", "lugre"):
        one = with_dynamic(cfg, dynamic)
        base = config_model(one, ident)
        check_resources(one, ident, base)
        starts[dynamic] = initial_model(one, ident, base)[0]
    est = cfg.estimator
    spec = est.ensemble_spec(cfg.seed) if est.ensemble > 0 else None
    say(
        f'  model.dynamic = "auto": static and LuGre friction identified on the first '
        f"{1 - HOLDOUT:.0%} of each record{_excerpts(len(ident), used, whole)}, each "
        f"predicting the last {HOLDOUT:.0%} in "
        f"{WINDOW_SECONDS:g}-s open-loop windows; LuGre is kept if it predicts better by > 2 σ "
        "and its bristles travel more than a position step and less than the records' span, "
        "slowly enough for the samples to see"
    )
    result = compare_dynamics(
        starts["none"], starts["lugre"], train, est.ekf_tuning(), spec, device=device,
        heads=excerpts,
    ).to_dict()  # fmt: skip
    if used < whole:
        result["excerpts"] = {"records": len(ident), "samples": used, "of": whole}
    for line in dynamic_lines(result):
        say("  " + line)
    return with_dynamic(cfg, result["chosen"]), result


def auto_estimate(cfg: Config, train: list[Any], lugre: RunEstimate, *, timed: bool) -> RunEstimate:
    """The time of a ``model.dynamic = "auto"`` run (``torchfric check``): both classes'
    ensembles on what `choose_dynamic` identifies them on (`comparison_heads`' excerpts, else
    the first 70 % of each record), then the kept class on all of it; from the static model
    after the fewest passes to the LuGre model after every pass. `lugre`: `estimate_run` of the
    LuGre model (the slower filter, the larger peak); the static filter is timed here from the
    config's unfitted start (its rate does not depend on θ; a timing that fails falls back on
    the nominal rate, as `estimate_run` does). The comparison's windows and pre-fits on the
    excerpts are left out: seconds on the records we measured (docs/results.md)."""
    if lugre.seconds is None or lugre.rate is None:  # output error: no time to add to
        return lugre
    static_cfg = with_dynamic(cfg, "none")
    static = estimate_run(static_cfg, train, config_model(static_cfg, train), timed=timed)
    if static.seconds is None or not static.rate:
        return lugre
    heads = comparison_heads(train) or held_out_heads(train, HOLDOUT)
    compared = sum(h.n for h in heads)
    passes = cfg.estimator.passes
    # one pass of both classes' ensembles over the compared samples
    both = lugre.members * compared * (1 / static.rate + 1 / lugre.rate)
    seconds = (
        static.seconds[0] + fewest_passes(passes) * both,
        lugre.seconds[1] + passes * both,
    )
    return dataclasses.replace(lugre, seconds=seconds, static_rate=static.rate, compared=compared)


COMPARE_SAMPLES = 100_000  # records up to this many samples in all: identified whole
COMPARE_PIECES = 4  # excerpts of each record's identification part beyond that


def comparison_heads(train: list[Any], budget: int = COMPARE_SAMPLES) -> list[Any] | None:
    """What `choose_dynamic` identifies both classes on: None (`compare_dynamics` cuts the first
    70 % of each record itself) up to `budget` samples in all, so every record up to 100 s at
    1 kHz is compared as before, bit for bit; beyond, `COMPARE_PIECES` excerpts of each
    record's first 70 %, evenly spread from its start to its end, of its share of 70 % of the
    budget. The held-out windows stay the whole last 30 % of every record, all of them (excerpts
    that held out their own ends would keep a third); only the two classes' identification, the
    comparison's cost (static and LuGre ensembles, 0.25 ms a sample on the 2-core machine of
    docs/results.md), is bounded. The verdict then moves with the data the candidates were
    identified on, as it does with the window length (docs/results.md, "Long records")."""
    if sum(e.n for e in train) <= budget:
        return None
    heads = held_out_heads(train, HOLDOUT)
    total = sum(h.n for h in heads)
    pieces = []
    for h in heads:
        length = int((1 - HOLDOUT) * budget * h.n / total) // COMPARE_PIECES
        if length * COMPARE_PIECES >= h.n or length < 1000:
            pieces.append(h)  # short records stay whole
            continue
        gap = (h.n - length) / max(COMPARE_PIECES - 1, 1)
        pieces += [h.slice(round(j * gap), round(j * gap) + length) for j in range(COMPARE_PIECES)]
    return pieces


def _excerpts(records: int, used: int, whole: int) -> str:
    """`dynamic_lines`' note of the excerpts identified on (`comparison_heads`), or ""."""
    if used >= whole:
        return ""
    return f" ({records} excerpts: {used:,} of its {whole:,} samples)"


def dynamic_lines(dynamics: Mapping[str, Any]) -> list[str]:
    """The comparison of friction classes (metrics' ``dynamics``) as text lines: the summary's
    and the progress output's."""
    chosen = CLASS_NAMES.get(dynamics["chosen"], dynamics["chosen"])
    lines = [
        f"friction class {chosen} chosen by open-loop prediction of held-out data: "
        f"{dynamics['windows']} windows of {dynamics['window_seconds']:g} s in the last "
        f"{dynamics['holdout']:.0%} of the records ({dynamics['seconds']:.1f} s):",
        f"  {'class':<7} {'k':>3}  {'RMS q error':>12}  {'BIC (for reference)':>20}",
    ]
    cut = dynamics.get("excerpts")
    if cut:  # a long record's (`comparison_heads`)
        lines.insert(1, f"  both identified on the first {1 - dynamics['holdout']:.0%} of "
                     f"each record{_excerpts(cut['records'], cut['samples'], cut['of'])}")  # fmt: skip
    for row in dynamics["table"]:
        rmse_text = _cell(row["rmse_q"], 12, ".4g", "diverged")
        mark = "  ← chosen" if row["chosen"] else ""
        name = CLASS_NAMES.get(row["dynamic"], row["dynamic"])
        lines.append(
            f"  {name:<7} {row['parameters']:>3}  {rmse_text}  "
            f"{_cell(row['bic'], 20, '.1f', '–')}{mark}"
        )
    t = dynamics["t"]
    t_text = f"{t:.1f}" if math.isfinite(t) else ("+∞" if t > 0 else "−∞")
    gain = dynamics["gain"]
    how = f"{abs(gain):.1%} {'lower' if gain >= 0 else 'higher'}" if math.isfinite(gain) else "–"
    lines.append(
        f"  LuGre's windows: mean squared error {how} than static's, {t_text} standard errors "
        f"of the difference (LuGre is kept above {dynamics['t_min']:g})"
    )
    return lines + _bristle_lines(dynamics, t, gain)


def _bristle_lines(dynamics: Mapping[str, Any], t: float, gain: float) -> list[str]:
    """`dynamic_lines`' lines on LuGre's bristles: their travel against the records' step and
    span, how fast the axis settles on them against the sample time, and a hint where LuGre
    predicted better than static yet was not kept."""
    travel, step = dynamics.get("bristle_travel"), dynamics.get("position_step")
    if travel is None or step is None:
        return []
    span = dynamics.get("position_span", math.inf)
    seen = bristles_seen(travel, step, span)
    why = (
        "" if seen
        else ": they never slide within the records (σ0 → 0: a spring, not friction)"
        if not travel < span
        else ": at the fitted σ0 the record cannot tell σ0 from ∞ (static); this is the fit's "
        "travel, which a fit whose σ0 ran away shares with a machine without bristles"
    )  # fmt: skip
    lines = [
        f"  LuGre's bristles travel 2 g(0)/σ0 = {travel:.3g} through a reversal, "
        f"{travel / step:.2g} position steps of {step:.3g} (kept from 1 step up to the "
        f"records' span of {span:.3g}){why}"
    ]
    rate, dt = dynamics.get("stick_rate"), dynamics.get("sample_time")
    timed = rate is None or dt is None or bristles_timed(rate, dt)
    if rate is not None and dt is not None:
        lines.append(
            f"  stuck on them, the axis settles at {rate:.3g} /s, {rate * dt:.2g} per sample "
            f"(kept up to {dynamics['stick_rate_limit']:g})"
            + ("" if timed else ": over within a sample, σ0 → ∞ in time (static)")
        )
    if dynamics["chosen"] != "none" or not seen or not gain > 0 or not math.isfinite(t):
        return lines
    if not timed and t > dynamics["t_min"]:  # the record is too slow for these bristles
        lines.append(
            "  LuGre predicted better, with bristles that settle within a sample: if the "
            "machine may be dynamic, record it faster, or train once with model.dynamic = "
            '"lugre" and compare the two on validation data'
        )
    elif timed:  # the windows' blind spot (docs/results.md: a LuGre spindle)
        lines.append(
            "  LuGre predicted better, though not by 2 σ, with bristles the encoder sees: "
            'if the machine may be dynamic, train once with model.dynamic = "lugre" and '
            "compare the two on validation data"
        )
    return lines
