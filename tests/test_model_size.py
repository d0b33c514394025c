"""``model.size = "auto"``: the friction's size chosen from data (`torchfric.estimators.sizing`).

The data come from a model of KNOWN size: a tanh(2) arm (neurons of slope 0.5 and 5 s/rad, so
that both shape the curve over the excited speeds and one neuron cannot stand in for both,
inertia 0.0292, viscous 0.01, c_m 16) simulated by `torchfric.models.simulate` under the first
3 s of the rig's identification excitation, positions quantised to the rig's encoder (2e-4 rad),
velocity from the paper's high-pass differentiator. Every candidate starts from its own pre-fit
and runs the run's default ensemble (Q × {÷10, 1, ×10}, R × {÷10, 1, ×10}, 10 passes).

Measured (sizes 1–4; ℓ: concentrated innovation log-likelihood, BIC = −2 ℓ + k ln 3000):

====  ==  ========  =========
size  k   ℓ         BIC
====  ==  ========  =========
1     4   14375.0   −28718.0
2     6   14472.1   −28896.2   chosen
3     8   14472.1   −28880.1
4     10  14471.3   −28862.6
====  ==  ========  =========

The true model itself scores ℓ = 14460.5 (its best Q/R ratio of the grid): the sizes above 2
gain nothing, and one neuron loses 97.
"""

from __future__ import annotations

import json
import math
import pathlib

import pytest
import torch

from torchfric.app.commands.check import check_run
from torchfric.app.config import Config
from torchfric.app.run import train
from torchfric.app.run.autosize import choose_size
from torchfric.app.run.outcome import summary_lines
from torchfric.data.experiment import Experiment, make_experiment
from torchfric.data.readers import save_csv
from torchfric.data.rig import RigParameters, excitation
from torchfric.errors import TorchfricError
from torchfric.estimators.prefit import prefit
from torchfric.estimators.settings import RUN_ENSEMBLE, EKFTuning
from torchfric.estimators.sizing import compare_sizes, concentrated_loglik
from torchfric.models.arm import ArmModel
from torchfric.models.friction import OddTanhFriction
from torchfric.models.simulate import simulate

N_SAMPLES = 3000


@pytest.fixture(scope="module")
def record() -> Experiment:
    """3 s of a tanh(2) arm under the rig's excitation, quantised, velocity reconstructed."""
    true = ArmModel(
        OddTanhFriction(2, w1=[0.5, 5.0], w2=[0.1, 0.15]), inertia=0.0292, viscous=0.01, c_m=16.0
    )
    rig = RigParameters()
    u = torch.as_tensor(excitation("identification", duration=30.0, seed=2)[:N_SAMPLES])
    t = torch.arange(N_SAMPLES, dtype=torch.float64) * rig.dt
    with torch.no_grad():
        x = simulate(true, t, u, torch.zeros(2))
    q = torch.round(x[:, 0] / rig.quantum) * rig.quantum
    return make_experiment(t, u, q, name="tanh2").with_velocity()


def _starts(exp: Experiment, sizes: range) -> dict[int, ArmModel]:
    v_scale = float(torch.quantile(exp.qdot.abs(), 0.95))
    out = {}
    for n in sizes:
        friction = OddTanhFriction(n, velocity_scale=v_scale, torque_scale=0.1)
        out[n] = prefit(ArmModel(friction, inertia=0.03, viscous=0.01, c_m=16.0), [exp]).model
    return out


def test_auto_recovers_the_size_of_synthetic_data(record: Experiment) -> None:
    starts = _starts(record, range(1, 5))
    result = compare_sizes(starts, [record], EKFTuning(), RUN_ENSEMBLE)
    assert result.batched  # tanh sizes nest: one batch of tanh(4)
    assert result.chosen == 2
    by_size = {s.size: s for s in result.scores}
    assert [s.size for s in result.scores] == [1, 2, 3, 4]
    assert [s.parameters for s in result.scores] == [4, 6, 8, 10]
    assert [s.chosen for s in result.scores] == [False, True, False, False]
    # one neuron cannot draw this curve (measured: ℓ lower by 97); more than two gain less than
    # their penalty (measured: nothing, against ln 3000 = 8 per parameter)
    assert by_size[2].loglik - by_size[1].loglik > 50.0
    for n in (3, 4):
        assert by_size[n].bic > by_size[2].bic + 10.0
        assert by_size[n].loglik - by_size[2].loglik < (n - 2) * math.log(N_SAMPLES)
    for s in result.scores:
        assert s.bic == pytest.approx(-2.0 * s.loglik + s.parameters * math.log(N_SAMPLES))
        assert s.members == 9 and s.diverged == 0 and 0 <= s.member < 9
    table = result.to_dict()
    assert table["criterion"] == "bic_innovations" and table["chosen"] == 2
    assert table["samples"] == N_SAMPLES and len(table["table"]) == 4


def test_a_padded_size_filters_exactly_as_the_size_alone(record: Experiment) -> None:
    """tanh(1) and tanh(2) as members of the tanh(3) batch (extra neurons zero, with zero
    variance) give the log-likelihoods, kept members and passes of their own filters."""
    starts = _starts(record, range(1, 4))
    tuning = EKFTuning(passes=3)
    spec = RUN_ENSEMBLE
    together = compare_sizes(starts, [record], tuning, spec)
    assert together.batched
    for score in together.scores[:2]:
        alone = compare_sizes({score.size: starts[score.size]}, [record], tuning, spec)
        assert not alone.batched
        mine = alone.scores[0]
        assert score.loglik == pytest.approx(mine.loglik, rel=1e-12, abs=0.0)
        assert (score.member, score.passes) == (mine.member, mine.passes)


def test_the_concentrated_likelihood_is_the_maximum_over_the_noise_scale() -> None:
    """ℓ(λ) = −½ (Σ nis / λ + Σ ln det S + m N ln λ + m N ln 2π) peaks at the closed form."""
    samples, channels = 500, 2
    nis, logdet = 1234.5, -8000.0
    mn = samples * channels

    def ll(lam: float) -> float:
        return -0.5 * (nis / lam + logdet + mn * math.log(lam) + mn * math.log(2 * math.pi))

    best = float(concentrated_loglik(torch.tensor(ll(1.0)), torch.tensor(nis), samples, channels))
    assert best == pytest.approx(ll(nis / mn), rel=1e-12)
    # no λ on a grid of ratio 10^0.002 beats it; the nearest is half a step (Δ ln λ = 0.0023)
    # away, which costs ¼ m N Δ² = 0.0013
    grid = [ll(lam) for lam in torch.logspace(-2, 2, 2001).tolist()]
    assert 0.0 <= best - max(grid) < 2e-3


def _config(tmp_path: pathlib.Path, **model: object) -> Config:
    return Config.from_dict(
        {
            "name": "sized",
            "out_dir": str(tmp_path / "runs"),
            "data": {"train": [str(tmp_path / "tanh2.csv")], "validation": []},
            "model": {"c_m": 16.0, **model},
        }
    )


def test_a_run_with_size_auto_trains_the_chosen_size(
    record: Experiment, tmp_path: pathlib.Path
) -> None:
    save_csv(tmp_path / "tanh2.csv", record, include_qdot=False)
    cfg = _config(tmp_path, size="auto", sizes=[3, 1, 2])
    assert cfg.model.sizes == (1, 2, 3)
    assert "size auto" in check_run(cfg)  # check starts the largest size; runs no filter
    lines: list[str] = []
    result = train(cfg, say=lines.append)
    assert result.model.friction.size == 2
    sizes = result.metrics["sizes"]
    assert sizes["chosen"] == 2 and sizes["friction"] == "tanh"
    assert [r["size"] for r in sizes["table"]] == [1, 2, 3]
    assert [r["chosen"] for r in sizes["table"]] == [False, True, False]
    saved = json.loads((result.run_dir / "metrics.json").read_text())
    assert saved["sizes"]["table"] == sizes["table"]
    assert 'size = "auto"' in (result.run_dir / "config.toml").read_text()
    assert "<h2>Model size</h2>" in (result.run_dir / "report.html").read_text()
    summary = summary_lines(result.metrics, {"run": str(result.run_dir)})
    assert any(line.startswith("model size tanh 2 chosen by BIC") for line in summary)
    assert any(line.endswith("← chosen") and line.split()[0] == "2" for line in summary)
    assert any('model.size = "auto"' in line for line in lines)
    # an integer size runs no sizing and records no table
    plain, table = choose_size(_config(tmp_path, size=2), [record])
    assert table is None and plain.model.size == 2


@pytest.mark.parametrize(
    ("model", "message"),
    [
        ({"size": "big"}, 'model.size = "big" is a string, expected "auto" or an integer >= 1'),
        ({"size": 0}, "model.size = 0 is out of range"),
        ({"size": 3, "sizes": [1, 2]}, 'lists the sizes that model.size = "auto" tries'),
        ({"size": "auto", "sizes": [0, 2]}, "model.sizes = [0, 2] is an array, expected an arr"),
        ({"size": "auto", "sizes": 3}, "model.sizes = 3 is an integer, expected an array"),
        ({"size": "auto", "sizes": [1.5]}, "expected an array of integers >= 1"),
        ({"size": "auto", "friction": "polytopic", "sizes": [3, 4]}, "holds even sizes ([4])"),
        ({"size": "auto", "friction": "coulomb"}, 'model.friction = "coulomb" has no size'),
        ({"size": "auto", "init": "warm.pt"}, "model.init is a checkpoint"),
    ],
)
def test_bad_size_values_are_one_line_errors(
    tmp_path: pathlib.Path, model: dict[str, object], message: str
) -> None:
    with pytest.raises(TorchfricError) as err:
        Config.from_dict({"model": model}, base_dir=tmp_path, check_files=False)
    text = str(err.value)
    assert message in text
    assert "\n" not in text
