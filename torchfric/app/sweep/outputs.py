"""What a sweep writes and prints: ``trials.csv``, ``best.toml``, ``sweep.png`` and the summary.

- ``trials.csv``: one row per trial of the study (all of them: earlier runs', other machines'),
  by number: ``number, state, score, duration_s``, one column per ``[space]`` key (arrays as
  their TOML text), then ``pruned_at`` (the pass after which the pruner stopped it), ``error``
  (a failed trial's message) and ``run_dir``. ``score`` is the objective of a complete trial;
  of a pruned one, the last score it reported (per pass, of the same kind; an ensemble's is
  its best member's log-likelihood); empty for a failed one.
- ``best.toml``: the best complete trial's whole config, written by `torchfric.app.config.toml_io`,
  with comments naming the trial; its paths are absolute, so ``torchfric train DIR/best.toml``
  runs it from any folder.
- ``sweep.png``: the objective against each parameter (complete trials; the best marked).
"""

from __future__ import annotations

import csv
import io
import math
import pathlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ...files import atomic_write_bytes, atomic_write_text
from ..artifacts import png_bytes
from ..config import toml_value
from .space import Param

if TYPE_CHECKING:
    from .trial import SweepSpec

__all__ = [
    "SCORE_LABELS",
    "SweepResult",
    "best_config",
    "score_figure",
    "summary_lines",
    "trial_rows",
    "write_outputs",
]

SCORE_LABELS = {
    "validation_fit": "validation FIT [%]",
    "loglik": "identification log-likelihood",
    "identification_fit": "identification FIT [%]",
}


@dataclass
class SweepResult:
    """A finished sweep: the study's trials as rows (`torchfric.app.sweep.outputs.trial_rows`),
    the best one, what this run added, and the files written."""

    out: pathlib.Path
    study: str
    storage: str
    kind: str
    params: tuple[Param, ...]
    rows: list[dict[str, Any]]
    best: dict[str, Any] | None
    added: int
    seconds: float
    files: dict[str, str]


def trial_rows(study: Any, params: tuple[Param, ...]) -> list[dict[str, Any]]:
    """The study's trials as plain rows (see the module's ``trials.csv``), by number."""
    rows = []
    for t in sorted(study.get_trials(deepcopy=False), key=lambda t: t.number):
        state = t.state.name
        score = t.value if state == "COMPLETE" else None
        if state == "PRUNED" and t.intermediate_values:
            score = t.intermediate_values[max(t.intermediate_values)]
        took = None
        if t.datetime_start is not None and t.datetime_complete is not None:
            took = (t.datetime_complete - t.datetime_start).total_seconds()
        rows.append({
            "number": t.number, "state": state, "score": score, "duration_s": took,
            "values": {p.key: p.value(t.params[p.key]) for p in params if p.key in t.params},
            "pruned_at": t.user_attrs.get("pruned_at"), "error": t.user_attrs.get("error"),
            "run_dir": t.user_attrs.get("run_dir"),
        })  # fmt: skip
    return rows


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | tuple | dict | bool):
        return toml_value(value)
    return str(value)


def csv_text(rows: list[dict[str, Any]], params: tuple[Param, ...]) -> str:
    """``trials.csv``'s text."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    keys = [p.key for p in params]
    w.writerow(["number", "state", "score", "duration_s", *keys, "pruned_at", "error", "run_dir"])
    for r in rows:
        cells = [r["number"], r["state"], r["score"], r["duration_s"]]
        cells += [r["values"].get(k) for k in keys]
        cells += [r["pruned_at"], r["error"], r["run_dir"]]
        w.writerow([_cell(c) for c in cells])
    return buf.getvalue()


def best_config(spec: SweepSpec, best: dict[str, Any]) -> str:
    """``best.toml``: the base config with the best trial's values, as TOML with a header."""
    from .trial import OBJECTIVES, values_text

    sets = [f"{k}={toml_value(v)}" for k, v in best["values"].items()]
    cfg = spec.base().with_overrides(sets)
    head = [
        f"# The best trial of the sweep in {spec.out}: trial {best['number']}, score "
        f"{best['score']:.6g}",
        f"# (objective: {OBJECTIVES[spec.kind]}).",
        f"# Its values: {values_text(best['values'])}",
        f"# Its run: {best['run_dir']}",
        f"# Train it again with: torchfric train {pathlib.Path(spec.out) / 'best.toml'}",
        "",
    ]
    return "\n".join(head) + cfg.to_toml()


def _axis_values(p: Param, rows: list[dict[str, Any]]) -> tuple[list[float], list[str] | None]:
    """x positions of `rows` for parameter `p`, and tick labels for choices."""
    if p.choices is None:
        return [float(r["values"][p.key]) for r in rows], None
    labels = [toml_value(c) for c in p.choices]
    return [float(labels.index(toml_value(r["values"][p.key]))) for r in rows], labels


def _space_axis(ax: Any, p: Param, labels: list[str] | None) -> None:
    """The x axis spans the parameter's whole range (log for a log range) or its choices."""
    from matplotlib.ticker import NullFormatter

    if labels is not None:
        ax.set_xticks(range(len(labels)), labels, rotation=30 if len(labels) > 4 else 0)
        ax.set_xlim(-0.5, len(labels) - 0.5)
    elif p.log:
        ax.set_xscale("log")
        ax.set_xlim(p.low / 1.2, p.high * 1.2)
        ax.xaxis.set_minor_formatter(NullFormatter())
    else:
        pad = 0.04 * (p.high - p.low)
        ax.set_xlim(p.low - pad, p.high + pad)


def score_figure(
    rows: list[dict[str, Any]], params: tuple[Param, ...], kind: str, title: str
) -> Any:
    """The objective against each parameter: one panel per ``[space]`` key, complete trials
    as dots, the best one as a star. A bare matplotlib Figure on an Agg canvas (no pyplot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    done = [
        r for r in rows
        if r["state"] == "COMPLETE" and r["score"] is not None and math.isfinite(r["score"])
        and all(p.key in r["values"] for p in params)
    ]  # fmt: skip
    best = max(done, key=lambda r: r["score"]) if done else None
    cols = min(3, len(params))
    nrows = math.ceil(len(params) / cols)
    fig = Figure(figsize=(4.2 * cols, 3.4 * nrows))
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, cols, squeeze=False).ravel()
    for ax, p in zip(axes, params, strict=False):
        x, labels = _axis_values(p, done)
        ax.scatter(x, [r["score"] for r in done], s=22, color="C0", label="complete trial")
        if best is not None:
            bx, _ = _axis_values(p, [best])
            ax.scatter(bx, [best["score"]], s=140, marker="*", color="C3", label="best", zorder=3)
        _space_axis(ax, p, labels)
        ax.set_xlabel(p.key)
        ax.set_ylabel(SCORE_LABELS[kind])
        ax.grid(True, alpha=0.3)
    for ax in axes[len(params) :]:
        ax.set_visible(False)
    if done:
        axes[0].legend(loc="best", fontsize="small")
    fig.suptitle(title)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.16, top=0.86, wspace=0.3, hspace=0.5)
    return fig


def write_outputs(
    study: Any, spec: SweepSpec
) -> tuple[list[dict[str, Any]], dict[str, Any] | None, dict[str, str]]:
    """Write ``trials.csv``, ``best.toml`` (when a trial completed) and ``sweep.png`` into the
    sweep's folder; returns the rows, the best row and the files by label."""
    out = pathlib.Path(spec.out)
    rows = trial_rows(study, spec.params)
    done = [r for r in rows if r["state"] == "COMPLETE" and r["score"] is not None]
    best = max(done, key=lambda r: (r["score"], -r["number"])) if done else None
    files = {"trials": str(out / "trials.csv")}
    atomic_write_text(out / "trials.csv", csv_text(rows, spec.params))
    if best is not None:
        atomic_write_text(out / "best.toml", best_config(spec, best))
        files["best config"] = str(out / "best.toml")
    counts = _counts(rows)
    title = f"sweep {spec.study}: {counts['COMPLETE']} complete, {counts['PRUNED']} pruned, " + (
        f"{counts['FAIL']} failed"
    )
    fig = score_figure(rows, spec.params, spec.kind, title)
    atomic_write_bytes(out / "sweep.png", png_bytes(fig), what="the sweep figure")
    files["figure"] = str(out / "sweep.png")
    files["runs"] = str(out / "trials")
    return rows, best, files


def _counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    counts = dict.fromkeys(("COMPLETE", "PRUNED", "FAIL", "RUNNING", "WAITING"), 0)
    for r in rows:
        counts[r["state"]] = counts.get(r["state"], 0) + 1
    return counts


def summary_lines(result: SweepResult) -> list[str]:
    """The summary ``torchfric sweep`` prints on stdout."""
    from .study import hide_password
    from .trial import OBJECTIVES, values_text

    c = _counts(result.rows)
    running = f", {c['RUNNING']} running elsewhere" if c["RUNNING"] else ""
    lines = [
        f"sweep {result.study}: {len(result.rows)} trials in the study: {c['COMPLETE']} done, "
        f"{c['PRUNED']} pruned, {c['FAIL']} failed{running} (this run finished {result.added} "
        f"in {result.seconds:.1f} s)",
        f"objective   {OBJECTIVES[result.kind]}",
    ]
    if result.best is None:
        lines.append("best        none: no trial completed (see the errors in trials.csv)")
    else:
        b = result.best
        lines.append(f"best        trial {b['number']}: {b['score']:.6g}")
        lines.append(f"            {values_text(b['values'])}")
    for label, path in result.files.items():
        lines.append(f"{label:<12}{path}")
    if "best config" in result.files:
        lines.append(f"train it    torchfric train {result.files['best config']}")
    storage = hide_password(result.storage)
    lines.append(f"study       {storage}")
    lines.append(f"browse it   optuna-dashboard {storage}")
    return lines
