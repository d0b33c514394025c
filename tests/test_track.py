"""``torchfric track``: the recursive EKF against the off-line pass, the change detector's
statistics, a synthetic change found and an unchanged record left alone, the outputs (track.csv,
events.json, final.pt, the figure, TensorBoard), ``--follow`` on a growing file, and bad input."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import torchfric.accel  # noqa: F401  (the compiled step)
from torchfric.app.artifacts.checkpoint import checkpoint_config, checkpoint_model, read_checkpoint
from torchfric.app.cli import main
from torchfric.data.axis import LINEAR_AXIS, axis_record
from torchfric.data.rig import RigParameters, changing_record, excitation, simulate_rig
from torchfric.errors import TorchfricError
from torchfric.estimators.ekf import EKFState, make_propagator, make_step, run_pass
from torchfric.estimators.tracking import NisDetector, Tracker, TrackSettings, cusum_threshold

ROOT = pathlib.Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "checkpoints" / "arm_tanh_ekf.pt"


def _csv(path: pathlib.Path, rec: dict, rows: slice = slice(None)) -> None:
    cols = np.column_stack([rec["t"], rec["u"], rec["q"]])[rows]
    np.savetxt(path, cols, delimiter=",", header="t,u,q", comments="", fmt="%.17g")


def _model():  # type: ignore[no-untyped-def]
    raw = read_checkpoint(CHECKPOINT)
    return checkpoint_model(raw, CHECKPOINT), checkpoint_config(raw), raw


# ------------------------------------------------------------------------------- the filter
def test_tracking_without_parameter_noise_is_the_offline_pass() -> None:
    """With q_theta = 0, no forgetting and no detector the tracker is the off-line EKF pass:
    the same step over the same samples gives the same θ and P (chunked or not)."""
    model, cfg, raw = _model()
    tuning = cfg.estimator.ekf_tuning()
    arr = simulate_rig(RigParameters(), excitation("validation", duration=3.0, seed=4), seed=4)
    t, u, q = (torch.tensor(arr[k]) for k in ("t", "u", "q"))
    y = torch.stack([q, torch.tensor(arr["qdot_true"])], 1)
    theta, P_theta = model.get_theta(), raw["estimator"]["state"]["P_theta"]
    off = TrackSettings(q_theta=0.0, detect=False)
    tracker = Tracker(model, theta, P_theta, tuning, off, 1e-3, every=97)
    rows = list(tracker.run(t[:1500], u[:1500], y[:1500])) + list(
        tracker.run(t[1500:], u[1500:], y[1500:])
    )
    assert len(rows) == 16 + 16 and rows[-1].t == pytest.approx(float(t[-1]))
    Q, P0_xx, H, R = tuning.matrices(model.num_parameters)
    n = 2 + model.num_parameters
    x0 = torch.cat([y[0], theta])
    P0 = torch.zeros(n, n, dtype=torch.float64)
    P0[:2, :2], P0[2:, 2:] = P0_xx, P_theta
    step = make_step(make_propagator(model, tuning.substeps), compile=True)
    state, _ = run_pass(EKFState(x0, P0), u, y, torch.tensor(1e-3, dtype=torch.float64), Q, H,
                        R, step)  # fmt: skip
    torch.testing.assert_close(tracker.state.x, state.x, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(tracker.state.P, state.P, rtol=1e-8, atol=1e-16)


def test_cusum_threshold_meets_its_design_run_length() -> None:
    """Siegmund's threshold against simulation: iid unit Gaussian block means through the CUSUM
    alarm about once per ARL₀ blocks (the approximation is known to be a little conservative)."""
    for kappa in (0.5, 1.0):
        h = cusum_threshold(500.0, kappa)
        assert cusum_threshold(5000.0, kappa) > h > cusum_threshold(50.0, kappa)
        rng = np.random.default_rng(0)
        runs = []
        for _ in range(200):
            g, n = 0.0, 0
            while g <= h:
                g = max(0.0, g + rng.standard_normal() - kappa)
                n += 1
            runs.append(n)
        assert 350 < np.mean(runs) < 1000, (kappa, np.mean(runs))


def test_detector_calibrates_holds_off_and_finds_a_shift() -> None:
    """A consistent filter's NIS (χ² with 2 degrees of freedom) whose mean rises by 60 % at
    t = 20 s: one alarm, within half a second, none before (blocks of 100: near-Gaussian means),
    whatever the split of the stream into calls."""
    det = NisDetector(block=100, calibrate_blocks=50, holdoff_blocks=20,
                      threshold=cusum_threshold(1e5))  # fmt: skip
    rng = np.random.default_rng(1)
    nis = rng.chisquare(2, 30000)
    nis[20000:] *= 1.6
    t = np.arange(30000) * 1e-3
    found = det.feed(nis[:1234], t[:1234]) + det.feed(nis[1234:], t[1234:])
    assert len(found) == 1 and 20.0 < found[0] < 20.5


def _stick_slip_nis(rng: np.random.Generator, seconds: float, slip_gain: float) -> np.ndarray:
    """Per-sample NIS shaped like a stick-slip carriage's (measured there on 0.1-s blocks:
    medians 0.04 stuck and 1.2 sliding, the 90th percentile of the sliding blocks 4.3; the
    calibration's mean 0.38 and standard deviation 0.88, single slip onsets 17 of those above
    the mean): 3.3 s cycles of 2 s stuck and 1.3 s sliding, each slide opening with a burst of
    0.1–0.3 s at 3–6 times the sliding level, log-normal (σ 1) throughout; `slip_gain` scales
    the sliding part."""
    n = int(seconds * 1000)
    t = np.arange(n) * 1e-3
    phase = (t + rng.uniform(0, 3.3)) % 3.3
    cycles = n // 3300 + 2
    length = np.repeat(rng.uniform(0.1, 0.3, cycles), 3300)[:n]
    height = np.repeat(rng.uniform(3.0, 6.0, cycles), 3300)[:n]
    level = np.where(phase < 2.0, 0.04, 1.2 * slip_gain)
    level = np.where((phase >= 2.0) & (phase < 2.0 + length), level * height, level)
    return level * rng.lognormal(0.0, 1.0, n)


def test_slip_onsets_like_the_calibrations_raise_no_alarm() -> None:
    """Heavy-tailed NIS that follows the regime (stick-slip): 10 minutes unchanged raise no
    alarm on any of 5 seeds, while scoring each block by its z alone (the detector before the
    rarity was added: κ = 2, h for 1 h) raises dozens on the same blocks, as it raised 13 in
    10 minutes on the carriage this imitates."""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        quiet = _stick_slip_nis(rng, 600.0, 1.0)
        det = NisDetector.from_settings(TrackSettings(), 1e-3)
        assert det.feed(quiet, np.arange(len(quiet)) * 1e-3) == [], seed
        means = quiet.reshape(-1, 100).mean(1)
        base = means[:200]
        g, h, z_alarms = 0.0, cusum_threshold(36000.0, 2.0), 0
        for m in means[200:]:
            g = max(0.0, g + (m - base.mean()) / base.std() - 2.0)
            if g > h:
                z_alarms, g = z_alarms + 1, 0.0
        assert z_alarms >= 30, (seed, z_alarms)


def test_one_block_far_beyond_the_calibration_is_a_change() -> None:
    """The rarity keeps a block's size beyond the calibration (the fitted tail, not the rank,
    which would cap it near 2.8): χ² NIS whose single 0.1-s block at 40 s is 30 times the usual
    level is an alarm at that block (the rig's maintenance change looks like this); the same
    stream without it raises none."""
    rng = np.random.default_rng(4)
    nis = rng.chisquare(2, 120000)
    t = np.arange(len(nis)) * 1e-3
    det = NisDetector.from_settings(TrackSettings(), 1e-3)
    assert det.feed(nis, t) == []
    nis[40000:40100] *= 30.0
    det = NisDetector.from_settings(TrackSettings(), 1e-3)
    assert det.feed(nis, t) == [pytest.approx(40.099)]


def test_an_axis_record_can_change_its_friction_mid_run() -> None:
    """`axis_record(..., change=(t, after))`: the same samples as the unchanged record up to the
    change, the state carried across it (no jump in q or q̇), the motion different after it."""
    after = dataclasses.replace(LINEAR_AXIS, coulomb=1.4 * LINEAR_AXIS.coulomb)
    same = axis_record(LINEAR_AXIS, seed=3, duration=2.0, kind="validation")
    rec = axis_record(LINEAR_AXIS, seed=3, duration=2.0, kind="validation", change=(1.0, after))
    k = round(float(rec["change"]) / LINEAR_AXIS.dt)
    assert float(rec["change"]) == pytest.approx(1.0)
    for key in ("u", "q", "q_true", "qdot_true"):
        np.testing.assert_array_equal(rec[key][: k + 1], same[key][: k + 1])
    assert np.abs(np.diff(rec["qdot_true"][k - 2 : k + 3])).max() < 1e-2  # no jump: m/s per ms
    assert np.abs(rec["q_true"][-1] - same["q_true"][-1]) > 10 * LINEAR_AXIS.quantum
    with pytest.raises(TorchfricError, match="outside the record"):
        axis_record(LINEAR_AXIS, seed=3, duration=2.0, change=(5.0, after))


# ------------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def change_run(tmp_path_factory) -> tuple[pathlib.Path, dict]:  # type: ignore[no-untyped-def]
    d = tmp_path_factory.mktemp("track")
    rec = changing_record(25.0, 20.0, seed=0)  # passes the low speeds (where Fs matters) at once
    _csv(d / "rec.csv", rec)
    args = ["track", str(CHECKPOINT), str(d / "rec.csv"), "--out", str(d / "out"), "--quiet"]
    assert main(args) == 0
    return d / "out", rec


def test_a_change_is_found_within_two_seconds(change_run) -> None:  # type: ignore[no-untyped-def]
    out, rec = change_run
    events = json.loads((out / "events.json").read_text())
    assert len(events["changes"]) == 1
    assert 0.0 < events["changes"][0] - float(rec["change"]) < 2.0
    assert events["detector"]["threshold"] == pytest.approx(cusum_threshold(3600.0 / 0.1))


def test_outputs_are_complete_and_the_final_checkpoint_works(change_run, capsys) -> None:  # type: ignore[no-untyped-def]
    out, rec = change_run
    header = (out / "track.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["t", "W1[1]", "W1[1]_std"] and header[-2:] == ["inertia", "inertia_std"]
    table = np.loadtxt(out / "track.csv", delimiter=",", skiprows=1)
    assert table.shape == (np.ceil((rec["t"].size - 1) / 100), 17)
    assert np.all(table[:, 2::2] > 0) and np.all(np.isfinite(table))
    final = read_checkpoint(out / "final.pt")
    model = checkpoint_model(final, out / "final.pt")
    assert float(model.inertia.detach()) == pytest.approx(table[-1, -2], rel=1e-12)
    assert (out / "track.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["evaluate", str(out / "final.pt"), "rig:changed_validation"]) == 0
    assert "FIT %" in capsys.readouterr().out
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(out))
    acc.Reload()
    assert "track/inertia" in acc.Tags()["scalars"] and "track/change" in acc.Tags()["scalars"]
    assert len(acc.Scalars("track/inertia")) == table.shape[0]


def test_after_a_change_the_sigma_are_measured_on_the_changed_machine(change_run) -> None:  # type: ignore[no-untyped-def]
    """Once the hold-off has gathered the changed machine's samples, the prediction-error stage
    runs over them at the tracked θ and the σ shown from there on are the filter's times the
    larger of the run's ratio and the new one (events.json ``remeasured``). The committed
    checkpoint holds only its filter's P_θθ (ratio 1): its band of the rig's true viscous b
    held it in none of the rows before the change and of the hold-off; from the re-measure on
    in every row (the inertia: 35 % before, 100 % after)."""
    out, _ = change_run
    events = json.loads((out / "events.json").read_text())
    (change,) = events["changes"]
    (entry,) = events["remeasured"]
    assert entry["change"] == change and entry["t"] >= change + TrackSettings().holdoff
    assert entry["samples"] == pytest.approx(TrackSettings().holdoff / 1e-3, abs=100)
    again = np.array(list(entry["band_scale"].values()))
    np.testing.assert_allclose(list(events["band_scale"].values()), np.maximum(again, 1.0))
    header = (out / "track.csv").read_text().splitlines()[0].split(",")
    table = np.loadtxt(out / "track.csv", delimiter=",", skiprows=1)
    t, i = table[:, 0], header.index("viscous")
    held = np.abs(table[:, i] - RigParameters().sigma2) <= 2 * table[:, i + 1]
    assert held[t > entry["t"]].mean() >= 0.9
    assert held[t <= entry["t"]].mean() < 0.1


def test_a_remeasure_that_finds_no_sigma_keeps_the_runs_ratio(tmp_path, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    """When the prediction-error stage finds no σ over the changed machine's window (every
    noise model's filter unhealthy), the track goes on with the run's ratio, says why in
    events.json's ``remeasured`` entry (``failed``) and on stderr, and writes every output."""
    import torchfric.app.run as run_room

    def fails(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise TorchfricError("the fixed-θ filter diverged for every noise model")

    monkeypatch.setattr(run_room, "covariance_at", fails)
    rec = changing_record(25.0, 15.0, seed=0)
    _csv(tmp_path / "rec.csv", rec)
    out = tmp_path / "out"
    assert main(["track", str(CHECKPOINT), str(tmp_path / "rec.csv"), "--out", str(out)]) == 0
    events = json.loads((out / "events.json").read_text())
    (entry,) = events["remeasured"]
    assert entry["failed"] == "the fixed-θ filter diverged for every noise model"
    assert "band_scale" not in entry
    assert "not re-measured: the fixed-θ filter diverged" in capsys.readouterr().err
    assert set(events["band_scale"].values()) == {1.0}  # the committed run's ratio: its filter's
    for name in ("track.csv", "final.pt", "track.png"):
        assert (out / name).stat().st_size > 0


def test_an_unchanged_record_raises_no_alarm(tmp_path) -> None:  # type: ignore[no-untyped-def]
    p = RigParameters()
    rec = simulate_rig(p, excitation("validation", duration=60.0, seed=5), seed=5)
    _csv(tmp_path / "rec.csv", rec)
    assert main(["track", str(CHECKPOINT), str(tmp_path / "rec.csv"), "--out",
                 str(tmp_path / "out"), "--quiet"]) == 0  # fmt: skip
    assert json.loads((tmp_path / "out" / "events.json").read_text())["changes"] == []


def test_follow_reads_a_growing_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    rec = simulate_rig(RigParameters(), excitation("validation", duration=4.0, seed=6), seed=6)
    _csv(tmp_path / "rec.csv", rec, slice(0, 1500))
    cmd = [sys.executable, "-m", "torchfric", "track", str(CHECKPOINT), str(tmp_path / "rec.csv"),
           "--out", str(tmp_path / "out"), "--follow", "--idle", "4", "--every", "50"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)
    _csv(tmp_path / "more.csv", rec)  # the writer appends the rest
    (tmp_path / "rec.csv").write_text((tmp_path / "more.csv").read_text())
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert "tracked 4000 samples" in out
    rows = np.loadtxt(tmp_path / "out" / "track.csv", delimiter=",", skiprows=1)
    assert rows[-1, 0] == pytest.approx(rec["t"][-1])


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--every", "0"], "--every must be an integer >= 1"),
        (["--set", "track.forgetting=2"], "track.forgetting = 2.0 is out of range"),
        (["--set", "track.qtheta=1"], 'unknown key "track.qtheta"'),
        (["--set", "data.input_delay=3"], "torchfric track takes track.* and estimator.* keys"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, extra, message) -> None:  # type: ignore[no-untyped-def]
    rec = simulate_rig(RigParameters(), excitation("validation", duration=1.0, seed=1), seed=1)
    _csv(tmp_path / "rec.csv", rec)
    code = main(["track", str(CHECKPOINT), str(tmp_path / "rec.csv"), "--out",
                 str(tmp_path / "out"), *extra])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error: ") and message in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_an_earlier_output_is_never_overwritten(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    rec = simulate_rig(RigParameters(), excitation("validation", duration=1.0, seed=1), seed=1)
    _csv(tmp_path / "rec.csv", rec)
    base = ["track", str(CHECKPOINT), str(tmp_path / "rec.csv"), "--out", str(tmp_path / "out"),
            "--quiet"]  # fmt: skip
    assert main(base) == 0
    before = (tmp_path / "out" / "track.csv").read_bytes()
    capsys.readouterr()
    assert main(base) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert (tmp_path / "out" / "track.csv").read_bytes() == before
    # --out naming a file (here the earlier track.csv) says so, and the file stays as it was
    assert main([*base[:3], "--out", str(tmp_path / "out" / "track.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "is a file" in err and "\n" not in err
    assert (tmp_path / "out" / "track.csv").read_bytes() == before


def test_a_calibration_with_a_light_top_does_not_make_near_misses_alarms() -> None:
    """The tail's β is no lighter than the log-normal one the upper half implies: with β fitted
    to the top 20 blocks alone, two blocks 10 % above the calibration's largest with an
    ordinary one between raised an alarm on 2 of 20 calibrations of Gaussian block means (an
    unchanged user axis, on one CPU, at 21.4 s); a block 3× the largest and one 1.7× still
    raise one at once on all of them."""

    def calibrated(blocks: np.ndarray) -> NisDetector:
        det = NisDetector(block=1, calibrate_blocks=len(blocks), holdoff_blocks=0, threshold=1.98)
        assert det.feed(blocks, np.arange(float(len(blocks)))) == [] and det.calibrated
        return det

    for seed in range(20):
        blocks = np.abs(1.0 + 0.23 * np.random.default_rng(seed).standard_normal(200))
        top = blocks.max()
        det = calibrated(blocks)
        ordinary = det._mean + 1.36 * det._std
        assert det.feed(np.array([1.1 * top, ordinary, 1.1 * top]), np.arange(3.0)) == [], seed
        assert calibrated(blocks).feed(np.array([3 * top, 1.7 * top]), np.arange(2.0)) == [0.0]


def test_the_tracker_starts_from_the_filters_own_covariance() -> None:
    """A run's reported σ (``P_theta``) hold its class's bias; the tracker's prior is the
    filter's belief (``filter_P_theta``) where the checkpoint has it, else ``P_theta``, else
    ``reopen · I``."""
    from torchfric.app.commands.track import _start

    model, _, raw = _model()
    k = model.num_parameters
    settings = TrackSettings()
    state = raw["estimator"]["state"]
    reported, own = (
        4.0 * torch.eye(k, dtype=torch.float64),
        1e-3 * torch.eye(k, dtype=torch.float64),
    )
    both = {"estimator": {"state": {**state, "P_theta": reported, "filter_P_theta": own}}}
    assert torch.equal(_start(both, model, settings)[1], own)
    assert torch.allclose(_start(both, model, settings)[2], torch.full((k,), 4e3**0.5))
    old = {"estimator": {"state": {**state, "P_theta": reported}}}
    assert torch.equal(_start(old, model, settings)[1], reported)
    assert torch.equal(_start(old, model, settings)[2], torch.ones(k, dtype=torch.float64))
    bad = {
        "estimator": {
            "state": {**state, "P_theta": reported[:2, :2], "filter_P_theta": own * float("nan")}
        }
    }
    assert torch.equal(
        _start(bad, model, settings)[1], settings.reopen * torch.eye(k, dtype=torch.float64)
    )


def test_the_sigma_shown_are_the_filters_times_the_runs_own_ratio(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """track.csv's σ are the tracking filter's times the checkpoint's reported/filter σ ratio
    (at least 1), the filter itself unchanged by it: a checkpoint whose reported P_θθ is 9
    times its filter's (and 1/4 of it for one parameter) tracks to the same values with σ 3
    times (and 1 times) as wide; final.pt keeps both matrices, so a second `track` from it
    shows the same scale."""
    from torchfric.app.artifacts import save_checkpoint

    raw = read_checkpoint(CHECKPOINT)
    own = raw["estimator"]["state"]["P_theta"]
    k = own.shape[0]
    factor = torch.full((k,), 3.0, dtype=torch.float64)
    factor[0] = 0.5  # a reported σ narrower than the filter's: shown as the filter's
    for name, reported in (("same", own), ("wide", factor[:, None] * own * factor[None, :])):
        state = {**raw["estimator"]["state"], "P_theta": reported, "filter_P_theta": own}
        save_checkpoint(
            tmp_path / f"{name}.pt", {**raw, "estimator": {**raw["estimator"], "state": state}}
        )
    arr = simulate_rig(RigParameters(), excitation("validation", duration=2.0, seed=5), seed=5)
    _csv(tmp_path / "rec.csv", arr)
    tables = {}
    for name in ("same", "wide"):
        out = tmp_path / f"out_{name}"
        assert (
            main(
                [
                    "track",
                    str(tmp_path / f"{name}.pt"),
                    str(tmp_path / "rec.csv"),
                    "--out",
                    str(out),
                    "--quiet",
                ]
            )
            == 0
        )
        tables[name] = np.loadtxt(out / "track.csv", delimiter=",", skiprows=1)
    same, wide = tables["same"], tables["wide"]
    np.testing.assert_array_equal(same[:, 1::2], wide[:, 1::2])  # the values: the same filter
    shown = np.where(np.arange(k) == 0, 1.0, 3.0)
    np.testing.assert_allclose(wide[:, 2::2], same[:, 2::2] * shown, rtol=1e-12)
    events = json.loads((tmp_path / "out_wide" / "events.json").read_text())
    assert list(events["band_scale"].values()) == pytest.approx(list(shown), rel=1e-12)
    final = read_checkpoint(tmp_path / "out_wide" / "final.pt")["estimator"]["state"]
    expect = torch.tensor(shown)[:, None] * final["filter_P_theta"] * torch.tensor(shown)[None, :]
    assert torch.allclose(final["P_theta"], expect, rtol=1e-12, atol=0)
    again = tmp_path / "again"
    assert (
        main(
            [
                "track",
                str(tmp_path / "out_wide" / "final.pt"),
                str(tmp_path / "rec.csv"),
                "--out",
                str(again),
                "--quiet",
            ]
        )
        == 0
    )
    assert list(
        json.loads((again / "events.json").read_text())["band_scale"].values()
    ) == pytest.approx(list(shown), rel=1e-9)
    # the committed checkpoint's run stopped at its pass limit: every session says so
    assert [w.split(" (")[0] for w in events["warnings"]] == [
        "the run behind this checkpoint did not converge"
    ]


def test_a_checkpoint_without_the_runs_sigma_or_convergence_is_named() -> None:
    """`start_notes`: a checkpoint holding only its filter's P_θθ (written before the run's
    reported σ were kept beside it, as the committed reference checkpoints are) and one whose
    run did not converge each get a warning line; a converged run's with both matrices none."""
    from torchfric.app.commands.track import start_notes

    raw = read_checkpoint(CHECKPOINT)
    assert "filter_P_theta" not in raw["estimator"]["state"]
    notes = start_notes(raw)
    assert len(notes) == 2 and "only its filter's covariance" in notes[0]
    assert "did not converge" in notes[1]
    own = raw["estimator"]["state"]["P_theta"]
    state = {**raw["estimator"]["state"], "filter_P_theta": own}
    fresh = {**raw, "estimator": {**raw["estimator"], "state": state},
             "metrics": {**raw["metrics"], "converged": True}}  # fmt: skip
    assert start_notes(fresh) == []
