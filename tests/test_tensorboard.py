"""What a run writes for TensorBoard, read back with the tensorboard library: the config as
text, hparams that the HParams tab compares across runs, named innovation channels, residual
figures and the friction band, and every ensemble member's trajectory over every pass."""

from __future__ import annotations

import json
import math
import pathlib

import pytest
from rig_configs import rig_config

from torchfric.app.artifacts.checkpoint import read_checkpoint
from torchfric.app.cli import main
from torchfric.app.config import Config
from torchfric.app.run.monitors import ekf_scalars
from torchfric.app.run.tensorboard_log import final_metrics, hparam_values
from torchfric.estimators.passes import PassRecord

PNG = b"\x89PNG\r\n\x1a\n"


def _events(run: pathlib.Path):  # noqa: ANN202 - tensorboard's EventAccumulator
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    acc.Reload()
    return acc


def _config(tmp: pathlib.Path, name: str, **estimator: object) -> pathlib.Path:
    """The rig config with `estimator`'s keys (no ensemble unless given), tolerance 0."""
    keys = {"ensemble": None, "tolerance": 0, **estimator}
    return rig_config(tmp, name, data={"test": []}, estimator=keys)


def _record(innovation_rms: list[float]) -> PassRecord:
    return PassRecord(
        index=1, theta=[0.0], parameters={"inertia": 1.0}, trace_P=1.0, trace_P_theta=0.5,
        innovation_rms=innovation_rms, nis=2.0, loglik=-3.0, rel_change=0.1, seconds=0.1,
        samples=10,
    )  # fmt: skip


def test_innovation_channels_are_named_by_what_is_measured() -> None:
    both = ekf_scalars(_record([0.1, 0.2]))
    assert both["ekf/innovation_rms/q"] == 0.1 and both["ekf/innovation_rms/qdot"] == 0.2
    assert not any(k.endswith(("/0", "/1")) for k in both)
    assert "ekf/innovation_rms/q" in ekf_scalars(_record([0.3]), "position")
    velocity = ekf_scalars(_record([0.3]), "velocity")
    assert velocity["ekf/innovation_rms/qdot"] == 0.3 and "ekf/innovation_rms/q" not in velocity
    with pytest.raises(ValueError):  # a record that does not fit the measure is a bug
        ekf_scalars(_record([0.3]), "both")


def test_hparams_are_the_flattened_config_and_the_final_numbers(tmp_path: pathlib.Path) -> None:
    cfg = Config.load(_config(tmp_path, "h", passes=3))
    values = hparam_values(cfg.to_dict())
    assert values["estimator.passes"] == 3 and values["estimator.tolerance"] == 0
    assert values["data.train"] == "[rig:identification]" and values["data.test"] == "[]"
    assert values["estimator.compile"] == "true" and values["data.stop"] == "none"
    assert values["estimator.r"] == "[0.001, 0.01]" and values["data.columns"] == "{}"
    assert values["log.figure_every"] == "auto" and values["name"] == "h"
    assert all(isinstance(v, int | float | str) and not isinstance(v, bool)
               for v in values.values())  # fmt: skip

    def leaves(d: dict) -> int:
        return sum(leaves(v) if isinstance(v, dict) and v else 1 for v in d.values())

    assert len(values) == leaves(cfg.to_dict())
    metrics = {
        "inertia": 0.03, "best_pass": 2, "passes": 3, "converged": False, "seconds": 1.5,
        "validation": {"val": {"fit_q": 97.0, "fit_qdot": float("nan"), "rms_q": 0.1}},
    }  # fmt: skip
    assert final_metrics(metrics) == {
        "final/inertia": 0.03, "final/best_pass": 2.0, "final/passes": 3.0,
        "final/converged": 0.0, "final/seconds": 1.5, "final/validation/val/fit_q": 97.0,
    }  # fmt: skip


def _session_groups(logdir: pathlib.Path) -> dict[str, tuple[dict, dict[str, float]]]:
    """What the HParams tab lists for `logdir`: by run, its hparams and metric values."""
    from tensorboard import context
    from tensorboard.backend.event_processing import data_provider, plugin_event_multiplexer
    from tensorboard.plugins import base_plugin
    from tensorboard.plugins.hparams import api_pb2, backend_context, list_session_groups

    mux = plugin_event_multiplexer.EventMultiplexer(size_guidance={"scalars": 0, "tensors": 0})
    mux.AddRunsFromDirectory(str(logdir))
    mux.Reload()
    provider = data_provider.MultiplexerDataProvider(mux, str(logdir))
    tb = base_plugin.TBContext(logdir=str(logdir), multiplexer=mux, data_provider=provider)
    request = api_pb2.ListSessionGroupsRequest(
        start_index=0, slice_size=100, include_metrics=True,
        allowed_statuses=[api_pb2.STATUS_UNKNOWN, api_pb2.STATUS_SUCCESS],
    )  # fmt: skip
    handler = list_session_groups.Handler(
        context.RequestContext(), backend_context.Context(tb), "", request
    )
    return {
        g.name: (dict(g.hparams), {m.name.tag: m.value for m in g.metric_values})
        for g in handler.run().session_groups
    }


def test_a_runs_events_hold_its_config_hparams_named_channels_and_figures(
    tmp_path: pathlib.Path, worker_cache: pathlib.Path
) -> None:
    from tensorboard.plugins.hparams import metadata

    cfg = _config(tmp_path, "short", ensemble=0)
    short = ["--quiet", "--set", "data.stop=3000"]
    assert main(["train", str(cfg), *short, "--set", "estimator.passes=2"]) == 0
    assert main(["train", str(cfg), *short, "--set", "estimator.passes=1"]) == 0
    runs = [tmp_path / "runs" / "short", tmp_path / "runs" / "short-2"]
    acc = _events(runs[0])
    metrics = json.loads((runs[0] / "metrics.json").read_text())
    tags = acc.Tags()
    # the resolved config, as written to config.toml, in a code block
    text = acc.Tensors("config/text_summary")[0].tensor_proto.string_val[0].decode()
    assert text == f"```toml\n{(runs[0] / 'config.toml').read_text()}```"
    # named channels
    scalars = set(tags["scalars"])
    assert {"ekf/innovation_rms/q", "ekf/innovation_rms/qdot"} <= scalars
    assert not {"ekf/innovation_rms/0", "ekf/innovation_rms/1"} & scalars
    # hparams in the run's own events: every config key, the final metrics also as scalars
    content = acc.PluginTagToContent(metadata.PLUGIN_NAME)
    experiment = metadata.parse_experiment_plugin_data(content[metadata.EXPERIMENT_TAG])
    start = metadata.parse_session_start_info_plugin_data(content[metadata.SESSION_START_INFO_TAG])
    declared = {m.name.tag for m in experiment.metric_infos}
    final = final_metrics(metrics)
    assert declared == set(final) and declared <= scalars
    assert {"final/validation/validation/fit_q", "final/best_pass", "final/converged"} <= declared
    for tag, value in final.items():
        assert acc.Scalars(tag)[-1].value == pytest.approx(value, rel=1e-6)
    config = Config.loads((runs[0] / "config.toml").read_text())
    expected = hparam_values(config.to_dict())
    assert set(start.hparams) == set(expected) == {h.name for h in experiment.hparam_infos}
    for key, value in expected.items():
        got = start.hparams[key]
        assert (got.string_value if isinstance(value, str) else got.number_value) == value, key
    # figures: friction curve (with its band at the end), responses and residuals, as PNGs
    for tag in ("friction_curve", "validation/validation", "residuals/validation"):
        images = acc.Images(tag)
        assert [e.step for e in images] == [0, 2], tag
        assert all(e.encoded_image_string[:8] == PNG and e.width > 400 for e in images)
    start_curve, end_curve = acc.Images("friction_curve")
    assert end_curve.height > start_curve.height  # the end's has the band's width panel
    # the HParams tab compares the two runs, each with its own config and metrics
    groups = _session_groups(tmp_path / "runs")
    assert set(groups) == {"short", "short-2"}
    for run in runs:
        hp, values = groups[run.name]
        m = json.loads((run / "metrics.json").read_text())
        assert hp["estimator.passes"].number_value == m["passes"]
        fit = m["validation"]["validation"]["fit_q"]
        assert values["final/validation/validation/fit_q"] == pytest.approx(fit, rel=1e-6)


def test_every_ensemble_member_has_its_trajectory_over_every_pass(
    tmp_path: pathlib.Path, worker_cache: pathlib.Path
) -> None:
    from tensorboard.plugins.custom_scalar import layout_pb2

    cfg = _config(
        tmp_path, "ens", passes=3, ensemble=3, ensemble_q_scales=[1.0, 10.0],
        ensemble_r_scales=[1.0],
    )  # fmt: skip
    assert main(["train", str(cfg), "--quiet", "--set", "data.stop=1200"]) == 0
    run = tmp_path / "runs" / "ens"
    acc = _events(run)
    state = read_checkpoint(run / "passes" / "ensemble_003.pt")["estimator"]["state"]
    histories = state["histories"]
    assert len(histories) == 6
    scalars = set(acc.Tags()["scalars"])
    longest = 0
    for i, history in enumerate(histories):
        for key in ("inertia", "loglik"):
            events = acc.Scalars(f"ensemble/member_{i}/{key}")
            assert [e.step for e in events] == [r["index"] for r in history]  # one per pass
            truth = [r["parameters"]["inertia"] if key == "inertia" else r["loglik"]
                     for r in history]  # fmt: skip
            assert [e.value for e in events] == pytest.approx(truth, rel=1e-6)
        longest = max(longest, len(history))
    assert longest == 3 and f"ensemble/member_{len(histories)}/inertia" not in scalars
    # the Custom Scalars tab overlays the members, one chart per quantity
    raw = acc.Tensors("custom_scalars__config__")[0].tensor_proto.string_val[0]
    charts = {c.title: c for cat in layout_pb2.Layout.FromString(raw).category for c in cat.chart}
    assert list(charts["inertia of each member"].multiline.tag) == [r"ensemble/member_\d+/inertia"]
    assert list(charts["log-likelihood of each member"].multiline.tag) == [
        r"ensemble/member_\d+/loglik"
    ]
    # the kept member under the single filter's tags, named channels included
    assert {"ekf/innovation_rms/q", "ekf/innovation_rms/qdot"} <= scalars
    assert math.isfinite(acc.Scalars("final/inertia")[-1].value)
