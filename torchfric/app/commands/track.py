"""``torchfric track CHECKPOINT DATA --out DIR``: follow a machine on-line from an identified model.

The checkpoint's θ and ``P_θθ`` start the recursive EKF (`torchfric.estimators.tracking`) over a
record, or over a file that is still being written (``--follow``), with the filter tuning of the
run that made the checkpoint and the ``[track]`` settings of its config (``--set track.KEY=V``).
Into its own new directory it writes, as it goes:

- ``track.csv``: ``t`` and every parameter's value and σ (physical units), a row every
  ``--every`` samples; the σ are the filter's times the run's own ratio of reported to filter σ
  (`band_scale`), measured again on the changed machine after each change
  (`torchfric.app.commands.bands`);
- ``events.json``: ``{"changes": [t, …], "detector": {…}, "band_scale": {name: factor},
  "remeasured": [{change, t, samples, band_scale, seconds}, …], "warnings": […]}``
  (`start_notes`), rewritten at each change;
- at the end: ``final.pt`` (an ordinary checkpoint of the last estimate: evaluate, simulate,
  export, train's ``model.init`` take it), ``track.png`` (the parameter tracks with ±2σ and the
  change times) and TensorBoard logs (the same tracks, per sample index).

"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from typing import Any

from ...errors import TorchfricError
from ...files import atomic_write_text, json_safe

__all__ = ["cmd_track"]

_BLOCK = 100  # tracker rows converted and written to track.csv at a time


def cmd_track(args: argparse.Namespace) -> int:
    if args.every < 1:
        raise TorchfricError(f"--every must be an integer >= 1, got {args.every}")
    if args.idle <= 0:
        raise TorchfricError(f"--idle must be > 0 seconds, got {args.idle}")
    from .evaluate import load_for_eval

    for item in args.set or []:
        if not item.startswith(("track.", "estimator.")):
            raise TorchfricError(
                f"--set {item}: torchfric track takes track.* and estimator.* keys (its settings "
                "and the filter's tuning); the record is read as the run read its records, with "
                "--column and --position-unit for another file's columns and unit"
            )
    model, cfg, exp, unit, raw = load_for_eval(args)
    if args.set:
        cfg = cfg.with_overrides(list(args.set))
    out = pathlib.Path(args.out)
    if not args.data.startswith("rig:") and pathlib.Path(args.data).resolve() == out.resolve():
        raise TorchfricError(f"--out {out} is the data file; give a new directory")
    if out.exists() and not out.is_dir():
        raise TorchfricError(f"--out {out} is a file; torchfric track writes into a directory: "
                             "give a new one")  # fmt: skip
    if out.exists() and any(out.iterdir()):
        raise TorchfricError(
            f"--out {out} exists and is not empty; torchfric track writes only into a new or "
            "empty directory, never over an earlier one: give another --out"
        )
    out.mkdir(parents=True, exist_ok=True)
    session = _Session(model, cfg, raw, exp, out, args)
    try:
        session.feed(exp)
        if args.follow:
            session.follow(args)
    except KeyboardInterrupt:
        sys.stderr.write("interrupted: writing what was tracked so far\n")
    except TorchfricError:  # a diverged filter: what was tracked before it is kept, then the error
        if session.ts:
            session.finish()
        raise
    session.finish()
    return 0


def _tuning(raw: dict[str, Any], cfg: Any, exp: Any) -> Any:
    """The run's EKF tuning in absolute units: as the run resolved it (its checkpoint's
    ``estimator.state.tuning``), else resolved at this record's velocity scale."""
    import dataclasses

    tuning = cfg.estimator.ekf_tuning()
    stored = (raw.get("estimator") or {}).get("state", {}).get("tuning")
    if stored:
        fields = {f.name for f in dataclasses.fields(tuning)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in stored.items()}
        return dataclasses.replace(tuning, **{k: v for k, v in values.items() if k in fields})
    return tuning.resolved([exp])


class _Session:
    """One tracking run: the tracker, its open output files, and the rows so far."""

    def __init__(self, model, cfg, raw, exp, run: pathlib.Path, args) -> None:  # type: ignore[no-untyped-def]
        import torch

        from ...estimators.tracking import Tracker

        self.model, self.cfg, self.run, self.args = model, cfg, run, args
        self.settings = cfg.track  # a TrackSettings, checked (`sections.TrackConfig`)
        tuning = _tuning(raw, cfg, exp)
        theta, P_theta, self.scale = _start(raw, model, self.settings)
        self.tuning, self.run_scale = tuning, self.scale
        self.remeasured: list[dict[str, Any]] = []  # the band scale re-measured after changes
        self.notes = start_notes(raw)
        self.tracker = Tracker(model, theta, P_theta, tuning, self.settings, float(exp.dt),
                               every=args.every, compile=tuning.compile)  # fmt: skip
        self.measure = tuning.measure
        # per row: the time, the physical values and their σ; the last θ and P_θθ for final.pt
        self.ts: list[float] = []
        self.values: list[list[float]] = []
        self.stds: list[list[float]] = []
        self.last: tuple[Any, Any] | None = None
        self.seen = 0
        self.seconds = 0.0  # in the tracking loop itself (filter, detector, rows)
        self.first: tuple[float, int] | None = None  # (seconds, samples) of the first chunk
        self.t0 = time.perf_counter()
        self.names = list(model.theta_names)
        self.csv = open(run / "track.csv", "w", encoding="utf-8")  # noqa: SIM115 (kept open)
        cols = ["t"] + [c for n in self.names for c in (n, f"{n}_std")]
        self.csv.write(",".join(cols) + "\n")
        self._events()
        self.torch = torch

    def feed(self, exp: Any) -> None:
        """Track the samples of `exp` beyond those already seen."""
        from ...estimators.tracking import tracking_data

        t, u, y = tracking_data(exp, self.measure)
        if self.seen >= t.numel():
            return
        t, u, y = t[self.seen :], u[self.seen :], y[self.seen :]
        changes = len(self.tracker.changes)
        start = time.perf_counter()
        block = []
        for row in self.tracker.run(t, u, y):
            if self.first is None:  # the session's first chunk builds or loads the C code
                self.first = (time.perf_counter() - start, self.tracker.samples)
            found = self.tracker.changes
            if len(found) > changes:
                self._events()
                for c in found[changes:]:
                    self._say(f"change detected at t = {c:.3f} s; P_θθ re-opened")
                changes = len(found)
            if found and len(self.remeasured) < len(found):
                if row.t >= found[-1] + self.settings.holdoff:  # the changed machine's window
                    if block:
                        self._write(block)
                        block = []
                    self._remeasure(exp, found[-1], row)
            block.append(row)
            if len(block) == _BLOCK:
                self._write(block)
                block = []
        if block:
            self._write(block)
        self.seconds += time.perf_counter() - start
        self.seen += t.numel()
        self._say(f"{self.seen} samples tracked, t = {float(t[-1]):.3f} s")

    def _remeasure(self, exp: Any, change: float, row: Any) -> None:
        """The scale measured again on the changed machine (`remeasured_scale`) over the
        samples from the change to `row`; the rows from there on are shown with the larger of
        it and the run's, per parameter (`torchfric.app.commands.bands`)."""
        from .bands import remeasured_scale

        began = time.perf_counter()
        scale, entry = remeasured_scale(self.model, exp, self.tuning, change, row)
        entry["seconds"] = time.perf_counter() - began
        self.remeasured.append(entry)
        if scale is None:
            self._say(f"σ after the change at {change:.3f} s not re-measured: {entry['failed']}")
            return
        self.scale = self.torch.maximum(self.run_scale, scale)
        self._events()
        self._say(f"σ re-measured on {entry['samples']} samples after the change at "
                  f"{change:.3f} s")  # fmt: skip

    def _write(self, rows: list[Any]) -> None:
        """Rows of the tracker into track.csv (flushed) and the session's tracks."""
        from ...estimators.uncertainty import physical_std

        torch = self.torch
        thetas = torch.stack([r.theta for r in rows])
        values = self.model.to_physical(thetas)
        variances = torch.stack([torch.diagonal(r.P_theta) for r in rows]) * self.scale**2
        stds = physical_std(self.model, thetas, variances)
        table = torch.stack([values, stds], dim=-1).reshape(len(rows), -1).tolist()
        for row, cells in zip(rows, table, strict=True):
            self.csv.write(",".join(map(repr, [row.t, *cells])) + "\n")
        self.csv.flush()
        self.ts.extend(r.t for r in rows)
        self.values.extend(values.tolist())
        self.stds.extend(stds.tolist())
        self.last = (rows[-1].theta, rows[-1].P_theta)

    def follow(self, args: argparse.Namespace) -> None:
        """Re-read the growing file and track its new samples, until `args.idle` seconds pass
        without any."""
        from ..run import load_record

        last = time.monotonic()
        while time.monotonic() - last < args.idle:
            time.sleep(min(1.0, args.idle / 10))
            try:  # the record as the first read took it (`load_for_eval`'s data config)
                exp, _ = load_record(self.cfg, args.data)
            except TorchfricError:
                continue  # a row being written: read again at the next poll
            if exp.n > self.seen:
                self.feed(exp)
                last = time.monotonic()

    def finish(self) -> None:
        self.csv.close()
        self._events()
        if self.last is None:
            raise TorchfricError(
                "no sample was tracked: the record has fewer than 2 samples, or tracking stopped "
                "before its first chunk"
            )
        theta, P_theta = self.last
        final = self.model.set_theta(theta)
        _final_checkpoint(final, self.cfg, theta, (P_theta, self.scale), self.run, self.tracker,
                          self.seen)  # fmt: skip
        figure = _track_figure(self.model.theta_names, self)
        from ..artifacts import pixels, png_from_pixels

        px = pixels(figure)
        (self.run / "track.png").write_bytes(png_from_pixels(px))
        _tensorboard(self.run, self.model.theta_names, self, px)
        seconds = time.perf_counter() - self.t0
        first_s, first_n = self.first or (0.0, 0)
        aside = sum(e["seconds"] for e in self.remeasured)  # once per change, not per sample
        rate = (self.tracker.samples - first_n) / max(self.seconds - first_s - aside, 1e-9)
        print(
            f"torchfric: tracked {self.seen} samples in {self.seconds:.2f} s ({rate:,.0f} "
            f"samples/s, {rate * float(self.tracker.dt):,.0f}× real time, after a first chunk "
            f"of {first_s:.2f} s that built or loaded the filter's C code; {seconds:.1f} s with "
            "the outputs)"
        )
        if self.remeasured:
            print(f"σ re-measured on the changed machine after {len(self.remeasured)} change(s) "
                  f"in {aside:.1f} s (events.json: remeasured)")  # fmt: skip
        wide = {n: f for n, f in zip(self.names, self.scale.tolist(), strict=True) if f > 1.0}
        if wide:
            factors = ", ".join(f"{n} ×{f:.3g}" for n, f in wide.items())
            again = " (re-measured after the last change)" if self.remeasured else ""
            print(f"σ shown     the filter's × the run's reported/filter σ{again}: {factors}")
        print("changes     " + (", ".join(f"{c:.3f} s" for c in self.tracker.changes) or "none"))
        for note in self.notes:
            print(f"warning     {note}")
        for label, name in (("tracks", "track.csv"), ("events", "events.json"),
                            ("checkpoint", "final.pt"), ("figure", "track.png")):  # fmt: skip
            print(f"{label:<11} {self.run / name}")
        print(f"tensorboard tensorboard --logdir {self.run}")

    def _events(self) -> None:
        det = self.tracker.detector
        detector = None
        if det is not None:
            detector = {
                "statistic": "one-sided CUSUM of the NIS block means, each scored by min(z, its rarity in the calibration)",
                "block_samples": det.block,
                "threshold": det.threshold,
                "false_alarm_hours": self.settings.false_alarm_hours,
                "calibrate_s": self.settings.calibrate,
                "holdoff_s": self.settings.holdoff,
            }
        scale = dict(zip(self.names, self.scale.tolist(), strict=True))
        body = {"changes": list(self.tracker.changes), "detector": detector, "band_scale": scale,
                "remeasured": self.remeasured, "warnings": self.notes}  # fmt: skip
        atomic_write_text(self.run / "events.json", json.dumps(json_safe(body)[0], indent=1) + "\n")

    def _say(self, text: str) -> None:
        if not self.args.quiet:
            sys.stderr.write(f"  {text}\n")


def _start(raw: dict, model: Any, settings: Any) -> tuple[Any, Any, Any]:
    """θ and ``P_θθ`` to start from, and the scale of the σ the tracker shows: the checkpoint's
    estimator state, else its θ with ``reopen · I`` (output error keeps no covariance).

    Of an EKF run's two matrices the tracker takes the filter's own (``filter_P_theta``), the
    belief a filter had at the end of its passes, and not the reported σ (``P_theta``): those
    also hold the distance between the run's two estimates and the class's bias, which a
    filter's prior must not hold — a direction the data barely pins, given a variance 1e5
    times the filter's, lets that direction take up every change (and the detector, which
    reads the innovations, then sees none). A checkpoint without it (written before the
    confidence stage) gives its ``P_theta``.

    The scale (`torchfric.app.commands.bands.band_scale`) is what the run measured of its own
    filter: the reported σ over the filter's, per parameter; the σ the tracker shows
    (track.csv, the figure, final.pt's ``P_theta``) are its filter's times that factor."""
    import torch

    from .bands import band_scale

    theta = model.get_theta()
    state = (raw.get("estimator") or {}).get("state") or {}
    k = theta.numel()
    ones = torch.ones(k, dtype=torch.float64)

    def usable(P: Any) -> bool:
        return P is not None and tuple(P.shape) == (k, k) and bool(torch.isfinite(P).all())

    own, reported = state.get("filter_P_theta"), state.get("P_theta")
    if usable(own):
        own = torch.as_tensor(own, dtype=torch.float64).clone()
        scale = band_scale(reported, own) if usable(reported) else ones
        return theta, own, scale
    if usable(reported):
        return theta, torch.as_tensor(reported, dtype=torch.float64).clone(), ones
    return theta, settings.reopen * torch.eye(k, dtype=torch.float64), ones


def start_notes(raw: dict) -> list[str]:
    """What makes the σ the tracker shows, or its start, less trustworthy than a run of this
    version gives: a checkpoint without the run's two covariances (the σ shown are then the
    filter's own: on the machines of docs/results.md they held M and b in 0–47 % of the rows
    against 89–100 % with the run's scale), and a run that did not converge (its filter's
    wide directions take a change up, so the detector sees less of it)."""
    state = (raw.get("estimator") or {}).get("state") or {}
    notes = []
    if state.get("P_theta") is not None and state.get("filter_P_theta") is None:
        notes.append(
            "this checkpoint holds only its filter's covariance (written before the run's "
            "reported σ were kept beside it): until a change the σ shown are the filter's own, "
            "which on a record with coloured noise are several times too narrow; train again "
            "with this version for σ that hold the truth"
        )
    if (raw.get("metrics") or {}).get("converged") is False:
        notes.append(
            "the run behind this checkpoint did not converge (its summary said what to change): "
            "directions its filter left wide can take a change up unseen"
        )
    return notes


def _final_checkpoint(model, cfg, theta, belief, run, tracker, samples) -> None:  # type: ignore[no-untyped-def]
    """final.pt: the last θ, its shown covariance (``P_theta``: the filter's scaled by
    `band_scale`, as track.csv shows it) and the filter's own (``filter_P_theta``: a later
    `track` starts from it and finds the same scale)."""
    from ..artifacts import build_checkpoint, save_checkpoint

    P_theta, scale = belief
    shown = scale[:, None] * P_theta * scale[None, :]
    state = {"method": "track", "theta": theta.clone(), "P_theta": shown,
             "filter_P_theta": P_theta.clone()}  # fmt: skip
    payload = build_checkpoint(
        model,
        config=cfg,
        estimator_state=state,
        metrics={
            "dt": float(tracker.dt),
            "inertia": float(model.inertia.detach()),
            "tracked_samples": samples,
            "changes": list(tracker.changes),
        },  # fmt: skip
        data_fingerprints={},
        name=run.name,
        complete=True,
        method="ekf",
    )
    save_checkpoint(run / "final.pt", payload)


def _track_figure(names, session):  # type: ignore[no-untyped-def]
    """The parameter tracks (physical values) with ±2σ bands and the change times."""
    import math

    import numpy as np

    from ..artifacts import subplots

    names, changes = list(names), session.tracker.changes
    t = np.array(session.ts)
    vals, stds = np.array(session.values), np.array(session.stds)
    cols = 3 if len(names) > 4 else 2
    nrows = math.ceil(len(names) / cols)
    fig, axes = subplots(nrows, cols, figsize=(4.2 * cols, 2.3 * nrows), squeeze=False)
    for i, ax in enumerate(axes.flat):
        if i >= len(names):
            ax.set_visible(False)
            continue
        lo, hi = vals[:, i] - 2 * stds[:, i], vals[:, i] + 2 * stds[:, i]
        ax.fill_between(t, lo, hi, color="C0", alpha=0.25, lw=0)
        ax.plot(t, vals[:, i], "C0", lw=1.0)
        _robust_limits(ax, lo, hi)
        for c in changes:
            ax.axvline(c, color="C3", lw=1.0, ls="--")
            if i == 0:  # each change's time, once, at the top of the first panel
                ax.text(c, 0.98, f" {c:.1f} s", color="C3", fontsize=7, va="top",
                        transform=ax.get_xaxis_transform())  # fmt: skip
        ax.set_title(names[i], fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]", fontsize=8)
    fig.suptitle(f"tracked parameters, ±2σ; red: {len(changes)} detected change(s)", fontsize=10)
    fig.tight_layout()
    return fig


def _robust_limits(ax, lo, hi) -> None:  # type: ignore[no-untyped-def]
    """The panel's y range from the 1st to the 99th percentile of its band, when the whole
    band spans more than three times that (a re-opened P_θθ's spike after a change would
    otherwise flatten every other row of the track)."""
    import numpy as np

    low, high = np.nanpercentile(lo, 1), np.nanpercentile(hi, 99)
    span = high - low
    if np.isfinite(span) and span > 0 and np.nanmax(hi) - np.nanmin(lo) > 3 * span:
        ax.set_ylim(low - 0.1 * span, high + 0.1 * span)


def _tensorboard(run, names, session, px) -> None:  # type: ignore[no-untyped-def]
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(log_dir=str(run))
    try:
        dt = float(session.tracker.dt)
        for t, values, stds in zip(session.ts, session.values, session.stds, strict=True):
            step = round(t / dt)
            for name, value, std in zip(names, values, stds, strict=True):
                writer.add_scalar(f"track/{name}", value, step)
                writer.add_scalar(f"track_std/{name}", std, step)
        for c in session.tracker.changes:
            writer.add_scalar("track/change", c, round(c / dt))
        writer.add_image("track/parameters", px, len(session.ts), dataformats="CHW")
    finally:
        writer.close()
