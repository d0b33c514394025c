"""report.html and the figures it shows: the autocorrelation of the residuals, the friction
curve's ±2σ band, the parameter trajectories, and a real run's report read back as a user's
browser would (self-contained, every parameter ± σ, the FITs of metrics.json, PNGs that decode)."""

from __future__ import annotations

import base64
import html.parser
import json
import pathlib
import re
import struct

import numpy as np
import pytest
import torch
from rig_configs import rig_config

from torchfric import ArmModel, OddTanhFriction
from torchfric.app.artifacts.figures import (
    MAX_PANELS,
    autocorrelation,
    friction_figure,
    png_bytes,
    trajectory_figure,
    whiteness_bound,
)
from torchfric.app.artifacts.report import parameter_rows, report_html
from torchfric.app.cli import main
from torchfric.estimators.uncertainty import friction_band

PNG = b"\x89PNG\r\n\x1a\n"


def _png_size(data: bytes) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk (after checking the signature)."""
    assert data[:8] == PNG and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


# -- autocorrelation ---------------------------------------------------------------------------


def test_autocorrelation_equals_the_direct_sum() -> None:
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.standard_normal(777)) + 3.0  # correlated, non-zero mean
    d = x - x.mean()
    direct = np.array([d[: d.size - k] @ d[k:] for k in range(51)]) / (d @ d)
    r = autocorrelation(x, 50)
    assert r.shape == (51,) and r[0] == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(r, direct, rtol=0, atol=1e-12)
    # the largest lag uses one product only: linear, not circular, correlation
    assert autocorrelation(x, 776)[-1] == pytest.approx(d[0] * d[-1] / (d @ d), abs=1e-12)


def test_white_noise_stays_inside_its_bounds_and_a_random_walk_does_not() -> None:
    rng = np.random.default_rng(7)
    n, lags = 20_000, 200
    bound = whiteness_bound(n)
    assert bound == pytest.approx(1.96 / np.sqrt(n))
    white = autocorrelation(rng.standard_normal(n), lags)[1:]
    outside = np.mean(np.abs(white) > bound)
    assert outside <= 0.10  # ≈ 5 % expected
    # AR(1) with a = 0.8: r[k] ≈ 0.8**k, far outside the bounds for the first lags
    e = rng.standard_normal(n)
    ar = np.empty(n)
    ar[0] = e[0]
    for i in range(1, n):
        ar[i] = 0.8 * ar[i - 1] + e[i]
    r = autocorrelation(ar, lags)
    np.testing.assert_allclose(r[1:6], 0.8 ** np.arange(1, 6), rtol=0, atol=0.05)
    assert np.all(np.abs(r[1:10]) > bound)


def test_autocorrelation_of_a_constant_and_bad_lags() -> None:
    np.testing.assert_array_equal(autocorrelation(np.full(10, 2.5), 3), [1.0, 0.0, 0.0, 0.0])
    for bad in (-1, 10, 2.0):
        with pytest.raises(ValueError, match="max_lag"):
            autocorrelation(np.arange(10.0), bad)


# -- figures -----------------------------------------------------------------------------------


def _arm(n: int = 3) -> ArmModel:
    torch.manual_seed(3)
    fric = OddTanhFriction(n, w1=torch.linspace(0.5, 20.0, n), w2=0.1 * torch.randn(n))
    return ArmModel(fric, inertia=0.03, viscous=0.01, c_m=16.0)


def test_friction_figure_draws_the_delta_method_band() -> None:
    arm = _arm()
    k = arm.num_parameters
    a = torch.randn(k, k, dtype=torch.float64)
    P = 1e-3 * (a @ a.T + torch.eye(k, dtype=torch.float64))
    fig = friction_figure(arm, 4.0, "t", "rad", P)
    ax = fig.axes[0]
    band = ax.collections[0].get_paths()[0].vertices
    v = torch.linspace(-4.0, 4.0, 801, dtype=torch.float64)
    mean, std = friction_band(arm, P, v)
    # the filled polygon runs along mean − 2σ one way and mean + 2σ back
    for j in (0, 200, 400, 650, 800):
        ys = band[np.isclose(band[:, 0], float(v[j]), rtol=0, atol=1e-12), 1]
        assert min(ys) == pytest.approx(float(mean[j] - 2 * std[j]), rel=1e-9, abs=1e-12)
        assert max(ys) == pytest.approx(float(mean[j] + 2 * std[j]), rel=1e-9, abs=1e-12)
    assert float(std[0]) > 1e-3  # a band that is there to see
    # the band's width has its own panel, and the legend says the widest half-width
    width = fig.axes[1].lines[0].get_ydata()
    np.testing.assert_allclose(width, 2 * std.numpy(), rtol=1e-12)
    assert f"±{2 * float(std.max()):.3g}" in ax.get_legend().get_texts()[0].get_text()
    png_bytes(fig)
    # without a covariance (output error): one panel, no band
    plain = friction_figure(arm, 4.0, "t")
    assert len(plain.axes) == 1 and not plain.axes[0].collections
    png_bytes(plain)


def test_trajectory_figure_shows_the_arm_first_and_at_most_twelve_panels() -> None:
    arm = _arm(30)  # 60 network weights + viscous + inertia
    names = arm.theta_names
    history = [
        {"index": i, "parameters": {n: float(i + j) for j, n in enumerate(names)}, "loss": 0.1}
        for i in range(1, 5)
    ]
    fig = trajectory_figure(history, best=3)
    shown = [ax for ax in fig.axes if ax.get_visible()]
    assert len(shown) == MAX_PANELS
    assert [ax.get_title() for ax in shown[:3]] == ["inertia", "viscous", "W1[1]"]
    line = shown[0].lines[0]
    np.testing.assert_array_equal(line.get_xdata(), [1, 2, 3, 4])
    j = names.index("inertia")
    np.testing.assert_array_equal(line.get_ydata(), [i + j for i in range(1, 5)])
    title = fig.get_suptitle()
    assert "epochs" in title and "kept: epoch 3" in title
    assert f"{len(names) - MAX_PANELS} more friction weights not shown" in title
    assert _png_size(png_bytes(fig))[0] > 600
    with pytest.raises(ValueError, match="history is empty"):
        trajectory_figure([])


# -- the report's text -------------------------------------------------------------------------


def test_parameter_rows_take_both_shapes() -> None:
    assert parameter_rows({"inertia": 0.5}) == [("inertia", 0.5, None)]
    rows = parameter_rows({"a": {"value": 1.0, "std": 0.1}, "b": {"value": 2.0, "std": None}})
    assert rows == [("a", 1.0, 0.1), ("b", 2.0, None)]


def test_report_escapes_the_users_text_and_says_when_nothing_validates() -> None:
    arm = _arm()
    metrics = {
        "name": "<b>run</b>",
        "estimator": "output_error",
        "epochs": 2,
        "best_epoch": 2,
        "parameters": {n: {"value": v, "std": None} for n, v in arm.physical_parameters().items()},
        "validation": {},
        "test": {},
        "warnings": ['data "x<y>.csv" & <script>alert(1)</script>'],
    }
    history = [
        {"index": i, "parameters": arm.physical_parameters(), "loss": 1.0 / i} for i in (1, 2)
    ]
    page = report_html(
        title="<b>run</b>", model=arm, metrics=metrics, history=history, validation=[],
        scores={}, v_max=3.0,
    )  # fmt: skip
    assert "<script>" not in page and "<b>run" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page and "&lt;b&gt;run&lt;/b&gt;" in page
    assert 'class="warn"' in page and "Warnings (1)" in page
    assert "No validation data" in page
    assert "kept epoch" in page
    for name, value in arm.physical_parameters().items():
        assert f"<td>{name}</td><td class='num'>{value:.6g} ± –</td>" in page
    assert "–: not known" in page and "filter's own belief" not in page


# -- a real run's report -----------------------------------------------------------------------


class _Page(html.parser.HTMLParser):
    """Collects the attributes that could reach outside the file, the images and the text."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: list[tuple[str, str, str]] = []
        self.images: list[str] = []
        self.text: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        for key, value in attrs:
            if key in ("src", "href", "srcset", "data", "action"):
                self.refs.append((tag, key, value or ""))
            if tag == "img" and key == "src":
                self.images.append(value or "")

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def _train(tmp: pathlib.Path) -> pathlib.Path:
    cfg = rig_config(tmp, data={"test": [], "stop": 3000}, estimator={"passes": 2, "tolerance": 0})
    assert main(["train", str(cfg), "--quiet"]) == 0
    return tmp / "runs" / "short"


def test_a_runs_report_is_self_contained_and_shows_the_runs_numbers(
    tmp_path: pathlib.Path, worker_cache: pathlib.Path
) -> None:
    run = _train(tmp_path)
    metrics = json.loads((run / "metrics.json").read_text())
    text = (run / "report.html").read_text(encoding="utf-8")
    page = _Page()
    page.feed(text)
    page.close()
    assert page.tags[:2] == ["html", "head"] and "body" in page.tags
    # nothing outside the file: no links, every src a data: URI, no script, no http(s) anywhere
    assert not re.search(r"https?://", text) and "<script" not in text and "<link" not in text
    assert all(key == "src" and value.startswith("data:image/png;base64,")
               for _, key, value in page.refs)  # fmt: skip
    # friction curve, response and residuals of the one validation record, trajectories
    assert len(page.images) == 4
    sizes = [
        _png_size(base64.b64decode(src.partition(",")[2], validate=True)) for src in page.images
    ]
    assert all(w >= 500 and h >= 350 for w, h in sizes)
    body = " ".join(page.text)
    for name, entry in metrics["parameters"].items():
        value, std = (entry["value"], entry["std"]) if isinstance(entry, dict) else (entry, None)
        sd = "–" if std is None else f"{std:.3g}"
        assert f"{value:.6g} ± {sd}" in body, name
        assert name in body
    fits = metrics["validation"]["validation"]
    row = re.search(r"<td>validation</td><td>validation</td>(.*?)</tr>", text).group(1)
    cells = re.findall(r"<td class='num'>([^<]*)</td>", row)
    assert cells[:2] == [f"{fits['fit_q']:.2f}", f"{fits['fit_qdot']:.2f}"]
    assert float(cells[0]) == pytest.approx(fits["fit_q"], abs=0.005)
    assert "with its ±2σ band" in body and "converged" in body
    # the σ are said to be what they are: this EKF run's sandwich, not the filter's P_θθ
    assert metrics["covariance"]["method"] == "sandwich"
    assert "sandwich covariance" in body and "filter's own belief" not in body


def test_a_parameter_without_sigma_is_explained_by_what_the_run_had() -> None:
    # A run with a covariance gives no σ to a parameter held at its bound or not determined by
    # the data (identifiability names it); a run without one gives none at all.
    from torchfric.app.artifacts.report import _parameters

    params = {"inertia": {"value": 0.3, "std": 1e-3}, "W1[3]": {"value": 0.36, "std": None}}
    held = _parameters({"parameters": params, "covariance": {"method": "sandwich"}})
    assert "0.36 ± –" in held and "held at its bound" in held and "no covariance" not in held
    bare = _parameters({"parameters": {"W1[3]": {"value": 0.36, "std": None}}})
    assert "no covariance was computed" in bare and "held at its bound" not in bare


# -- the painter: figures drawn in a helper process --------------------------------------------
def _friction_spec_of_a_model():  # type: ignore[no-untyped-def]
    from torchfric.app.artifacts.figures import friction_spec

    model = ArmModel(OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
    P = torch.eye(model.num_parameters, dtype=torch.float64) * 1e-4
    return friction_spec(model, 5.0, "a model", "rad", P)


def test_the_painter_draws_the_same_png_as_this_process() -> None:
    """The helper's figure is byte for byte the one `render` draws here, for every spec
    submitted, in any order of collection; after `close` nothing is lost."""
    from torchfric.app.artifacts.drawing import render
    from torchfric.app.artifacts.painter import Painter

    spec = _friction_spec_of_a_model()
    history = [{"index": i, "parameters": {"inertia": 0.03 + 1e-3 * i, "viscous": 0.01}}
               for i in range(1, 4)]  # fmt: skip
    trajectory = ("trajectory", {"history": history, "best": 2})
    painter = Painter()
    painter.start()
    ids = [painter.submit(*spec), painter.submit(*trajectory), painter.submit(*spec)]
    assert painter._proc is not None  # a helper is running, not the fallback
    got = {fid: painter.png(fid) for fid in reversed(ids)}
    painter.close()
    assert got[ids[0]] == got[ids[2]] == render(*spec)
    assert got[ids[1]] == render(*trajectory)
    assert _png_size(got[ids[0]]) == (600, 520)


def test_a_painter_that_cannot_draw_falls_back_to_this_process(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A helper that dies (here: a Python that cannot import torchfric) or is switched off
    (TORCHFRIC_PAINTER=0) costs nothing but time: each figure is drawn here, the same PNG; a
    spec the helper fails on is drawn here, where its error is raised."""
    import subprocess
    import sys

    from torchfric.app.artifacts import painter as painter_module
    from torchfric.app.artifacts.drawing import render

    spec = _friction_spec_of_a_model()
    real_popen = subprocess.Popen

    def broken(args, **kwargs):  # type: ignore[no-untyped-def]
        return real_popen([sys.executable, "-c", "import sys; sys.exit(3)"], **kwargs)

    monkeypatch.setattr(painter_module.subprocess, "Popen", broken)
    dead = painter_module.Painter()
    assert dead.png(dead.submit(*spec)) == render(*spec)
    dead.close()
    monkeypatch.undo()

    monkeypatch.setattr(painter_module.sys, "executable", "")  # embedded: no Python to start
    embedded = painter_module.Painter()
    assert embedded.png(embedded.submit(*spec)) == render(*spec) and embedded._proc is None
    monkeypatch.undo()

    monkeypatch.setenv("TORCHFRIC_PAINTER", "0")
    off = painter_module.Painter()
    fid = off.submit(*spec)
    assert off._proc is None and off.ready(fid) and off.png(fid) == render(*spec)
    monkeypatch.delenv("TORCHFRIC_PAINTER")

    alive = painter_module.Painter()
    bad = alive.submit("friction", {**spec[1], "v": None})  # the helper's render raises
    with pytest.raises((TypeError, AttributeError)):
        alive.png(bad)
    good = alive.submit(*spec)
    assert alive.png(good) == render(*spec)  # the helper is still drawing
    alive.close()


def test_the_kept_figures_handed_over_early_are_not_drawn_again(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The responses, residuals and trajectories handed over when the estimator ends are the
    ones the run's end uses (only the friction curve, which needs the σ, is added); a model
    that changed in between (a polish the run keeps) gets all its figures drawn anew."""
    import dataclasses

    from torchfric.app.config import Config
    from torchfric.app.run import load_data, monitors
    from torchfric.estimators.observers import RunEnd

    class Recorder:
        def __init__(self) -> None:
            self.kinds: list[str] = []

        def submit(self, kind, spec):  # type: ignore[no-untyped-def]
            self.kinds.append(kind)
            return len(self.kinds) - 1

    recorder = Recorder()
    monkeypatch.setattr(monitors, "shared_painter", lambda: recorder)
    cfg = Config.load(rig_config(tmp_path))
    _, validation, *_ = load_data(cfg)
    scores = monitors.ValidationScores(cfg, list(validation))
    model = ArmModel(OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
    scores.update(model)
    history = [{"index": 1, "parameters": {"inertia": 0.03}}]
    drawing = monitors.KeptFigures(cfg, validation, 5.0)
    early = RunEnd(model, {"best_pass": 1}, 1, None, scores.latest, history)
    drawing.early(early)
    assert recorder.kinds == ["response", "residuals", "trajectory"]
    P = torch.eye(model.num_parameters, dtype=torch.float64) * 1e-6
    end = dataclasses.replace(early, metrics={"best_pass": 1, "inertia": 0.03}, covariance=P)
    figures = drawing.kept(end)
    assert recorder.kinds[3:] == ["friction"]  # nothing else drawn again
    assert sorted(figures) == ["friction_curve", "residuals/validation", "validation/validation"]
    assert drawing._trajectory == 2  # the painter's trajectory, not one drawn here

    polished = ArmModel(OddTanhFriction(3), inertia=0.031, viscous=0.01, c_m=16.0)
    scores.update(polished)
    drawing.early(early)
    moved = dataclasses.replace(end, model=polished, scores=scores.latest)
    del recorder.kinds[:]
    monkeypatch.setattr(monitors, "render", lambda kind, spec: b"drawn here")
    drawing.kept(moved)
    assert sorted(recorder.kinds) == ["friction", "residuals", "response"]
    assert drawing.trajectory() == b"drawn here"


def test_a_kept_polish_titles_the_friction_curve_as_polished(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The curve of a run whose polish was kept is the polished θ's, not the pass's: its
    title says so; without a kept polish it is the pass's."""
    import dataclasses

    from torchfric.app.config import Config
    from torchfric.app.run import load_data, monitors
    from torchfric.estimators.observers import RunEnd

    titles: list[str] = []

    class Recorder:
        def submit(self, kind, spec):  # type: ignore[no-untyped-def]
            if kind == "friction":
                titles.append(spec["title"])
            return len(titles)

    monkeypatch.setattr(monitors, "shared_painter", lambda: Recorder())
    monkeypatch.setattr(monitors, "render", lambda kind, spec: b"")
    cfg = Config.load(rig_config(tmp_path))
    _, validation, *_ = load_data(cfg)
    scores = monitors.ValidationScores(cfg, list(validation))
    model = ArmModel(OddTanhFriction(3), inertia=0.03, viscous=0.01, c_m=16.0)
    scores.update(model)
    P = torch.eye(model.num_parameters, dtype=torch.float64) * 1e-6
    end = RunEnd(model, {"best_pass": 3}, 3, P, scores.latest, [])
    monitors.KeptFigures(cfg, validation, 5.0).kept(end)
    polished = dataclasses.replace(end, metrics={"best_pass": 3, "polished": {"steps": 2}})
    monitors.KeptFigures(cfg, validation, 5.0).kept(polished)
    assert titles == ["pass 3", "pass 3, polished"]


@pytest.mark.parametrize("value", ["yes", "2", " 0"])
def test_an_invalid_painter_switch_is_a_one_line_error(value, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from torchfric.environment import check_environment
    from torchfric.errors import TorchfricError

    with pytest.raises(TorchfricError) as info:
        check_environment({"TORCHFRIC_PAINTER": value})
    message = str(info.value)
    assert (
        "\n" not in message
        and "TORCHFRIC_PAINTER=1" in message
        and "TORCHFRIC_PAINTER=0" in message
    )
    assert check_environment({"TORCHFRIC_PAINTER": "0"})["TORCHFRIC_PAINTER"] is False
