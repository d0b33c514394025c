"""``torchfric init DATA --c-m VALUE``: a commented starter config for a user's data file.

`write_starter` reads the file with the project's readers (`read_columns`, `load_segments`:
every check a run makes on a record; which columns are ours and the units:
`torchfric.app.commands.columns`) and writes a config only once it has passed `check_run`.

- Format: a CSV's delimiter (comma, semicolon, tab, space) and decimal comma are sniffed by
  the reader; anything but plain commas and points gets a note.
- Columns: ours (t, u, q, qdot) by name or a common alternative in English, German, French,
  Spanish or Italian (`ALIASES`: ``Zeit``, ``Strom``, ``Stellgröße``, ``Winkel``, …), without
  case, accents and a unit (``Time [s]``, ``t/ms``, ``pos_deg``); our own name wins. Two
  candidates, or none for t, u or q, stop with the header and the line to write.
- Sample time: a unit in t's name (``Zeit [ms]``) is written as ``time_unit`` and applied at
  load. The t column's step (uniform to the loader's 1e-3, gaps aside), or ``--time-step``,
  that still looks like milliseconds is refused, not worked around: a step of `MS_STEP` (0.5 s,
  2 Hz) or more always, a step of 0.05 s or more when the data check finds q or qdot moving as
  if sampled much faster. Any other rate too slow for the 200 Hz velocity filter gets
  ``velocity_cutoff_hz`` = 0.4 × Nyquist.
- Gaps: rows missing or with empty/NaN fields cut the record into segments (train reads them
  so too); the note says which lines.
- Units of q: a unit in the column's name sets ``position_unit`` (one torchfric does not read
  is refused), ``--position-unit`` where the name states none. Encoder counts (by the name,
  or whole numbers only) become ``"counts"`` with ``--counts-per-rev``/``--counts-per-m``, or
  with the wrap period of a q that wraps; counts with neither are refused. A q that wraps gets
  ``wrap_period``. Otherwise q is taken as rad (or m), with a note when a speed above
  `FAST_SPEED` units/s suggests degrees.
- Model: the white-box terms (``offset``, ``gravity``, ``asymmetric``) are written commented
  out, each with when to turn it on.
- Validation: ``data.start``/``stop`` apply to every file, so one file cannot be split by
  sample ranges. ``--split F`` (only when asked) writes its first fraction F and the rest as two
  new CSV files beside the config; otherwise a record beside the data named as its held-out
  record (``run1_train`` ↔ ``run1_val`` or ``run1_test``, ``identification`` ↔ ``validation``,
  ``train`` ↔ ``test``) with the same columns and sample time is proposed as validation, or a
  comment says how to add one; with both a validation- and a test-named record, the test one
  goes to ``data.test``. Nothing is replaced: not the data, not a split file; the config only
  with ``--force``.

Why this size: one plan, read top to bottom (the file → columns, units, split → the commented
config text it writes); the header's column mapping is apart, in `columns`.
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
import re
import textwrap
from collections.abc import Mapping, Sequence

import numpy as np

from ...data import DEFAULT_CUTOFF_HZ, Experiment, load_segments
from ...data.lab import counter_time, reading_notes, sniff_format
from ...data.readers import FILE_TYPES, TEXT_TYPES, read_columns, save_csv
from ...data.units import POSITION_UNITS
from ...errors import TorchfricError
from ...files import atomic_write_text
from ...models.friction import FRICTIONS
from ...version import __version__
from ..config import MAX_NAME, Config, EstimatorConfig, ModelConfig, toml_value
from .check import check_run
from .columns import (
    PositionGuess,
    map_columns,
    named_file,
    noisy_cutoff,
    parse_c_m,
    parse_columns,
    parse_counts,
    position_unit_guess,
    refuse_milliseconds,
    slow_cutoff,
    split_record,
    terms_found,
    time_unit_of,
)
from .pairs import held_out_siblings

__all__ = ["cmd_init", "write_starter"]


# ------------------------------------------------------------------------------------ the text
def _comment(*comment: str) -> list[str]:
    """`comment` wrapped as ``#`` lines."""
    text = " ".join(c for c in comment if c)
    return textwrap.wrap(text, 96, initial_indent="# ", subsequent_indent="# ") if text else []


def _block(key: str, value: object, *comment: str, active: bool = True) -> list[str]:
    """`comment` wrapped as ``#`` lines, then ``key = value`` (commented out unless `active`)."""
    return [*_comment(*comment), ("" if active else "# ") + f"{key} = {toml_value(value)}"]


def _rel(path: pathlib.Path, folder: pathlib.Path) -> str:
    """`path` relative to the config's `folder` (how `Config.load` reads it), else absolute."""
    try:
        return os.path.relpath(path, folder)
    except ValueError:  # another drive
        return str(path)


class _Plan:
    """What init found and decided; `text` writes it as the commented config."""

    def __init__(self, data: pathlib.Path, out: pathlib.Path, c_m: float) -> None:
        self.data, self.out, self.folder, self.c_m = data, out, out.parent, c_m
        # the run is named after the config (`--out my_axis.toml` → runs/my_axis/), which by
        # default is named after the data file
        stem = re.sub(r"[^A-Za-z0-9._+-]+", "_", out.stem).lstrip("._+-")[:MAX_NAME]
        self.name = stem or "run"
        self.mapping: dict[str, str] = {}
        self.time_step: float | None = None
        self.notes: list[str] = []
        self.train: list[pathlib.Path] = [data]
        self.validation: list[pathlib.Path] = []
        self.test: list[pathlib.Path] = []
        self.others: list[pathlib.Path] = []
        self.splits: dict[pathlib.Path, Experiment] = {}
        self.split = ""
        self.segments: list[Experiment] = []
        self.time_unit = "s"
        self.counter: str | None = None  # how t came from the file's sample counter
        self.q_given: dict[str, object] = {}  # --counts-per-rev/-m, --position-unit
        self.position = PositionGuess("rad", "")
        self.cutoff: float | None = None
        self.noisy: tuple[float, float] | None = None  # (noise share, quieter cut-off)
        self.terms: dict[str, tuple[float | None, str]] = {}  # `terms_found`

    def _validation(self) -> list[str]:
        val = [_rel(p, self.folder) for p in self.validation]
        if self.split or val:
            return _block("validation", val, _HELP["validation"], "" if self.split else _FOUND)
        others = [_rel(p, self.folder) for p in self.others]
        named = f" (named like one, beside the data: {', '.join(others)})" if others else ""
        none = _NONE.format(named=named, data=self.data.name)
        return _block(
            "validation", others or ["second.csv"], _HELP["validation"], none, active=False
        )

    def _test(self) -> list[str]:
        if not self.test:
            return []
        test = [_rel(p, self.folder) for p in self.test]
        return _block("test", test, _HELP["test"], _FOUND)

    def _data(self) -> list[str]:
        units = ", ".join(f'"{u}"' for u in POSITION_UNITS)
        lines = ["[data]", *_block("train", [_rel(p, self.folder) for p in self.train],
                                   self.split, _HELP["train"]), *self._validation(),
                 *self._test()]  # fmt: skip
        if self.mapping:
            lines += _block("columns", self.mapping, _HELP["columns"])
        if self.time_step is not None:
            lines += _block("time_step", self.time_step, "Sample time [s]: the file has no t.")
        if self.time_unit != "s":
            why = f"Unit of t in the file: {self.time_unit}, from its column name (t becomes s)."
            lines += _block("time_unit", self.time_unit, why)
        pos = self.position
        unit = f"Unit of q in the file: {units} (q becomes rad or m); {pos.why}."
        lines += _block("position_unit", pos.unit, unit, pos.hint)
        if pos.counts_per_rev:
            lines += _block("counts_per_rev", pos.counts_per_rev, _HELP["counts_per_rev"])
        if pos.counts_per_m:
            lines += _block("counts_per_m", pos.counts_per_m, _HELP["counts_per_m"])
        if pos.wrap_period:
            lines += _block("wrap_period", pos.wrap_period, _HELP["wrap_period"])
        lines += _block("velocity", "highpass", _HELP["velocity"])
        why = f"The velocity filter's cut-off [Hz], below Nyquist ({0.5 / self.exp.dt:g} Hz)."
        if self.cutoff is not None:
            why += " Set to 0.4 × Nyquist: the default 200 Hz is too fast for this sampling."
        if self.noisy:
            noisy = _NOISY.format(self.cutoff or DEFAULT_CUTOFF_HZ["highpass"], *self.noisy)
            why += f" {noisy[0].upper()}{noisy[1:]}."
        cutoff = self.noisy[1] if self.noisy else self.cutoff
        lines += _block(
            "velocity_cutoff_hz", cutoff or DEFAULT_CUTOFF_HZ["highpass"], why, active=bool(cutoff)
        )
        delay = self.terms.get("input_delay")
        if delay:
            note = f"{delay[1][0].upper()}{delay[1][1:]}."
            lines += _block("input_delay", int(delay[0]), _HELP["input_delay"], note)
        n = sum(e.n for e in self.segments) if len(self.segments) > 1 else self.exp.n
        return lines + _block("stop", n, _HELP["stop"], active=False)

    def text(self) -> str:
        exp, out = self.exp, self.out.name
        # saturation "auto": 6 static, 3 LuGre (`torchfric.app.run.inputs.saturation_floor`)
        model = ModelConfig(c_m=self.c_m, dynamic="auto", saturation="auto")
        est = EstimatorConfig()
        head = [
            f"# Starter config for {self.data.name}, by `torchfric init` (torchfric {__version__})",
            f"#   torchfric check {out}    what a run would do (checks all, writes nothing)",
            f"#   torchfric train {out}    identify the model, in runs/{self.name}/",
            "# Every key, its default and allowed values: docs/config.md in the torchfric source.",
            f"# {self.data.name}: {_samples(self)}, dt = {exp.dt:.6g} s ({1 / exp.dt:.6g} Hz, "
            f"uniform to {self.jitter:.2g} of a step).",
            *[f"# Note: {n}" for n in self.notes],
            "",
            *_block("name", self.name, _HELP["name"]),
            *_block("seed", 0, _HELP["seed"]),
            "",
            *self._data(),
            "",
            "[model]",
        ]
        keys = ("friction", "size", "saturation", "dynamic", "c_m", "init", "inertia", "viscous")
        for key in keys:
            head += _block(key, getattr(model, key), _HELP.get(key, ""))
        head += _comment(_TERMS_HELP)
        for key, example, why in _TERMS:
            found = self.terms.get(key, (None, ""))[0]
            head += _block(key, example if found is None else found, why, active=found is not None)
        head += ["", "[estimator]"]
        for key in ("method", "select", "passes", "tolerance", "substeps", "ensemble"):
            value = "auto" if key == "substeps" else getattr(est, key)
            head += _block(key, value, _HELP.get(key, ""))
        return "\n".join(head) + "\n"


_NOISY = (
    "the velocity reconstructed from q's steps at {0:g} Hz carries noise of {1:.1%} of its "
    "95th-percentile speed (a coarse encoder), which biases the filter: velocity_cutoff_hz = "
    "{2:g} Hz, where it carries 1 %"
)
_TERMS_HELP = (
    "White-box terms, each off until you remove the # before its line; the number is the "
    'initial guess (init = "prefit" fits it from the data).'
)
_TERMS = (
    ("offset", 0.0, "A constant force or torque (gravity on a tilted linear axis, a "
     "cable, an amplifier offset); try it when the simulation drifts one way (EMPS needs it)."),
    ("gravity", 0.1, "g_c·sin q of an unbalanced rotating arm (g_c = m·g·l > 0, q in "
     "rad or deg, 0 hanging straight down); for an arm that swings back when let go."),
    ("asymmetric", 0.0, "a·|q̇|, viscous slope b + a forwards and b − a backwards; "
     "try it when the machine runs faster one way than the other under the same input."),
)  # fmt: skip
"""[model] keys written commented out: (key, example value, when to turn it on)."""
_FOUND = (
    "Found beside the data file, named as its held-out record (validation or test), with the "
    "same columns and sample time: remove the line if it is not a record of this machine."
)
_NONE = (
    "None yet: a run is then scored on its own identification data, which says little about the "
    "model. Name a second record of this machine (another input signal) here{named}, or rerun "
    "init with --split 0.7 to hold out the last 30 % of {data} (written as two new files beside "
    "this config)."
)
_HELP = {
    "saturation": 'tanh: each neuron\'s input weight >= saturation / v95. "auto": 6 for a '
    "static model (saturated by v95/2: b is the curve's slope there, where a slower neuron "
    "takes part of it on machines that stick), 3 for LuGre, whose bristles hold the stick.",
    "dynamic": '"auto": static friction and LuGre bristle dynamics (stick, pre-sliding, '
    "hysteresis) are both identified on the first 70 % of the records; LuGre is kept only if it "
    "predicts the held-out rest better and its bristles move the encoder slowly enough for the "
    'samples to see (the summary shows both). "none" or "lugre" fixes the '
    "class and skips the comparison (on a 60-s record 5 s of a 15-s run, 14 s of a first run's "
    "33 s: benchmarks/first_run.py).",
    "train": "Identification records (paths relative to this file); every pass uses all of them.",
    "validation": "Other runs' records: their open-loop FIT keeps the pass (estimator.select).",
    "test": "Held-out records scored once, at the end; they pick nothing.",
    "columns": "Our name = the file's: t time [s], u input, q position, qdot velocity (optional).",
    "velocity": 'q̇ for the estimator: "highpass" (the paper\'s causal differentiator), '
    '"zero_phase" (off-line) or "measured" (the file\'s qdot column).',
    "stop": "Use samples start <= k < stop of every file (also: start = 0).",
    "input_delay": "Whole samples by which the input acts late (sample k is driven by "
    "u[k − input_delay]).",
    "counts_per_rev": "Encoder counts per revolution (q becomes rad); counts_per_m for a "
    "linear axis.",
    "counts_per_m": "Encoder counts per metre (q becomes m).",
    "wrap_period": "q wraps at this value (in position_unit): each record is unwrapped at load.",
    "name": "The run: directory out_dir/name (out_dir: runs, relative to where train runs), "
    "checkpoint name.pt.",
    "seed": "Seeds the random parts (ensemble starts, output-error batches).",
    "friction": "Friction curve C(q̇): " + ", ".join(f'"{f}"' for f in FRICTIONS) + ".",
    "size": "Neurons (tanh) or local models (polytopic: odd).",
    "c_m": "The motor constant: torque (N·m) or force (N) per unit of u, in M q̈ = c_m·u − "
    "b·q̇ − C(q̇). It is given, not estimated (estimate_c_m = false): from u and q alone it "
    "cannot be, since c_m, M, b and C scaled by one factor give the same q. It sets the units "
    "of every estimated parameter.",
    "init": 'The start: "prefit" (least squares on the identification data), "config" (the '
    "guesses below) or a checkpoint.",
    "inertia": 'Initial guesses of M and b for init = "config".',
    "method": '"ekf" (the paper\'s iterative augmented-state EKF) or "output_error" '
    "(simulation-error training).",
    "select": 'What keeps the pass and ensemble member: "validation" (the validation records, '
    "with the identification records; their FIT is then not held out: a test record is) or "
    '"identification" (those alone: validation is held out; on a third record neither rule '
    "kept the better models everywhere: docs/results.md).",
    "passes": "EKF passes over the data, at most; they stop, converged, once a pass raises the "
    "innovation log-likelihood by less than `tolerance` nats per parameter (0: never).",
    "substeps": 'RK4 steps per sample in the filter: "auto", the fewest that keep it stable on '
    "the model's steepest friction (raised as the passes steepen it, at most 16), or a number "
    "(1: the paper's); a filter that cannot follow a stiff model biases it (docs/results.md).",
    "ensemble": "1: the start under 3 Q × 3 R tunings (9 filters), the best kept; 0: one "
    "filter, the paper's method.",
}


# ------------------------------------------------------------------------------------ writing
def _out_path(data: pathlib.Path, out: str | os.PathLike[str] | None, force: bool) -> pathlib.Path:
    target = pathlib.Path(f"{data.stem}.toml" if out is None else out).absolute()
    if target.suffix.lower() in FILE_TYPES or target.resolve() == data.resolve():
        raise TorchfricError(
            f"--out {target} names a data file; init writes a config: give a .toml file name"
        )
    if target.is_dir():
        raise TorchfricError(f"--out {target} is a folder; give a .toml file name")
    if target.exists() and not force:
        raise TorchfricError(
            f"{target} exists; give another name with --out, or --force to replace it"
        )
    if not target.parent.is_dir():
        raise TorchfricError(f"--out {target}: the folder {target.parent} does not exist")
    return target


def _units(plan: _Plan) -> dict[str, object]:
    """The loader's unit arguments as the config will give them."""
    return {"time_unit": plan.time_unit, "wrap_period": plan.position.wrap_period}


def _read(plan: _Plan, columns: Mapping[str, str], time_step: float | None) -> None:
    """Columns, the record, its sample time and the units of t and q into `plan`."""
    data = plan.data
    table = read_columns(data)
    plan.mapping = map_columns(table, columns, data, time_step is not None)
    plan.read_as = dict(plan.mapping)
    plan.time_step = time_step if "t" not in plan.mapping else None
    counted = counter_time(table, plan.time_step) if plan.time_step else None
    plan.counter = counted[1] if counted else None
    fmt = sniff_format(data)[0] if data.suffix.lower() in TEXT_TYPES else None
    clock = fmt.clock if fmt else ()
    with named_file(data):  # the units' messages name the file
        plan.time_unit = time_unit_of(plan.mapping, clock) if plan.time_step is None else "s"
    exps, notes = load_segments(data, columns=plan.mapping, time_step=time_step,
                                time_unit=plan.time_unit, wrap_period=math.inf)  # fmt: skip
    plan.segments = exps
    plan.exp = exp = max(exps, key=lambda e: e.n)
    refuse_milliseconds(exp, plan.mapping.get("t"), data)
    parts = [e.q.numpy() for e in exps]
    with named_file(data):
        plan.position = position_unit_guess(
            plan.mapping["q"], parts, exp.dt, plan.out.name, **plan.q_given
        )
    plan.notes += reading_notes(data.name, fmt, plan.mapping["u"])
    if plan.time_unit != "s":
        plan.notes.append(
            f"t in {plan.time_unit} (column {plan.mapping['t']!r}): data.time_unit = "
            f'"{plan.time_unit}" converts it to s at load'
        )
    plan.notes += plan.position.notes + notes
    steps = np.concatenate([np.diff(e.t.numpy()) for e in exps])
    plan.jitter = float(np.max(np.abs(steps - np.median(steps))) / np.median(steps))
    plan.cutoff = slow_cutoff(exp.dt)
    if "qdot" not in plan.mapping:  # a coarse encoder's steps: a quieter velocity
        start = plan.cutoff or DEFAULT_CUTOFF_HZ["highpass"]
        plan.noisy = noisy_cutoff(exp.q.numpy(), exp.dt, start, plan.position.wrap_period)
        if plan.noisy:
            plan.notes.append(_NOISY.format(start, *plan.noisy))
    plan.terms = terms_found(plan.segments, plan.c_m, plan.position)
    plan.notes += [note for _, note in plan.terms.values()]


def _propose_validation(plan: _Plan, split: float | str | None) -> None:
    if split is None:
        plan.validation, plan.test, plan.others = held_out_siblings(
            plan.data, plan.mapping, plan.time_step, plan.exp.dt, _units(plan)
        )
        return
    try:
        fraction = float(split)
    except ValueError:
        fraction = math.nan
    if not 0 < fraction < 1:
        raise TorchfricError(
            f"--split {split}: expected the identification part's fraction, between 0 and 1, "
            "e.g. --split 0.7 (the first 70 % identify, the last 30 % validate)"
        )
    if len(plan.segments) > 1 or plan.time_unit != "s" or plan.position.wrap_period:
        raise TorchfricError(
            f"--split {split}: {plan.data.name} is not a whole record in s (gaps, t in "
            f"{plan.time_unit} or a wrapping q); init splits only plain records: give a second "
            "record as validation instead (see the comment in the config without --split)"
        )
    plan.splits = split_record(plan.exp, fraction, plan.folder, plan.data.stem)
    plan.train, plan.validation = list(plan.splits)[:1], list(plan.splits)[1:]
    k = plan.splits[plan.train[0]].n
    plan.split = (
        f"--split {fraction:g}: samples 0 … {k - 1} of {plan.data.name} identify, the other "
        f"{plan.exp.n - k} validate (written by init as the two files below)"
    )
    plan.mapping, plan.time_step = {}, None  # the new files name t, u, q (and qdot)


def _write(plan: _Plan, force: bool) -> list[str]:
    """Write the split files (if any) and the config once the config passes `check_run`;
    a failure removes what this call wrote. Returns the data warnings."""
    text, found, written = plan.text(), [], []
    try:
        for path, part in plan.splits.items():
            save_csv(path, part)
            written.append(path)
        cfg = Config.loads(text, base_dir=plan.folder, source=str(plan.out))
        check_run(cfg, warnings=found)
        if plan.out.exists() and not force:
            raise TorchfricError(f"{plan.out} appeared meanwhile; init leaves it as it is")
        atomic_write_text(plan.out, text)
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise
    return found


def write_starter(
    data: str | os.PathLike[str],
    *,
    c_m: float | str | None,
    out: str | os.PathLike[str] | None = None,
    force: bool = False,
    split: float | str | None = None,
    columns: Mapping[str, str] | Sequence[str] = (),
    time_step: float | None = None,
    counts_per_rev: float | None = None,
    counts_per_m: float | None = None,
    position_unit: str | None = None,
) -> list[str]:
    """Write a commented starter config for the record `data`; returns what to tell the user.

    Args:
        data: the user's record (.csv; .npz and .mat read too).
        c_m: the motor constant (required; a string from the command line is parsed).
        out: the config file (default ``<data stem>.toml`` in the working directory); never
            replaced unless `force`.
        split: identification fraction: write the record's first part and the rest as two new
            CSV files beside the config, for identification and validation.
        columns: our name → the file's (a mapping, or ``"q=NAME"`` strings), where the names
            do not tell.
        time_step: sample time in s for a file without a time column.
        counts_per_rev, counts_per_m: q is in encoder counts, so many per revolution (rotary)
            or per metre (linear).
        position_unit: q's unit (`POSITION_UNITS`) where its column name states none, or one
            torchfric does not read; a name that states a known unit must agree.
    """
    c = parse_c_m(c_m)
    path = pathlib.Path(data).absolute()
    if not path.is_file():
        raise TorchfricError(f"{data}: no such file; give the path of your data file (CSV)")
    mapping = parse_columns(columns)
    plan = _Plan(path, _out_path(path, out, force), c)
    plan.q_given = {**parse_counts(counts_per_rev, counts_per_m), "position_unit": position_unit}
    _read(plan, mapping, time_step)
    _propose_validation(plan, split)
    found = _write(plan, force)
    exp = plan.exp
    counter = f"time        {plan.counter} (a sample counter: skipped samples stay gaps)"
    lines = [
        f"data        {plan.data.name}: {_samples(plan)}, dt {exp.dt:.6g} s ({1 / exp.dt:.6g} "
        f"Hz, uniform to {plan.jitter:.2g} of a step)",
        "columns     " + ", ".join(f"{k} = {v!r}" for k, v in plan.read_as.items()),
        *([f"time        {plan.time_unit} (converted to s)"] if plan.time_unit != "s" else []),
        *([counter] if plan.counter else []),
        f"position    {plan.position.unit} ({plan.position.why})",
    ]
    if plan.validation:
        lines.append("validation  " + ", ".join(p.name for p in plan.validation))
    else:
        lines.append("validation  none (see the comment in the config, or use --split 0.7)")
    if plan.test:
        lines.append("test        " + ", ".join(p.name for p in plan.test))
    lines += [f"note        {n}" for n in plan.notes]
    lines += [f"warning     {w}" for w in found if w not in plan.notes]
    lines += [f"wrote       {p}" for p in (*plan.splits, plan.out)]
    lines.append(f"next        torchfric check {plan.out.name}; torchfric train {plan.out.name}")
    return lines


def _samples(plan: _Plan) -> str:
    n = sum(e.n for e in plan.segments)
    cut = f" in {len(plan.segments)} segments" if len(plan.segments) > 1 else ""
    return f"{n} samples{cut}, {sum(e.duration for e in plan.segments):.6g} s"


def cmd_init(args: argparse.Namespace) -> int:
    lines = write_starter(
        args.data,
        c_m=args.c_m,
        out=args.out,
        force=args.force,
        split=args.split,
        columns=args.column or (),
        time_step=args.time_step,
        counts_per_rev=getattr(args, "counts_per_rev", None),
        counts_per_m=getattr(args, "counts_per_m", None),
        position_unit=getattr(args, "position_unit", None),
    )
    print("\n".join(lines))
    return 0
