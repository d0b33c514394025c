"""The speed a user sees (issue 21): whole commands, not the filter alone. Prints one table;
every number is measured in this run, on this machine.

    python benchmarks/user_speed.py                       # about 3 minutes on 2 cores
    python benchmarks/user_speed.py --repeat 5 --json after.json
    python benchmarks/user_speed.py --before before.json  # adds the earlier run as a column

Rows (each command in a fresh process, as a user runs it; medians of --repeat runs):
- quick start, cold: ``torchfric train experiments/configs/arm_tanh_ekf.toml`` (the README's
  command, 10 passes of tanh(3) over the rig's 30 k samples, with validation) with an empty
  compiled-code cache (``TORCHFRIC_CACHE`` set to a fresh folder): the generated C is built;
- quick start, warm: the same command again, the compiled code now on disk;
- one more pass end to end: ``(T(31 passes) − T(1 pass)) / 30`` of that command with
  ``estimator.tolerance = 0`` (a fixed pass count), warm: the filter pass plus everything a pass
  costs around it (validation simulation, logging, snapshots), as samples/s;
- the filter pass alone: `run_pass` of the compiled step over the same 30 k samples, in process;
- the numpy reference EKF (`benchmarks/ekf_speed.py`'s, hand-derived Jacobian, same equations),
  in the same process, for scale;
- ``torchfric train experiments/configs/arm_defaults.toml`` (the default 9-filter ensemble), warm;
- ``import torchfric`` (its names load on first use), ``from torchfric import ArmModel,
  identify_ekf`` (torch and the estimators); ``torchfric --help``, ``--version`` and an
  argument error;
- the pre-fit: `prefit` of the quick start's model in a fresh process with a warm cache (what
  ``model.init = "prefit"`` costs a run), and a second call in that process.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "experiments" / "configs" / "arm_tanh_ekf.toml"
DEFAULTS = ROOT / "experiments" / "configs" / "arm_defaults.toml"
SAMPLES = 30_000  # the rig's identification record
EXTRA = 30  # passes between the two runs whose times give the cost of one more pass
# exactly what the `torchfric` console script runs
CLI = "import sys; from torchfric.app.cli import main; sys.exit(main())"

GOALS = {
    "quick_cold_s": "≤ 10 s",
    "quick_warm_s": "≤ 2.5 s",
    "defaults_warm_s": "",
    "pass_samples_per_s": "≥ 300 k/s",
    "filter_steps_per_s": "(1.5 M/s moonshot)",
    "numpy_steps_per_s": "reference",
    "import_s": "≤ 1.8 s",
    "import_api_s": "≤ 1.8 s",
    "help_s": "≤ 0.3 s",
    "version_s": "≤ 0.3 s",
    "argerror_s": "≤ 0.3 s",
    "prefit_s": "≤ 0.3 s",
    "prefit_again_s": "",
}
LABELS = {
    "quick_cold_s": "quick start `train`, cold cache",
    "quick_warm_s": "quick start `train`, warm cache",
    "defaults_warm_s": "`train arm_defaults.toml` (9-filter ensemble), warm",
    "pass_samples_per_s": "one more pass, end to end",
    "filter_steps_per_s": "the filter pass alone (native step)",
    "numpy_steps_per_s": "numpy reference EKF",
    "import_s": "`import torchfric`",
    "import_api_s": "`from torchfric import ArmModel, identify_ekf`",
    "help_s": "`torchfric --help`",
    "version_s": "`torchfric --version`",
    "argerror_s": "`torchfric train` (argument error)",
    "prefit_s": "pre-fit, first call in a process",
    "prefit_again_s": "pre-fit, again in that process",
}


def timed(argv: list[str], env: dict, cwd: Path) -> tuple[float, int]:
    """Wall seconds and exit status of one command."""
    t0 = time.perf_counter()
    run = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True)
    return time.perf_counter() - t0, run.returncode


def median_of(
    repeat: int, argv: list[str], env: dict, cwd: Path, ok: tuple[int, ...] = (0,)
) -> float:
    times = []
    for _ in range(repeat):
        seconds, rc = timed(argv, env, cwd)
        if rc not in ok:
            out = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True)
            raise SystemExit(f"{' '.join(argv)} exited with {rc}:\n{out.stderr[-2000:]}")
        times.append(seconds)
    return statistics.median(times)


def train_argv(*sets: str, config: Path = CONFIG) -> list[str]:
    argv = [sys.executable, "-c", CLI, "train", str(config), "--quiet"]
    for s in sets:
        argv += ["--set", s]
    return argv


def fresh_cache(parent: Path) -> Path:
    folder = Path(tempfile.mkdtemp(prefix="cache-", dir=parent))
    os.chmod(folder, 0o700)
    return folder


PREFIT = """
import time, torch, torchfric
from torchfric.data.rig import rig_experiment
d = rig_experiment("identification")
exp = torchfric.make_experiment(d["t"], d["u"], d["q"], name="identification")
model = torchfric.ArmModel(torchfric.OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
t0 = time.perf_counter(); torchfric.prefit(model, [exp]); t1 = time.perf_counter()
torchfric.prefit(model, [exp]); t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def in_process_rates() -> tuple[float, float]:
    """(filter steps/s, numpy reference steps/s) over the rig's identification record."""
    sys.path.insert(0, str(Path(__file__).parent))
    import torch
    from ekf_speed import numpy_baseline, rig_data, time_pass

    from torchfric import ArmModel, OddTanhFriction

    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)  # as the CLI runs it
    exp = rig_data()
    model = ArmModel(OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
    rate = max(time_pass(model, exp, SAMPLES, compile=True)[0] for _ in range(3))
    np_rate, _ = numpy_baseline(model, exp, 3000)
    return rate, np_rate


def measure(repeat: int) -> dict[str, float]:
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="user-speed-") as tmp:
        work = Path(tmp)
        env = dict(os.environ, PYTHONDONTWRITEBYTECODE="0")
        env.pop("TORCHFRIC_NATIVE", None)
        colds = []
        for _ in range(max(1, min(repeat, 2))):  # each a fresh, empty cache
            env["TORCHFRIC_CACHE"] = str(fresh_cache(work))
            colds.append(median_of(1, train_argv(), env, work))
        out["quick_cold_s"] = statistics.median(colds)
        out["quick_warm_s"] = median_of(repeat, train_argv(), env, work)
        median_of(1, train_argv(config=DEFAULTS), env, work)  # its ensemble's code, built
        out["defaults_warm_s"] = median_of(repeat, train_argv(config=DEFAULTS), env, work)
        fixed = "estimator.tolerance=0"  # no early stop: exactly the passes asked for
        one = median_of(repeat, train_argv("estimator.passes=1", fixed), env, work)
        more = median_of(repeat, train_argv(f"estimator.passes={1 + EXTRA}", fixed), env, work)
        out["pass_samples_per_s"] = SAMPLES / max((more - one) / EXTRA, 1e-9)
        out["import_s"] = median_of(repeat, [sys.executable, "-c", "import torchfric"], env, work)
        api = "from torchfric import ArmModel, identify_ekf"
        out["import_api_s"] = median_of(repeat, [sys.executable, "-c", api], env, work)
        base = [sys.executable, "-c", CLI]
        out["help_s"] = median_of(repeat, [*base, "--help"], env, work)
        out["version_s"] = median_of(repeat, [*base, "--version"], env, work, ok=(0, 2))
        out["argerror_s"] = median_of(repeat, [*base, "train"], env, work, ok=(2,))
        runs = []
        for _ in range(repeat):
            run = subprocess.run([sys.executable, "-c", PREFIT], env=env, cwd=work,
                                 capture_output=True, text=True, check=True)  # fmt: skip
            runs.append([float(w) for w in run.stdout.split()])
        out["prefit_s"] = statistics.median(r[0] for r in runs)
        out["prefit_again_s"] = statistics.median(r[1] for r in runs)
    out["filter_steps_per_s"], out["numpy_steps_per_s"] = in_process_rates()
    return out


def show(key: str, value: float | None) -> str:
    if value is None:
        return "—"
    if key.endswith("_per_s"):
        return f"{value / 1e3:,.0f} k/s"
    return f"{value:.2f} s"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--repeat", type=int, default=3, help="runs per command (median)")
    p.add_argument("--json", help="also write the numbers to this file")
    p.add_argument("--before", help="a JSON file of an earlier run, shown as a column")
    args = p.parse_args()
    out = measure(args.repeat)
    before = json.loads(Path(args.before).read_text()) if args.before else None
    head = "| measure | goal | " + ("before | after |" if before else "this run |")
    print(head)
    print("|" + "---|" * (4 if before else 3))
    for key, label in LABELS.items():
        cells = [label, GOALS[key]]
        if before:
            cells.append(show(key, before.get(key)))
        cells.append(show(key, out.get(key)))
        print("| " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
