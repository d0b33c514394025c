"""``torchfric init DATA --c-m VALUE``: a commented starter config for a user's data file.

`write_starter` reads the file with the project's readers (`read_columns`, `load_experiment`:
every check a run makes on a record) and writes a config only once it has passed `check_run`.

- Columns: ours (t, u, q, qdot) by name or a common alternative (`ALIASES`), without case and
  without a unit in brackets or after an underscore (``Time [s]``, ``pos_deg``); our own name
  wins. Two candidates, or none for t, u or q, stop with the header and the line to write.
- Sample time: the t column's (uniform to the loader's 1e-3), or ``--time-step``. A rate too
  slow for the 200 Hz velocity filter gets ``velocity_cutoff_hz`` = 0.4 × Nyquist.
- Units of q: a unit in the column's name sets ``position_unit``; without one q is taken as
  rad (or m), with a note when whole numbers only (encoder counts) or a speed above
  `FAST_SPEED` units/s (about 1000 rpm in rad) suggest otherwise.
- Validation: ``data.start``/``stop`` apply to every file, so one file cannot be split by
  sample ranges. ``--split F`` (only when asked) writes its first fraction F and the rest as two
  new CSV files beside the config; otherwise a record beside the data named as its validation
  record (``run1_train`` ↔ ``run1_val``, ``identification`` ↔ ``validation``) with the same
  columns and sample time is proposed, or a comment says how to add one. Nothing is replaced:
  not the data, not a split file; the config only with ``--force``.
"""

from __future__ import annotations

import math
import os
import pathlib
import re
import textwrap
from collections.abc import Mapping, Sequence

import numpy as np

from ..data import DEFAULT_CUTOFF_HZ, Experiment, load_experiment
from ..data.readers import read_columns, save_csv
from ..errors import TorchfricError, shorten
from ..files import atomic_write_text
from ..models.friction import FRICTIONS
from ..version import __version__
from .check import check_run
from .config import COLUMN_NAMES, MAX_NAME, POSITION_UNITS, Config, EstimatorConfig, ModelConfig
from .toml_io import toml_value

__all__ = ["ALIASES", "FAST_SPEED", "write_starter"]

ALIASES: dict[str, tuple[str, ...]] = {
    "t": ("t", "time", "times", "timestamp", "sec", "secs", "seconds"),
    "u": ("u", "input", "current", "i", "iq", "cmd", "command", "control", "torque", "tau",
          "force", "voltage", "volt", "pwm"),
    "q": ("q", "pos", "position", "theta", "th", "angle", "phi", "qm", "x", "encoder", "enc"),
    "qdot": ("qdot", "q_dot", "qd", "dq", "dqdt", "velocity", "vel", "speed", "omega",
             "thetadot", "theta_dot", "dtheta", "xdot", "x_dot"),
}  # fmt: skip
"""Names (lower case, unit removed) recognised for each of our columns; our own name first."""
FAST_SPEED = 100.0
"""A q that moves faster than this (99th percentile of |Δq|/dt, units/s) gets a unit note."""
_MEANING = {"t": "time in s", "u": "input", "q": "position", "qdot": "velocity"}
_UNITS = {"deg": "deg", "degree": "deg", "degrees": "deg", "°": "deg", "rad": "rad",
          "radian": "rad", "radians": "rad", "m": "m", "meter": "m", "metre": "m",
          "meters": "m", "metres": "m", "mm": "mm", "counts": "counts", "count": "counts",
          "cnt": "counts", "cnts": "counts", "inc": "counts", "ticks": "counts",
          "s": "s", "sec": "s", "ms": "ms", "us": "us", "µs": "us"}  # fmt: skip
_UNIT_IN_BRACKETS = re.compile(r"\s*[\[(]([^\])]*)[\])]\s*$")
_TRAIN_WORDS = {"train", "training", "identification", "ident", "id", "idf", "estimation", "fit"}
_VALID_WORDS = {"val", "valid", "validation", "validate"}
_MIN_PART = 100  # samples in each part of a --split


# ------------------------------------------------------------------------------------ columns
def _parse_name(name: str) -> tuple[str, str | None]:
    """(base name, unit) of a column name: ``"Time [s]"`` → ("time", "s"), ``"pos_deg"`` →
    ("pos", "deg"); the unit is None when the name gives none."""
    s, unit = name.strip().lower(), None
    m = _UNIT_IN_BRACKETS.search(s)
    if m:
        s, unit = s[: m.start()], _UNITS.get(m.group(1).strip())
    s = re.sub(r"[\s.\-]+", "_", s).strip("_")
    base, sep, tail = s.rpartition("_")
    if unit is None and sep and base and tail in _UNITS:
        s, unit = base, _UNITS[tail]
    return s, unit


def _map_columns(
    table: Mapping[str, np.ndarray], given: Mapping[str, str], path: pathlib.Path, timed: bool
) -> dict[str, str]:
    """Our names → the file's, from `given` (``--column``) and the names in `table`.

    `timed`: the sample time comes from ``--time-step``, so no t column is needed."""
    for role, name in given.items():
        if role not in COLUMN_NAMES:
            raise TorchfricError(
                f"--column {role}={name}: {role!r} is not one of our columns; use "
                f"{', '.join(COLUMN_NAMES)}, e.g. --column q=encoder"
            )
    names = [k for k, v in table.items() if np.ndim(v) == 1 or 1 in np.shape(v)]
    header = ", ".join(table) or "nothing"
    mapping, unknown = dict(given), {}
    for role in COLUMN_NAMES:
        if role in mapping or (role == "t" and timed):
            continue
        free = [n for n in names if n not in mapping.values()]
        own = [n for n in free if _parse_name(n)[0] == role]
        found = own or [n for n in free if _parse_name(n)[0] in ALIASES[role]]
        if len(found) == 1:
            mapping[role] = found[0]
        elif role != "qdot":  # qdot is optional (the velocity is rebuilt from q)
            unknown[role] = f"{' and '.join(found)} all look like it" if found else "none does"
    if unknown:
        which = "; ".join(f"{r} ({_MEANING[r]}): {why}" for r, why in unknown.items())
        fix = " ".join(f"--column {r}=NAME" for r in unknown)
        if unknown.get("t") == "none does":
            fix += " (or --time-step SECONDS for a file without a time column)"
        line = {k: mapping.get(k, "NAME") for k in COLUMN_NAMES if k in mapping or k in unknown}
        raise TorchfricError(
            f"{path}: cannot tell which column is {which}; the header is: {shorten(header)}; "
            f"rerun with {fix}, which writes under [data]: columns = {toml_value(line)}"
        )
    return mapping


# ------------------------------------------------------------------------------------ checks
def _time_unit(mapping: Mapping[str, str], path: pathlib.Path) -> None:
    name = mapping.get("t")
    unit = _parse_name(name)[1] if name else None
    if unit in ("ms", "us"):
        raise TorchfricError(
            f"{path}: the time column {name!r} is in {unit}; torchfric reads t in seconds: "
            "convert it (t/1000 for ms), or leave it out and give --time-step SECONDS"
        )


def _position_unit(name: str, q: np.ndarray, dt: float) -> tuple[str, str, list[str]]:
    """(data.position_unit, the reason for the config's comment, notes to show the user)."""
    unit = _parse_name(name)[1]
    if unit in POSITION_UNITS:
        return unit, f'from the column name "{name}"', []
    speed = float(np.quantile(np.abs(np.diff(q)), 0.99)) / dt
    if unit == "counts" or (np.all(q == np.round(q)) and np.unique(q).size >= 20):
        why = f'the name "{name}" says counts' if unit == "counts" else "q holds whole numbers only"
        note = (
            f"{why} ({q.min():.0f} … {q.max():.0f}): encoder counts? torchfric has no unit for "
            "counts; convert q to rad (× 2π / counts per turn) or to m before training, or "
            "every parameter comes out per count"
        )
    elif speed > FAST_SPEED:
        note = (
            f"q moves at up to {speed:.4g} units/s: {speed * 30 / math.pi:,.0f} rpm if it is in "
            f'rad. If q is in degrees set data.position_unit = "deg" ({speed * math.pi / 180:.3g} '
            'rad/s), in millimetres "mm"'
        )
    else:
        return "rad", "nothing says otherwise; for a linear axis in m, the same numbers", []
    return "rad", "taken as rad, but see the note at the top", [note]


def _cutoff(dt: float) -> float | None:
    """A velocity cut-off when the default one is above 0.4 × Nyquist, else None."""
    nyquist = 0.5 / dt
    if DEFAULT_CUTOFF_HZ["highpass"] <= 0.4 * nyquist:
        return None
    return float(f"{0.4 * nyquist:.3g}")


# ------------------------------------------------------------------------------------ validation
def _words(stem: str) -> list[str]:
    return [w for w in re.split(r"[^a-z0-9]+", stem.lower()) if w]


def _paired(data: pathlib.Path, other: pathlib.Path) -> bool | None:
    """True: `other` is named as `data`'s validation record; False: named as a validation
    record of something else; None: not named as a validation record."""
    words = _words(other.stem)
    if not any(w in _VALID_WORDS for w in words):
        return None
    rest = [w for w in words if w not in _VALID_WORDS]
    return rest == [w for w in _words(data.stem) if w not in _TRAIN_WORDS]


def _siblings(
    data: pathlib.Path, mapping: Mapping[str, str], time_step: float | None, dt: float
) -> tuple[list[pathlib.Path], list[pathlib.Path]]:
    """(paired, other) validation-named records beside `data` that read with its columns and
    sample time (`_paired`)."""
    paired: list[pathlib.Path] = []
    other: list[pathlib.Path] = []
    for p in sorted(data.parent.iterdir()):
        if p == data or p.suffix.lower() != data.suffix.lower() or not p.is_file():
            continue
        kind = _paired(data, p)
        if kind is None:
            continue
        try:
            exp = load_experiment(p, columns=mapping, time_step=time_step)
        except TorchfricError:
            continue
        if abs(exp.dt - dt) <= 1e-3 * dt:
            (paired if kind else other).append(p)
    return paired, other


def _split(
    exp: Experiment, fraction: float, folder: pathlib.Path, stem: str
) -> dict[pathlib.Path, Experiment]:
    """{new file: its part} for ``--split``: the first `fraction` and the rest."""
    k = round(fraction * exp.n)
    if min(k, exp.n - k) < _MIN_PART:
        raise TorchfricError(
            f"--split {fraction:g} leaves {min(k, exp.n - k)} samples in one part of "
            f"{exp.n}; each part needs at least {_MIN_PART}: choose a fraction nearer 0.5"
        )
    parts = {
        folder / f"{stem}_identification.csv": exp.slice(0, k),
        folder / f"{stem}_validation.csv": exp.slice(k),
    }
    for p in parts:
        if p.exists() or p.is_symlink():
            raise TorchfricError(
                f"--split would write {p}, which exists; init never replaces a data file: move "
                "it away, or write the config into another folder with --out"
            )
    return parts


# ------------------------------------------------------------------------------------ the text
def _block(key: str, value: object, *comment: str, active: bool = True) -> list[str]:
    """`comment` wrapped as ``#`` lines, then ``key = value`` (commented out unless `active`)."""
    text = " ".join(c for c in comment if c)
    lines = textwrap.wrap(text, 96, initial_indent="# ", subsequent_indent="# ") if text else []
    return [*lines, ("" if active else "# ") + f"{key} = {toml_value(value)}"]


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
        self.others: list[pathlib.Path] = []
        self.splits: dict[pathlib.Path, Experiment] = {}
        self.split = ""

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

    def _data(self) -> list[str]:
        units = ", ".join(f'"{u}"' for u in POSITION_UNITS)
        lines = ["[data]", *_block("train", [_rel(p, self.folder) for p in self.train],
                                   self.split, _HELP["train"]), *self._validation()]  # fmt: skip
        if self.mapping:
            lines += _block("columns", self.mapping, _HELP["columns"])
        if self.time_step is not None:
            lines += _block("time_step", self.time_step, "Sample time [s]: the file has no t.")
        unit = f"Unit of q in the file: {units} (q becomes rad or m); {self.unit_why}."
        lines += _block("position_unit", self.unit, unit)
        lines += _block("velocity", "highpass", _HELP["velocity"])
        why = f"The velocity filter's cut-off [Hz], below Nyquist ({0.5 / self.exp.dt:g} Hz)."
        if self.cutoff is not None:
            why += " Set to 0.4 × Nyquist: the default 200 Hz is too fast for this sampling."
        lines += _block("velocity_cutoff_hz", self.cutoff or 200.0, why, active=bool(self.cutoff))
        return lines + _block("stop", self.exp.n, _HELP["stop"], active=False)

    def text(self) -> str:
        exp, out = self.exp, self.out.name
        model, est = ModelConfig(c_m=self.c_m), EstimatorConfig()
        head = [
            f"# Starter config for {self.data.name}, by `torchfric init` (torchfric {__version__})",
            f"#   torchfric check {out}    what a run would do (checks all, writes nothing)",
            f"#   torchfric train {out}    identify the model, in runs/{self.name}/",
            "# Every key, its default and allowed values: docs/config.md in the torchfric source.",
            f"# {self.data.name}: {exp.n} samples, dt = {exp.dt:.6g} s ({1 / exp.dt:.6g} Hz, "
            f"uniform to {self.jitter:.2g} of a step), {exp.duration:.6g} s.",
            *[f"# Note: {n}" for n in self.notes],
            "",
            *_block("name", self.name, _HELP["name"]),
            *_block("seed", 0, _HELP["seed"]),
            "",
            *self._data(),
            "",
            "[model]",
        ]
        for key in ("friction", "size", "c_m", "init", "inertia", "viscous"):
            head += _block(key, getattr(model, key), _HELP.get(key, ""))
        head += ["", "[estimator]"]
        for key in ("method", "passes", "tolerance", "ensemble"):
            head += _block(key, getattr(est, key), _HELP.get(key, ""))
        return "\n".join(head) + "\n"


_FOUND = (
    "Found beside the data file, named as its validation record, with the same columns and "
    "sample time: remove the line if it is not a record of this machine."
)
_NONE = (
    "None yet: a run is then scored on its own identification data, which says little about the "
    "model. Name a second record of this machine (another input signal) here{named}, or rerun "
    "init with --split 0.7 to hold out the last 30 % of {data} (written as two new files beside "
    "this config)."
)
_HELP = {
    "train": "Identification records (paths relative to this file); every pass uses all of them.",
    "validation": "Held-out records: open-loop FIT after every pass, which picks the pass kept.",
    "columns": "Our name = the file's: t time [s], u input, q position, qdot velocity (optional).",
    "velocity": 'q̇ for the estimator: "highpass" (the paper\'s causal differentiator), '
    '"zero_phase" (off-line) or "measured" (the file\'s qdot column).',
    "stop": "Use samples start <= k < stop of every file (also: start = 0).",
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
    "passes": "EKF passes over the data, at most; it stops once a pass changes θ by less than "
    "`tolerance` (relative; 0: never).",
    "ensemble": "1: the start under 3 Q × 3 R tunings (9 filters), the best kept; 0: one "
    "filter, the paper's method.",
}


# ------------------------------------------------------------------------------------ writing
def _c_m(value: float | str | None) -> float:
    if value is None:
        raise TorchfricError(
            "--c-m is required: the motor constant, torque (N·m) or force (N) per unit of the "
            "input u (e.g. the torque constant in N·m/A times the gear ratio); torchfric does "
            "not estimate it by default, because from u and q alone it cannot be told from the "
            "inertia and friction: e.g. torchfric init data.csv --c-m 0.5"
        )
    try:
        c_m = float(value)
    except ValueError:
        c_m = math.nan
    if not (math.isfinite(c_m) and c_m > 0):
        raise TorchfricError(
            f"--c-m {value}: expected a positive number, the motor constant (torque or force "
            "per unit of u), e.g. --c-m 16"
        )
    return c_m


def _out_path(data: pathlib.Path, out: str | os.PathLike[str] | None, force: bool) -> pathlib.Path:
    target = pathlib.Path(f"{data.stem}.toml" if out is None else out).absolute()
    if target.suffix.lower() in (".csv", ".npz", ".mat") or target.resolve() == data.resolve():
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


def _read(plan: _Plan, columns: Mapping[str, str], time_step: float | None) -> None:
    """Columns, the record, its sample time and the unit of q into `plan`."""
    data = plan.data
    plan.mapping = _map_columns(read_columns(data), columns, data, time_step is not None)
    plan.read_as = dict(plan.mapping)
    _time_unit(plan.mapping, data)
    plan.time_step = time_step if "t" not in plan.mapping else None
    plan.exp = exp = load_experiment(data, columns=plan.mapping, time_step=time_step)
    steps = np.diff(exp.t.numpy())
    plan.jitter = float(np.max(np.abs(steps - np.median(steps))) / np.median(steps))
    plan.unit, plan.unit_why, notes = _position_unit(plan.mapping["q"], exp.q.numpy(), exp.dt)
    plan.notes += notes
    plan.cutoff = _cutoff(exp.dt)


def _propose_validation(plan: _Plan, split: float | str | None) -> None:
    if split is None:
        paired, plan.others = _siblings(plan.data, plan.mapping, plan.time_step, plan.exp.dt)
        plan.validation = paired
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
    plan.splits = _split(plan.exp, fraction, plan.folder, plan.data.stem)
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
    """
    c = _c_m(c_m)
    path = pathlib.Path(data).absolute()
    if not path.is_file():
        raise TorchfricError(f"{data}: no such file; give the path of your data file (CSV)")
    if not isinstance(columns, Mapping):
        bad = [s for s in columns if "=" not in s]
        if bad:
            raise TorchfricError(f"--column {bad[0]}: expected OURS=NAME, e.g. --column q=pos")
        columns = dict(s.split("=", 1) for s in columns)
    plan = _Plan(path, _out_path(path, out, force), c)
    _read(plan, {k.strip(): v.strip() for k, v in columns.items()}, time_step)
    _propose_validation(plan, split)
    found = _write(plan, force)
    exp = plan.exp
    lines = [
        f"data        {plan.data.name}: {exp.n} samples, dt {exp.dt:.6g} s ({1 / exp.dt:.6g} Hz, "
        f"uniform to {plan.jitter:.2g} of a step), {exp.duration:.6g} s",
        "columns     " + ", ".join(f"{k} = {v!r}" for k, v in plan.read_as.items()),
        f"position    {plan.unit} ({plan.unit_why})",
    ]
    if plan.validation:
        lines.append("validation  " + ", ".join(p.name for p in plan.validation))
    else:
        lines.append("validation  none (see the comment in the config, or use --split 0.7)")
    lines += [f"note        {n}" for n in plan.notes]
    lines += [f"warning     {w}" for w in found]
    lines += [f"wrote       {p}" for p in (*plan.splits, plan.out)]
    lines.append(f"next        torchfric check {plan.out.name}; torchfric train {plan.out.name}")
    return lines
