"""The ensemble's near members as other estimates of θ (`confidence.near_members`,
`member_spread`): where a member that simulates nearly as well puts a white-box parameter far
outside the reported σ, the σ widen by the near members' spread; otherwise they stand."""

from __future__ import annotations

import math
import pathlib
from types import SimpleNamespace

import torch

from torchfric.app.artifacts import load_checkpoint
from torchfric.app.run.confidence import NEAR_FIT, SPREAD_LIMIT, member_spread, near_members
from torchfric.estimators.ensemble import MemberSummary

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _member(index: int, score: float, status: str = "converged") -> MemberSummary:
    return MemberSummary(index, 1.0, 1.0, status, 3, -1.0, 0.1, score)


def test_near_members_score_within_two_points_and_did_not_diverge() -> None:
    scores = [90.0, 90.0 - NEAR_FIT, 90.0 - NEAR_FIT - 0.01, 89.5, math.nan, 95.0]
    status = ["converged", "rolled_back", "converged", "diverged", "running", "converged"]
    members = [_member(i, s, st) for i, (s, st) in enumerate(zip(scores, status, strict=True))]
    thetas = torch.arange(12.0, dtype=torch.float64).reshape(6, 2)
    near = near_members(SimpleNamespace(best=0, members=members, thetas=thetas))
    # the kept member itself, one 2.01 points behind, the diverged one and one without a
    # score are left out; one that scores better than the kept member counts as near
    assert [i for i, _ in near] == [1, 5]
    torch.testing.assert_close(near[0][1], thetas[1], rtol=0, atol=0)
    near[0][1][0] = -1.0  # a copy: the ensemble's θ stay
    assert thetas[1, 0] == 2.0


def test_member_spread_widens_only_past_the_limit_by_every_near_member() -> None:
    model = load_checkpoint(ROOT / "checkpoints" / "arm_tanh_ekf.pt")
    theta = model.get_theta().detach().clone()
    names = list(model.theta_names)
    k, j_m, j_b = theta.numel(), names.index("inertia"), names.index("viscous")
    sd = 1e-3 * theta.abs().clamp_min(1e-3)
    cov = torch.diag(sd**2)
    cov[0, 0] = 0.0  # held (a step neuron's steepness): no σ, and the spread gives it none
    step = torch.zeros(k, dtype=torch.float64)
    step[j_b], step[0] = 3.0 * sd[j_b], 5.0
    close = (4, theta + step)  # b 3 σ away (linearly stored: exactly)
    assert member_spread(model, theta, cov, [close]) is None
    assert member_spread(model, theta, cov, []) is None
    far_step = torch.zeros(k, dtype=torch.float64)
    far_step[j_m], far_step[1] = 2.0 * SPREAD_LIMIT * sd[j_m], 0.5
    far = (7, theta + far_step)  # M about 20 σ away (log-stored)
    out = member_spread(model, theta, cov, [close, far])
    assert out is not None
    widened, record = out
    free = torch.ones(k, dtype=torch.float64)
    free[0] = 0.0
    expected = cov + sum(torch.outer(d * free, d * free) for d in (step, far_step))
    torch.testing.assert_close(widened, expected, rtol=1e-12, atol=0)  # θ + d − θ: rounding
    assert widened[0].abs().sum() == 0  # the held entry keeps no σ
    assert record["members"] == [4, 7]
    assert record["worst"]["member"] == 7 and record["worst"]["parameter"] == "inertia"
    # the physical distance over the delta method's σ: exp(20 σ_θ) − 1 over σ_θ
    s = float(sd[j_m])
    assert math.isclose(record["worst"]["sigmas"], math.expm1(20 * s) / s, rel_tol=1e-9)


def test_the_summary_warns_of_a_spread_the_covariance_took_in(tmp_path: pathlib.Path) -> None:
    """metrics.json's ``covariance.member_spread`` becomes a warning naming the member, the
    parameter and how many σ; a run without it gets none."""
    from rig_configs import rig_config

    from torchfric.app.config import Config
    from torchfric.app.run.assessment import result_warnings

    cfg = Config.load(rig_config(tmp_path))
    model = load_checkpoint(ROOT / "checkpoints" / "arm_tanh_ekf.pt")
    record = {"members": [3, 5], "near_fit": NEAR_FIT, "limit": SPREAD_LIMIT,
              "worst": {"member": 5, "parameter": "viscous", "sigmas": 473.3}}  # fmt: skip
    base = {"inertia": 0.03, "initial_inertia": 0.03, "validation": {}}
    spread = {**base, "covariance": {"method": "sandwich", "member_spread": record}}
    text = " ".join(result_warnings(cfg, model, spread, "prefit"))
    assert "ensemble member 5 simulates within 2 FIT points of the kept one with viscous 473 σ" in text
    assert "far beyond the sandwich's σ" not in " ".join(
        result_warnings(cfg, model, {**base, "covariance": {"method": "sandwich"}}, "prefit")
    )
