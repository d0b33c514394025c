"""Filter speed on this machine (issue 8). Prints tables; every number is measured in this run.

    python benchmarks/ekf_speed.py            # all sections (about 15 min on 2 cores)
    python benchmarks/ekf_speed.py --quick    # fewer samples per measurement
    python benchmarks/ekf_speed.py --json speed.json

Sections:
1. One filter through the real code path (`make_propagator` → `make_step` → `run_pass`, float64,
   paper tuning, the rig's identification data): steps/s eager, through the Inductor scan and
   through the generated C (`torchfric.accel.native`, the default), each with its one-time compile,
   for tanh(3, 10, 30) and polytopic(3, 5, 9).
2. Baselines in the same run: an EKF in numpy with a hand-derived Jacobian implementing the same
   equations (RK4 3/8 map with its variational Φ, trapezoid Q_d, Joseph update) for tanh(3),
   checked against torchfric's step to 1e-9 before it is timed; and filterpy's EKF where installed
   (it is not a dependency; the row says so when absent).
3. Batched ensembles (`torchfric.estimators.ensemble.make_masked_step`, compiled chunks, as
   `identify_ekf_ensemble` runs them): filter-steps/s against K, generated C (four members per
   SIMD vector, members split across the cores) and the Inductor scan of the vmapped step.
4. Pass time against the number of samples (default path, tanh(3), 1 k – 1 M) and the peak
   resident memory.
5. `identify_ekf` end to end: 10 passes of tanh(3) over the rig's 30 s identification data, as
   `torchfric train` runs them, in a fresh process: with an empty build cache (the build is in
   pass 1) and again with the library cached on disk.

Inductor means `torch.compile` of a `scan` over 1000-sample chunks (Inductor's C++ wrapper);
native means the step traced, scalarised and compiled by the system C compiler (cached on disk
by its source's hash). The first call per process and model compiles (the "first call" columns;
this benchmark builds into an empty cache folder of its own, so they include the C build).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

from torchfric import ArmModel, make_experiment, make_friction
from torchfric.data.rig import rig_experiment
from torchfric.estimators.ekf import (
    EKFState,
    make_propagator,
    make_step,
    measurement_matrix,
    run_pass,
)
from torchfric.estimators.ensemble import make_masked_step, random_thetas
from torchfric.estimators.identify import EKFTuning, identify_ekf
from torchfric.estimators.prefit import prefit

F64 = torch.float64


def rig_data():  # type: ignore[no-untyped-def]
    d = rig_experiment("identification")
    return make_experiment(d["t"], d["u"], d["q"], name="identification").with_velocity("highpass")


def tuning(k: int):  # type: ignore[no-untyped-def]
    Q = torch.diag(torch.tensor([0.0, 1e-3] + [0.0] * k, dtype=F64))
    R = torch.diag(torch.tensor([1e-3, 1e-2], dtype=F64))
    return Q, measurement_matrix("both", 2 + k), R


def initial(model: ArmModel, exp) -> EKFState:  # type: ignore[no-untyped-def]
    k = model.num_parameters
    x = torch.cat([torch.stack([exp.q[0], exp.qdot[0]]).to(F64), model.get_theta()])
    P = torch.zeros(2 + k, 2 + k, dtype=F64)
    P[2:, 2:] = torch.eye(k, dtype=F64)
    return EKFState(x, P)


def peak_rss_mb() -> float:
    """This process's peak resident memory: VmHWM where /proc has it (ru_maxrss on Linux
    carries the parent's peak over fork and exec, so a child would report the parent's)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def time_pass(model: ArmModel, exp, n: int, compile: bool, native: bool = True):  # type: ignore[no-untyped-def]
    """(steps/s, first-call seconds, path) of `run_pass` over n samples; path is the chunk's
    ("native", "inductor", "eager")."""
    Q, H, R = tuning(model.num_parameters)
    step = make_step(make_propagator(model, 1), compile=compile, native=native)
    u, y = exp.u.to(F64), torch.stack([exp.q, exp.qdot], -1).to(F64)
    dt = torch.tensor(exp.dt, dtype=F64)
    t0 = time.perf_counter()
    state, _ = run_pass(initial(model, exp), u[:3], y[:3], dt, Q, H, R, step)  # warm-up/compile
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    run_pass(initial(model, exp), u[:n], y[:n], dt, Q, H, R, step)
    path = step.chunk.path if step.chunk is not None else "eager"
    return (n - 1) / (time.perf_counter() - t0), first, path


# -- numpy baseline --------------------------------------------------------------------------
class NumpyEKF:
    """tanh(n) + viscous arm, θ = [W1, W2, log b, log M], hand-derived Jacobians, same equations."""

    def __init__(self, c_m: float, n: int) -> None:
        self.c_m, self.n = c_m, n

    def field(self, x, th, u):  # type: ignore[no-untyped-def]
        n = self.n
        W1, W2, b, M = th[:n], th[n : 2 * n], math.exp(th[2 * n]), math.exp(th[2 * n + 1])
        v = x[1]
        th_v = np.tanh(W1 * v)
        acc = (self.c_m * u - b * v - (W2 * th_v).sum()) / M
        sech2 = 1.0 - th_v**2
        F = np.zeros((2, 2 + len(th)))
        F[0, 1] = 1.0
        F[1, 1] = (-b - (W2 * W1 * sech2).sum()) / M
        F[1, 2 : 2 + n] = -W2 * sech2 * v / M
        F[1, 2 + n : 2 + 2 * n] = -th_v / M
        F[1, 2 + 2 * n] = -b * v / M
        F[1, 3 + 2 * n] = -acc
        return np.array([v, acc]), F

    def propagate(self, z, u, h):  # type: ignore[no-untyped-def]
        """One RK4 (3/8) interval: the prior mean `(nz,)` and Φ `(nz, nz)`, the exact Jacobian."""
        nz = z.shape[0]
        x, th = z[:2], z[2:]
        Phi = np.eye(2, nz)
        k1, F1 = self.field(x, th, u)
        x2 = x + h * k1 / 3.0
        k2, F2 = self.field(x2, th, u)
        x3 = x + h * (k2 - k1 / 3.0)
        k3, F3 = self.field(x3, th, u)
        x4 = x + h * (k1 - k2 + k3)
        k4, F4 = self.field(x4, th, u)

        def K(F, D):  # type: ignore[no-untyped-def]
            out = F[:, :2] @ D
            out[:, 2:] += F[:, 2:]
            return out

        K1 = K(F1, Phi)
        K2 = K(F2, Phi + h * K1 / 3.0)
        K3 = K(F3, Phi + h * (K2 - K1 / 3.0))
        K4 = K(F4, Phi + h * (K1 - K2 + K3))
        Phi = Phi + (K1 + 3.0 * (K2 + K3) + K4) * (h / 8.0)
        x_next = x + (k1 + 3.0 * (k2 + k3) + k4) * (h / 8.0)
        Pf = np.eye(nz)
        Pf[:2] = Phi
        return np.concatenate([x_next, th]), Pf

    def step(self, z, P, u, y, dt, Q, H, R):  # type: ignore[no-untyped-def]
        nz = z.shape[0]
        zp, Pf = self.propagate(z, u, dt)
        Pp = Pf @ P @ Pf.T + 0.5 * (Pf @ Q @ Pf.T + Q) * dt
        Pp = 0.5 * (Pp + Pp.T)
        S = H @ Pp @ H.T + R
        L = np.linalg.cholesky(S)
        PHt = Pp @ H.T
        Kg = np.linalg.solve(L.T, np.linalg.solve(L, PHt.T)).T
        e = y - H @ zp
        z_new = zp + Kg @ e
        IKH = np.eye(nz) - Kg @ H
        P_new = IKH @ Pp @ IKH.T + Kg @ R @ Kg.T
        return z_new, 0.5 * (P_new + P_new.T)


def _baseline(model: ArmModel, exp, n: int, make):  # type: ignore[no-untyped-def]
    """(steps/s, max |difference| to torchfric's step over 50 samples) of a reference filter.

    ``make(ekf, z0, P0, Q, H, R) -> step(u_prev, y) -> (z, P)`` builds it on numpy arrays
    around `ekf`, the `NumpyEKF` of `model`."""
    ekf = NumpyEKF(float(model.split(model.get_theta())[1]["c_m"]), model.friction.n)
    Q, H, R = tuning(model.num_parameters)
    st = initial(model, exp)
    u, y = exp.u.numpy(), np.stack([exp.q.numpy(), exp.qdot.numpy()], -1)
    args = (Q.numpy(), H.numpy(), R.numpy())
    ref = make(ekf, st.x.numpy().copy(), st.P.numpy().copy(), *args)
    step = make_step(make_propagator(model, 1))
    dt = torch.tensor(exp.dt, dtype=F64)
    xt, Pt = st.x, st.P
    diff = 0.0
    for j in range(1, 50):
        z, P = ref(u[j - 1], y[j])
        xt, Pt, *_ = step(xt, Pt, exp.u[j - 1].to(F64), torch.as_tensor(y[j]), dt, Q, H, R,
                          torch.tensor(1e6, dtype=F64))  # fmt: skip
        diff = max(diff, float(np.abs(z - xt.numpy()).max()), float(np.abs(P - Pt.numpy()).max()))
    ref = make(ekf, st.x.numpy().copy(), st.P.numpy().copy(), *args)
    t0 = time.perf_counter()
    for j in range(1, n):
        ref(u[j - 1], y[j])
    return (n - 1) / (time.perf_counter() - t0), diff


def numpy_baseline(model: ArmModel, exp, n: int) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """The numpy EKF above: (steps/s, max |difference| to torchfric over 50 samples)."""

    def make(ekf, z, P, Q, H, R):  # type: ignore[no-untyped-def]
        state = [z, P]

        def step(u, y):  # type: ignore[no-untyped-def]
            state[:] = ekf.step(*state, u, y, exp.dt, Q, H, R)
            return tuple(state)

        return step

    return _baseline(model, exp, n, make)


def filterpy_baseline(model: ArmModel, exp, n: int) -> tuple[float, float] | None:  # type: ignore[no-untyped-def]
    """filterpy's `ExtendedKalmanFilter` (its predict, its Joseph-form update with an explicit
    S⁻¹) with the numpy EKF's RK4 mean and exact Φ plugged into `predict_x`, and the same
    discretised Q; `None` when filterpy is not installed (``pip install -e ".[bench]"``)."""
    try:
        from filterpy.kalman import ExtendedKalmanFilter
    except ImportError:
        return None
    dt = exp.dt

    class RK4EKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):  # type: ignore[no-untyped-def]
            # filterpy then forms P⁻ = F P Fᵀ + Q with the F and Q set here
            self.x, self.F = self.ekf.propagate(self.x, u, dt)
            self.Q = 0.5 * (self.F @ self.Qc @ self.F.T + self.Qc) * dt

    def make(ekf, z, P, Q, H, R):  # type: ignore[no-untyped-def]
        kf = RK4EKF(dim_x=z.shape[0], dim_z=2)
        kf.ekf, kf.Qc, kf.x, kf.P, kf.R = ekf, Q, z, P, R

        def step(u, y):  # type: ignore[no-untyped-def]
            kf.predict(u)
            kf.update(y, lambda x: H, lambda x: H @ x)
            return kf.x, kf.P

        return step

    return _baseline(model, exp, n, make)


def batched(model: ArmModel, exp, K: int, n: int, native: bool = True):  # type: ignore[no-untyped-def]
    """(filter-steps/s, first-call seconds, path) of the ensemble's compiled chunked step (the
    code `identify_ekf_ensemble` runs: the masked step, one chunk call per 1000 samples)."""
    k = model.num_parameters
    Q, H, R = tuning(k)
    g = torch.Generator().manual_seed(0)
    th = random_thetas(model, model.get_theta(), K, 1.5, g)
    st = initial(model, exp)
    x = torch.cat([st.x[:2].expand(K, 2), th], 1)
    P = st.P.expand(K, -1, -1).clone()
    Qk, Rk = Q.expand(K, -1, -1).clone(), R.expand(K, -1, -1).clone()
    step = make_masked_step(model, 1, compile=True, native=native)
    f64 = torch.float64
    carry = (x, P, torch.ones(K, dtype=torch.bool), torch.full((K,), -1),
             torch.zeros(K, 2, dtype=f64), torch.zeros(K, dtype=f64), torch.zeros(K, dtype=f64))  # fmt: skip
    u, y = exp.u.to(F64), torch.stack([exp.q, exp.qdot], -1).to(F64)
    dt, bound = torch.tensor(exp.dt, dtype=F64), torch.tensor(1e6, dtype=F64)
    C, index = step.size, torch.arange(exp.n)

    def chunk(carry, j0):  # type: ignore[no-untyped-def]
        sl = slice(j0, j0 + C)
        xs = (index[sl], u[j0 - 1 : j0 - 1 + C], y[sl])
        return step.chunk(carry, xs, torch.ones(C, dtype=torch.bool), (dt, Qk, H, Rk, bound))[0]

    t0 = time.perf_counter()
    chunk(carry, 1)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for j0 in range(1, 1 + n, C):
        carry = chunk(carry, j0)
    bool(carry[2].all())
    rate = K * len(range(1, 1 + n, C)) * C / (time.perf_counter() - t0)
    return rate, first, step.chunk.path


def identification(model: ArmModel, exp, passes: int) -> tuple[float, float, float]:  # type: ignore[no-untyped-def]
    """`identify_ekf` as `torchfric train` runs it (compiled, `passes` full passes, no early
    stop): (total s, pass 1 s including the one-time compile, median s of the other passes)."""
    t0 = time.perf_counter()
    res = identify_ekf(
        model, exp, EKFTuning(passes=passes, tolerance=0.0, rollback=False, compile=True)
    )
    total = time.perf_counter() - t0
    rest = sorted(r.seconds for r in res.history[1:])
    return total, res.history[0].seconds, rest[len(rest) // 2] if rest else float("nan")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json")
    p.add_argument("--identify-only", type=int, metavar="PASSES", help=argparse.SUPPRESS)
    p.add_argument("--samples", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.identify_only:  # section 5's fresh process: prints its JSON row
        torch.set_num_threads(1)
        exp = rig_data()
        model = prefit(ArmModel(make_friction("tanh", 3), inertia=0.03, viscous=0.01, c_m=16.0), [exp]).model
        if args.samples:  # the record repeated to `samples` (the memory row)
            reps = -(-args.samples // exp.n)
            t = torch.arange(exp.n * reps, dtype=F64) * exp.dt
            exp = make_experiment(t, exp.u.repeat(reps), exp.q.repeat(reps), qdot=exp.qdot.repeat(reps))
            exp = exp.slice(0, args.samples)
        row = identification(model, exp, args.identify_only)
        print(json.dumps([*row, peak_rss_mb(), exp.n]))
        return
    torch.set_num_threads(1)
    # The first calls below include the C build: build into a folder of this run's own.
    os.environ["TORCHFRIC_CACHE"] = tempfile.mkdtemp(prefix="torchfric-bench-")
    exp = rig_data()
    out: dict = {"single": [], "baselines": {}, "batched": [], "scaling": []}
    n_c, n_e, n_n = (3000, 200, 3000) if args.quick else (20000, 600, 30000)

    print("## 1. One filter, real code path (run_pass), float64, rig data")
    print("| model | k | eager steps/s | Inductor scan steps/s (first call s) "
          "| native steps/s (first call s) | native / Inductor |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for kind, size in [("tanh", 3), ("tanh", 10), ("tanh", 30), ("polytopic", 3),
                       ("polytopic", 5), ("polytopic", 9)]:  # fmt: skip
        model = prefit(ArmModel(make_friction(kind, size), inertia=0.03,
                                viscous=0.01 if kind == "tanh" else None, c_m=16.0), [exp]).model  # fmt: skip
        eager, _, _ = time_pass(model, exp, n_e, compile=False)
        ind, ind_first, _ = time_pass(model, exp, n_c, compile=True, native=False)
        nat, nat_first, path = time_pass(model, exp, n_n, compile=True, native=True)
        out["single"].append({"model": f"{kind}({size})", "k": model.num_parameters,
                              "eager": eager, "inductor": ind, "inductor_compile_s": ind_first,
                              "native": nat, "native_compile_s": nat_first, "native_path": path})  # fmt: skip
        note = "" if path == "native" else f" ({path}: step above the native size ceiling)"
        print(f"| {kind}({size}) | {model.num_parameters} | {eager:,.0f} | {ind:,.0f} ({ind_first:.1f}) "
              f"| {nat:,.0f} ({nat_first:.1f}){note} | {nat / ind:.1f} |", flush=True)  # fmt: skip

    tanh3 = prefit(
        ArmModel(make_friction("tanh", 3), inertia=0.03, viscous=0.01, c_m=16.0), [exp]
    ).model
    print("\n## 2. Baselines, tanh(3), same data, same machine, same run")
    np_rate, diff = numpy_baseline(tanh3, exp, n_e * 5)
    ours, ind = out["single"][0]["native"], out["single"][0]["inductor"]
    fp = filterpy_baseline(tanh3, exp, n_e * 5)
    out["baselines"] = {"numpy_analytic": np_rate, "numpy_max_diff": diff, "torchfric": ours,
                        "torchfric_inductor": ind, "filterpy": fp and fp[0],
                        "filterpy_max_diff": fp and fp[1]}  # fmt: skip
    print("| implementation | steps/s | torchfric (native) is faster by |")
    print("|---|---|---|")
    print(f"| torchfric, generated C (the default; autograd Jacobians) | {ours:,.0f} | 1.0 |")
    print(f"| torchfric, Inductor scan | {ind:,.0f} | {ours / ind:.1f}x |")
    print(f"| numpy, hand-derived Jacobian (max diff to torchfric over 50 steps {diff:.1e}) "
          f"| {np_rate:,.0f} | {ours / np_rate:.0f}x |")  # fmt: skip
    if fp is None:
        print('| filterpy | – | not installed (pip install -e ".[bench]"); not measured |')
    else:
        print(f"| filterpy `ExtendedKalmanFilter`, the numpy RK4 map and Jacobian plugged in "
              f"(max diff {fp[1]:.1e}) | {fp[0]:,.0f} | {ours / fp[0]:.0f}x |", flush=True)  # fmt: skip

    print("\n## 3. Batched ensembles, tanh(3), the masked step in chunks of 1000 samples")
    print("| K filters | native filter-steps/s (first call s) | Inductor scan filter-steps/s "
          "(first call s) | native / Inductor |")  # fmt: skip
    print("|---|---|---|---|")
    for K in [1, 9, 16, 64, 256, 1024]:
        n = 1000 if args.quick or K >= 256 else 4000
        nat, nat_first, path = batched(tanh3, exp, K, 4 * n)
        ind, ind_first, _ = batched(tanh3, exp, K, n, native=False)
        out["batched"].append({"K": K, "native": nat, "native_compile_s": nat_first,
                               "native_path": path, "inductor": ind, "inductor_compile_s": ind_first})  # fmt: skip
        print(f"| {K} | {nat:,.0f} ({nat_first:.1f}) | {ind:,.0f} ({ind_first:.1f}) "
              f"| {nat / ind:.1f} |", flush=True)  # fmt: skip

    print("\n## 4. Pass time against samples (default path, tanh(3)); peak memory")
    print("| samples | seconds | steps/s |")
    print("|---|---|---|")
    reps = 34  # 34 × 30 s at 1 kHz > 1 M samples
    long = torch.cat([exp.u] * reps), torch.cat([exp.q] * reps), torch.cat([exp.qdot] * reps)
    t_long = torch.arange(long[0].numel(), dtype=F64) * exp.dt
    big = make_experiment(t_long, long[0], long[1], qdot=long[2])
    for n in [1000, 10000] if args.quick else [1000, 10000, 100000, 1000000]:
        rate, _, _ = time_pass(tanh3, big, n, compile=True)
        out["scaling"].append({"samples": n, "seconds": n / rate, "steps_per_s": rate})
        print(f"| {n:,} | {n / rate:.2f} | {rate:,.0f} |", flush=True)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["peak_rss_mb"] = rss

    passes = 3 if args.quick else 10
    print(f"\n## 5. identify_ekf, tanh(3), {passes} passes over the rig's 30 s identification data")
    print("| build cache | samples | total s | pass 1 s (with the one-time build) "
          "| later passes, median s | peak RSS MB |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    # In fresh processes, as `torchfric train` would run it: the build is in pass 1. The first
    # process finds an empty cache folder, the second the library the first one built.
    out["identify"] = []
    with tempfile.TemporaryDirectory() as cache:
        long = 100_000 if args.quick else 1_000_000
        for label, samples in [("empty", 0), ("cached", 0), ("cached", long)]:
            run = subprocess.run(
                [sys.executable, __file__, "--identify-only", str(passes), "--samples", str(samples)],
                capture_output=True, text=True, check=True, env={**os.environ, "TORCHFRIC_CACHE": cache},
            )  # fmt: skip
            total, first, later, rss, n = json.loads(run.stdout.strip().splitlines()[-1])
            out["identify"].append({"cache": label, "samples": n, "passes": passes, "total_s": total,
                                    "pass1_s": first, "later_s": later, "peak_rss_mb": rss})  # fmt: skip
            print(f"| {label} | {n:,} | {total:.1f} | {first:.1f} | {later:.2f} | {rss:.0f} |", flush=True)
    print(f"\npeak resident memory of this whole benchmark process: {rss:.0f} MB "
          "(run_pass keeps sums, not per-sample history)")  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
