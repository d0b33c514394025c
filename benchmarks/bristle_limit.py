"""Can the held-out windows of ``model.dynamic = "auto"`` tell LuGre's bristles from their limit
σ0 → ∞ (a friction law that sticks)? A probe of issue 36's part 1, not a rule torchfric uses. A table.

    python benchmarks/bristle_limit.py --machines rig turntable lugre stribeck --seeds 1 2 --jobs 2

For each machine (those of `benchmarks/model_class.py`; a user's path: ``init --c-m``, then
``train`` as written, which compares the classes), the comparison's own candidates — static and
LuGre, identified on the first 70 % of the record — are taken as they are, and their held-out
0.05-s windows (`torchfric.estimators.selection.window_errors`) scored three ways:

- LuGre against the static model (the comparison's t: > 0, LuGre predicts better), on all
  windows, on the *stuck* ones (the measured position moves at most 3 encoder steps in the
  window) and on the moving ones;
- LuGre against its own stiff limit: σ0 × 16 and σ1 × 4 (the same damping ratio, a quarter of
  the travel), everything else the same (> 0: the finite bristles predict better), on the same
  three sets of windows.

On a LuGre machine whose bristles the record resolves, the finite σ0 should predict the stuck
windows better than its stiff limit; on a static machine it should not. The train itself is
stopped once the comparison has been scored (nothing is written to its run folder).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from model_class import AXES, CONFIGS, _prepare, run_machines  # noqa: E402  (a sibling)

STIFF = 16.0  # σ0's factor of the stiff limit (σ1 × √16 keeps the damping ratio)
STUCK_STEPS = 3  # a window is stuck when its measured position spans at most this many steps


def _t(a: torch.Tensor, b: torch.Tensor) -> float:
    """The mean of a − b over its standard error (> 0: b predicts better); NaN if any is not
    finite or fewer than 3 windows."""
    d = a - b
    if d.numel() < 3 or not bool(torch.isfinite(d).all()):
        return math.nan
    return float(d.mean() / (d.std() / math.sqrt(d.numel())))


def _score(starts: Any, heads: Any, picks: Any, tuning: Any, mse: dict, scores: dict,
           thetas: dict) -> dict[str, float]:  # fmt: skip
    """The probe's figures from the comparison's candidates (`_identify_and_predict`'s values)."""
    from torchfric.data import position_step
    from torchfric.estimators.passes import prepared
    from torchfric.estimators.selection import window_errors
    from torchfric.models.lugre import bristle_travel, stick_rate

    key = next(k for k in starts if k != "none")
    model, theta, score, lugre = starts[key], thetas[key], scores[key], mse[key]
    step = position_step([p[0] for p in picks])
    fric, arm = model.split(theta)
    phys = model.to_physical(theta).clone()
    names = model.theta_names
    phys[names.index("lugre_sigma0")] *= STIFF
    phys[names.index("lugre_sigma1")] *= math.sqrt(STIFF)
    resolved = prepared(heads, tuning, model.num_parameters, "compare_dynamics")[1]
    kw = {"q_scale": score.q_scale, "r_scale": score.r_scale}
    stiff = torch.cat([window_errors(model, model.from_physical(phys), e, resolved, c, w, **kw)
                       for e, c, w in picks])  # fmt: skip
    stuck = []
    for e, c, w in picks:  # the windows `window_errors` tiles, in its order
        q = e.q.to(torch.float64)
        stuck += [float(q[a : a + w + 1].max() - q[a : a + w + 1].min()) <= STUCK_STEPS * step
                  for a in range(c, e.n - w, w)]  # fmt: skip
    s = torch.tensor(stuck)
    row = {"travel_steps": bristle_travel(model.friction, fric, arm) / step,
           "per_sample": stick_rate(arm) * min(p[0].dt for p in picks),
           "windows": int(s.numel()), "stuck": int(s.sum())}  # fmt: skip
    for name, other in (("static", mse["none"]), ("stiff", torch.nan_to_num(stiff, nan=math.inf))):
        for part, m in (("all", torch.ones_like(s)), ("stuck", s), ("moving", ~s)):
            row[f"{name}_{part}"] = _t(other[m], lugre[m])
    return row


def probe(argv: list[str]) -> int:
    """``--probe CONFIG [--set K=V …]``: train as written up to the class comparison, print its
    probe's row as one JSON line, and stop."""
    import torchfric.estimators.sizing as sizing
    from torchfric.app.cli import main

    identify = sizing._identify_and_predict

    def scored(starts, heads, picks, tuning, spec, device):  # type: ignore[no-untyped-def]
        scores, thetas, mse = identify(starts, heads, picks, tuning, spec, device)
        row = _score(starts, heads, picks, tuning, mse, scores, thetas)
        print("PROBE " + json.dumps(row), flush=True)
        raise SystemExit(0)

    sizing._identify_and_predict = scored
    cfg, sets = argv[0], argv[1:]
    return main(["train", cfg, "--out", str(Path.cwd() / "probe_run"), "--quiet", *sets])


def one(out: Path, machine: str, seed: int) -> dict[str, Any]:
    folder = out / f"{machine}_{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    cfg, sets = _prepare(folder, machine, seed)
    argv = [sys.executable, __file__, "--probe", str(cfg)]
    for s in sets:
        argv += ["--set", s]
    done = subprocess.run(argv, cwd=folder, capture_output=True, text=True)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("PROBE ")]
    if not lines:
        raise RuntimeError(f"{machine} seed {seed}: {done.stderr.strip()[-400:]}")
    print(f"{machine} seed {seed} done", file=sys.stderr, flush=True)
    return {"machine": machine, "seed": seed, **json.loads(lines[0][6:])}


def print_table(rows: list[dict]) -> None:
    head = ("machine", "seed", "travel", "settling per sample", "stuck windows",
            "LuGre vs static: all", "stuck", "moving", "LuGre vs stiff limit: all", "stuck",
            "moving")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        ts = " | ".join(f"{r[f'{n}_{p}']:+.1f}" for n in ("static", "stiff")
                        for p in ("all", "stuck", "moving"))  # fmt: skip
        print(f"| {r['machine']} | {r['seed']} | {r['travel_steps']:.2f} steps | "
              f"{r['per_sample']:.2f} | {r['stuck']}/{r['windows']} | {ts} |")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--probe"]:
        return probe(argv[1:])
    machines = ["rig", "lugre", "belt-fast", "spindle", "stribeck", "linear", "table", "turntable"]
    return run_machines(argv, __doc__, one, print_table, machines,
                        [m for m in ["rig", *AXES] if m in AXES or m in CONFIGS])  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
