"""The filter's RK4 sub-steps on a machine whose friction is too stiff for one: ``estimator.substeps
= "auto"`` against the paper's 1. Prints one table: per seed and measurement-noise scale, the
inertia, Fs and vs errors the EKF ends at when it starts at the truth, in the true model class.

    python benchmarks/substeps.py                    # seeds 1-4, R ×1 and ×10 (about a minute)
    python benchmarks/substeps.py --seeds 1 2 --r-scales 10

The machine is `tests/test_substeps.py`'s (written there, not by torchfric): a vertical axis in a
PID loop, 3.2 kg, c_m 55 N/V, b 40 N s/m, gravity 31.39 N, Stribeck friction with its sign drawn
by ``tanh(v / 0.2 mm/s)``, a 0.5 µm encoder, 20 s; its slope at rest over the mass asks for 8
RK4 sub-steps a millisecond (`filter_substeps`). The filter is `identify_ekf` with the paper's
tuning, R times the scale, 8 passes, from the true parameters; a run that diverges says so.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torchfric
from torchfric.models.simulate import filter_substeps

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_substeps import DT, FS, VS, M, _record, _truth  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--r-scales", type=float, nargs="+", default=[1.0, 10.0])
    args = ap.parse_args()
    print(f"filter_substeps at the truth: {filter_substeps(_truth(), DT)}")
    print("| seed | R × | substeps | M error | Fs error | vs error | passes | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    paper = torchfric.EKFTuning(passes=8)
    for seed in args.seeds:
        exp = _record(seed)
        for scale in args.r_scales:
            for substeps in ("auto", 1):
                tuning = dataclasses.replace(
                    paper, r=tuple(scale * x for x in paper.r), substeps=substeps
                )
                t0 = time.perf_counter()
                try:
                    result = torchfric.identify_ekf(_truth(), [exp], tuning)
                except torchfric.TorchfricError as err:
                    print(f"| {seed} | {scale:g} | {substeps} | diverged: {str(err)[:60]} |")
                    continue
                p, seconds = result.model.physical_parameters(), time.perf_counter() - t0
                print(
                    f"| {seed} | {scale:g} | {substeps} | {p['inertia'] / M - 1:+.2%} | "
                    f"{p['Fs'] / FS - 1:+.1%} | {p['vs'] / VS - 1:+.0%} | {result.passes} | "
                    f"{seconds:.1f} |"
                )


if __name__ == "__main__":
    main()
