"""``report.html``: one self-contained page per run that any browser opens without a server.

The figures are inline PNGs (``data:`` URIs) and the style is inline CSS: no script, no link to
anything outside the file. It shows the run at a glance (estimator, convergence, the kept
pass), the warnings, the parameters as value ± σ, the validation FITs, and the figures: the
friction curve with its ±2σ band, each validation record's simulation against measurement and
its residuals with their autocorrelation, and the parameters over the passes. Every text that
comes from the user (names, paths, warnings) is HTML-escaped.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import math
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

from torch import Tensor

from ...data import Experiment
from ...estimators.metrics import SimulationScore
from ...estimators.uncertainty import SIGMA_SOURCES
from ...files import atomic_write_text
from ...models.arm import ArmModel
from ...models.lugre import CLASS_NAMES
from .figures import (
    friction_figure,
    png_bytes,
    residual_figure,
    response_figure,
    trajectory_figure,
)

__all__ = ["write_report", "report_html", "parameter_rows"]

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1040px; color: #222;
       padding: 0 1em; line-height: 1.4; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
table { border-collapse: collapse; margin: 0.5em 0 1em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.7em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
th { background: #f2f2f2; }
.warn { background: #fff3cd; border: 2px solid #e0a800; padding: 0.6em 1em; margin: 1em 0; }
.warn h2 { border: none; margin: 0.2em 0; color: #8a5a00; }
.ok { color: #1a7f37; } .bad { color: #b42318; font-weight: bold; }
.note { color: #555; font-size: 0.92em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { color: #555; font-size: 0.92em; }
"""


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _num(value: Any, fmt: str) -> str:
    """A number as text, or "–" when it is missing or not finite."""
    if value is None or isinstance(value, bool):
        return "–"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "–"
    return format(v, fmt) if math.isfinite(v) else "–"


def parameter_rows(parameters: Mapping[str, Any]) -> list[tuple[str, float, float | None]]:
    """``(name, value, std)`` from metrics' "parameters": either ``{name: value}`` or
    ``{name: {"value": v, "std": s}}`` (std None or missing: not known)."""
    rows = []
    for name, entry in parameters.items():
        if isinstance(entry, Mapping):
            std = entry.get("std")
            rows.append((str(name), float(entry["value"]), None if std is None else float(std)))
        else:
            rows.append((str(name), float(entry), None))
    return rows


def _figure(fig: Any, caption: str) -> str:
    """A figure inline: a matplotlib figure, or PNG bytes drawn before (`png_from_pixels`)."""
    png = fig if isinstance(fig, bytes) else png_bytes(fig)
    data = base64.b64encode(png).decode("ascii")
    return (
        f'<figure><img alt="{_e(caption)}" src="data:image/png;base64,{data}">'
        f"<figcaption>{_e(caption)}</figcaption></figure>"
    )


_CHOSEN_BY = {
    "identification": "open-loop FIT on the identification records (validation held out)",
    "validation": "validation FIT (so validation is not held out)",
    "likelihood": "innovation likelihood",
    "last_epoch": "the last epoch (validation held out)",
}
"""metrics.json's ``selected_on`` in words: what chose the kept pass (estimator.select)."""


def _summary(metrics: Mapping[str, Any], title: str, created: dt.datetime) -> str:
    converged = metrics.get("converged")
    if converged is None:
        conv = "–"
    else:
        conv = '<span class="ok">yes</span>' if converged else '<span class="bad">no</span>'
    epochs = "epochs" in metrics and "passes" not in metrics
    best = metrics.get("best_epoch" if epochs else "best_pass")
    rows = [
        ("run", _e(metrics.get("name", title))),
        ("date", _e(created.strftime("%Y-%m-%d %H:%M:%S"))),
        ("estimator", _e(metrics.get("estimator", "–"))),
        ("started from", _e(metrics.get("init", "–"))),
        ("epochs" if epochs else "passes", _e(metrics.get("epochs" if epochs else "passes", "–"))),
        ("converged", conv),
        (f"kept {'epoch' if epochs else 'pass'}", _e("–" if best is None else best)),
        ("chosen by", _e(_CHOSEN_BY.get(metrics.get("selected_on", ""), "–"))),
        ("time", f"{_num(metrics.get('seconds'), '.1f')} s"),
    ]
    body = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _warnings(metrics: Mapping[str, Any]) -> str:
    warnings = list(metrics.get("warnings") or [])
    if not warnings:
        return '<p class="ok">No warnings.</p>' + _identifiability(metrics)
    items = "".join(f"<li>{_e(w)}</li>" for w in warnings)
    block = f'<div class="warn"><h2>Warnings ({len(warnings)})</h2><ul>{items}</ul></div>'
    return block + _identifiability(metrics)


def _identifiability(metrics: Mapping[str, Any]) -> str:
    """The parameters the data cannot separate, one line per group (metrics.json's
    ``identifiability``; those with a white-box parameter are among the warnings too)."""
    lines = (metrics.get("identifiability") or {}).get("messages") or []
    if not lines:
        return ""
    items = "".join(f"<li>{_e(m)}</li>" for m in lines)
    return f"<h2>Identifiability</h2><ul>{items}</ul>"


def _parameters(metrics: Mapping[str, Any]) -> str:
    rows, table = [], parameter_rows(metrics.get("parameters") or {})
    for name, value, std in table:
        rel = "–" if std is None or value == 0 else _num(100.0 * std / abs(value), ".2g") + " %"
        sd = "–" if std is None else _num(std, ".3g")
        rows.append(
            f"<tr><td>{_e(name)}</td><td class='num'>{_num(value, '.6g')} ± {sd}</td>"
            f"<td class='num'>{rel}</td></tr>"
        )
    head = "<tr><th>parameter</th><th>value ± σ</th><th>σ / |value|</th></tr>"
    known = any(std is not None for _, _, std in table)
    unknown = any(std is None for _, _, std in table)
    method = (metrics.get("covariance") or {}).get("method")
    missing = ""  # what a "–" means: a run with a covariance gives none to some parameters
    if unknown:
        missing = (
            "–: no σ: the data do not determine it, or it is held at its bound (Identifiability)."
            if known
            else "–: not known (no covariance was computed for this run)."
        )
    source = SIGMA_SOURCES.get(method or "filter", SIGMA_SOURCES["filter"])
    said = f"σ: {_e(source)} (docs/estimators.md, Uncertainty). " if known else ""
    note = f'<p class="note">{said}{missing}</p>'
    return f"<table>{head}{''.join(rows)}</table>{note}"


def _fits(metrics: Mapping[str, Any]) -> str:
    rows = []
    for group in ("validation", "test", "identification"):
        for name, m in (metrics.get(group) or {}).items():
            rows.append(
                f"<tr><td>{group}</td><td>{_e(name)}</td>"
                f"<td class='num'>{_num(m.get('fit_q'), '.2f')}</td>"
                f"<td class='num'>{_num(m.get('fit_qdot'), '.2f')}</td>"
                f"<td class='num'>{_num(m.get('rms_q'), '.4g')}</td>"
                f"<td class='num'>{_num(m.get('rms_qdot'), '.4g')}</td></tr>"
            )
    if not rows:
        return (
            '<p class="bad">No validation data: the model was checked on the identification '
            "data only. Add held-out records as data.validation.</p>"
        )
    head = (
        "<tr><th>set</th><th>record</th><th>FIT q [%]</th><th>FIT q̇ [%]</th>"
        "<th>RMS q</th><th>RMS q̇</th></tr>"
    )
    note = (
        '<p class="note">FIT = 100 (1 − ‖y − ŷ‖ / ‖y − mean(y)‖) of the open-loop simulation '
        "from the record's first state; 100 % is a perfect match.</p>"
    )
    if not metrics.get("validation"):
        note += (
            '<p class="bad">No validation data: the identification records\' own FIT is shown, '
            "and it flatters the model. Add held-out records as data.validation.</p>"
        )
    return f"<table>{head}{''.join(rows)}</table>{note}"


def _sizes(metrics: Mapping[str, Any]) -> str:
    """The table of sizes of ``model.size = "auto"`` (metrics' ``sizes``); "" without one."""
    sizes = metrics.get("sizes")
    if not sizes:
        return ""
    rows = []
    for r in sizes["table"]:
        mark = '<span class="ok">chosen</span>' if r["chosen"] else ""
        member = "–" if r["member"] < 0 else f"Q ×{r['q_scale']:g}, R ×{r['r_scale']:g}"
        rows.append(
            f"<tr><td class='num'>{_e(r['size'])}</td><td class='num'>{_e(r['parameters'])}</td>"
            f"<td class='num'>{_num(r['loglik'], '.1f')}</td>"
            f"<td class='num'>{_num(r['bic'], '.1f')}</td><td>{_e(member)}</td>"
            f"<td class='num'>{_e(r['diverged'])} of {_e(r['members'])}</td><td>{mark}</td></tr>"
        )
    head = (
        "<tr><th>size</th><th>k</th><th>log-likelihood ℓ</th><th>BIC</th><th>best filter</th>"
        "<th>diverged</th><th></th></tr>"
    )
    note = (
        f'<p class="note">model.size = "auto" ({_e(sizes.get("friction", ""))}): every size was '
        "identified by the EKF and scored on the identification data by BIC = −2 ℓ + k ln N "
        f"(N = {_e(sizes['samples'])} samples, k parameters), where ℓ is the log-likelihood of "
        "the one-step innovations of a filter pass with θ held fixed, maximised over a common "
        "scale of the noise model; the lowest BIC is kept and trained as the run's model.</p>"
    )
    return f"<h2>Model size</h2><table>{head}{''.join(rows)}</table>{note}"


def _cut(dyn: Mapping[str, Any]) -> str:
    """The excerpts a long record's comparison was made on (``dynamics.excerpts``), or ""."""
    cut = dyn.get("excerpts")
    if not cut:
        return ""
    return (
        f" ({cut['records']} excerpts spread over it: {cut['samples']:,} of its {cut['of']:,} "
        "samples)"
    )


def _dynamics(metrics: Mapping[str, Any]) -> str:
    """The comparison of ``model.dynamic = "auto"`` (metrics' ``dynamics``); "" without one."""
    dyn = metrics.get("dynamics")
    if not dyn:
        return ""
    gain = dyn["gain"]  # (not finite when LuGre diverged: shown as –)
    rows = []
    for r in dyn["table"]:
        mark = '<span class="ok">chosen</span>' if r["chosen"] else ""
        rows.append(
            f"<tr><td>{_e(CLASS_NAMES.get(r['dynamic'], r['dynamic']))}</td>"
            f"<td class='num'>{_e(r['parameters'])}</td><td class='num'>{_num(r['rmse_q'], '.4g')}</td>"
            f"<td class='num'>{_num(r['bic'], '.1f')}</td>"
            f"<td class='num'>{_e(r['diverged'])} of {_e(r['members'])}</td><td>{mark}</td></tr>"
        )
    head = (
        "<tr><th>friction</th><th>k</th><th>RMS position error, held out</th>"
        "<th>BIC (not used)</th><th>diverged</th><th></th></tr>"
    )
    note = (
        f'<p class="note">model.dynamic = "auto": both classes were identified on the first '
        f"{1 - dyn['holdout']:.0%} of each identification record{_e(_cut(dyn))}; each then "
        f"predicted the last "
        f"{dyn['holdout']:.0%} in {_e(dyn['windows'])} open-loop windows of "
        f"{dyn['window_seconds']:g} s, each started from its own filter's estimate. LuGre's "
        f"mean squared error was {_num(100 * abs(gain), '.1f')} % "
        f"{'lower' if gain >= 0 else 'higher'}, "
        f"{_num(dyn['t'], '.1f')} standard errors of the paired difference; LuGre is kept only "
        f"above {dyn['t_min']:g} (a tie keeps the simpler static model), and only if its "
        f"bristles travel at least one position step through a reversal: 2 g(0)/σ0 = "
        f"{_num(dyn.get('bristle_travel', math.nan), '.3g')} against "
        f"{_num(dyn.get('position_step', math.nan), '.3g')} (a travel below the encoder's step "
        "is the limit σ0 → ∞, a static model that sticks), and less than the records' position "
        f"span of {_num(dyn.get('position_span', math.inf), '.3g')} (beyond it the bristles "
        "never slide: σ0 → 0, a spring); and only if the axis stuck on its bristles settles "
        f"slowly enough for the samples to see it: {_num(dyn.get('stick_rate', math.nan), '.3g')}"
        f" /s × the sample time {_num(dyn.get('sample_time', math.nan), '.3g')} s at most "
        f"{_num(dyn.get('stick_rate_limit', math.nan), 'g')} (faster is σ0 → ∞ in time). "
        "The one-step BIC is shown but not "
        "used: the bristle state's extra freedom raises the filter's likelihood on static "
        "machines too.</p>"
    )
    return f"<h2>Friction class</h2><table>{head}{''.join(rows)}</table>{note}"


def _figures(
    model: ArmModel,
    P_theta: Tensor | None,
    history: Sequence[Any],
    validation: Sequence[Experiment],
    scores: Mapping[str, SimulationScore],
    unit: str,
    v_max: float,
    best: int | None,
    what: str,
    images: Mapping[str, bytes],
) -> str:
    """The figures' sections; a figure in `images` (PNG by TensorBoard tag) is not drawn again."""

    def drawn(tag: str, draw: Any, *args: Any) -> Any:
        return images[tag] if tag in images else draw(*args)

    band = "with its ±2σ band" if P_theta is not None else "(no covariance: no band)"
    parts = [
        "<h2>Friction curve</h2>",
        _figure(
            drawn(
                "friction_curve",
                friction_figure,
                model,
                v_max,
                "identified friction",
                unit,
                P_theta,
            ),
            f"total friction of the final model {band}",
        ),
        "<h2>Validation</h2>",
    ]
    if not validation:
        parts.append('<p class="bad">No validation data: nothing to simulate against.</p>')
    for e in validation:
        score = scores[e.name]
        parts.append(f"<h3>{_e(e.name)}</h3>")
        response = drawn(f"validation/{e.name}", response_figure, e, score, unit)
        parts.append(_figure(response, f"{e.name}: simulated vs measured"))
        parts.append(
            _figure(
                drawn(f"residuals/{e.name}", residual_figure, e, score, unit),
                f"{e.name}: residuals and their autocorrelation (white residuals stay "
                "inside the shaded bounds)",
            )
        )
    plural = "passes" if what == "pass" else "epochs"
    parts.append(f"<h2>Parameters over the {plural}</h2>")
    if history:
        caption = f"each parameter after every {what}; the kept one marked (red, dashed)"
        parts.append(_figure(drawn("trajectory", trajectory_figure, history, best), caption))
    else:
        parts.append("<p>No pass history.</p>")
    return "".join(parts)


def report_html(
    *,
    title: str,
    model: ArmModel,
    metrics: Mapping[str, Any],
    history: Sequence[Any],
    validation: Sequence[Experiment],
    scores: Mapping[str, SimulationScore],
    v_max: float,
    unit: str = "rad",
    P_theta: Tensor | None = None,
    created: dt.datetime | None = None,
    images: Mapping[str, bytes] | None = None,
) -> str:
    """The run's report as one self-contained HTML page (figures inline as PNG, no scripts).

    Args:
        title: the run's name (the page's heading).
        model: the final model; `P_theta` `(k, k)` its θ covariance in estimation coordinates
            (the EKF's; None for output error: no band).
        metrics: the run's ``metrics.json`` content ("parameters" either ``{name: value}`` or
            ``{name: {"value", "std"}}``; "validation"/"test" FITs; "warnings"; "converged",
            "best_pass" or "best_epoch" when known).
        history: the passes' or epochs' records (`PassRecord`, `EpochRecord` or their dicts).
        validation: the validation records, and `scores` their open-loop scores by name.
        v_max: the friction curve's velocity range ±v_max; `unit` the data's position unit.
        created: the date shown (default now).
        images: figures already drawn, as PNG by TensorBoard tag (``friction_curve``,
            ``validation/NAME``, ``residuals/NAME``; see
            `torchfric.app.artifacts.figures.model_specs`) and ``trajectory``
            (`trajectory_spec` of `history`): used as they are instead of drawn again.
    """
    created = created or dt.datetime.now()
    best = metrics.get("best_pass", metrics.get("best_epoch"))
    what = "epoch" if "epochs" in metrics and "passes" not in metrics else "pass"
    figures = _figures(
        model, P_theta, history, validation, scores, unit, v_max, best, what, images or {}
    )
    return (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>{_e(title)} · torchfric report</title><style>{_STYLE}</style></head><body>"
        f"<h1>{_e(title)}</h1>{_summary(metrics, title, created)}{_warnings(metrics)}"
        f"{_sizes(metrics)}{_dynamics(metrics)}<h2>Parameters</h2>{_parameters(metrics)}"
        f"<h2>Fit</h2>{_fits(metrics)}{figures}"
        "</body></html>\n"
    )


def write_report(path: str | pathlib.Path, **content: Any) -> None:
    """Write the run's report (`report_html` of `content`) to `path`, atomically."""
    atomic_write_text(path, report_html(**content))
