"""The ± σ a run reports: the prediction-error sandwich covariance at the kept θ.

An EKF run ends with the filter's own ``P_θθ``; on synthetic axes its σ were 10–1000× narrower
than the real error (it has absorbed the data once per pass under an assumed noise model).
`attach_covariance` replaces it, in the run's estimator state, with the covariance of
`torchfric.estimators.covariance.pem_covariance` — the observed information of the fixed-θ
innovations' likelihood over all identification records, sandwiched with the measured
long-run covariance of its score — under the kept member's tuning. The filter's own matrix is
kept beside it (``filter_P_theta``), so is the tuning the filter ran with, in absolute units
(``tuning``: what `torchfric track` then uses). Everything that shows a σ (summary, metrics,
report, the curve's band, `evaluate`) reads ``P_theta`` and so shows the new one.

metrics.json gains ``covariance`` (method, samples, blocks, the Newey–West bandwidth, the
correlation matrix, and the Newton step to the likelihood's maximum in σ units) and
``identifiability`` (pairs with |ρ| > 0.99 and near-null directions, by name).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import torch

from ..data import Experiment
from ..errors import TorchfricError
from ..estimators.covariance import noise_model, pem_refine
from ..models.arm import ArmModel
from .config import Config

__all__ = ["attach_covariance", "PHYSICAL"]

PHYSICAL = ("inertia", "viscous", "offset", "gravity", "asymmetric", "c_m", "lugre_")
"""White-box names: a non-identifiable direction that involves one of them is a warning; one
inside the black-box curve alone (two neurons that trade off) is a note."""


def attach_covariance(
    cfg: Config,
    final: ArmModel,
    train: list[Experiment],
    state: dict[str, Any],
    extra: dict[str, Any],
    say: Callable[[str], None],
) -> None:
    """Replace ``state["P_theta"]`` by the sandwich covariance at ``state["theta"]`` and add
    ``covariance`` and ``identifiability`` to `extra` (see the module docstring). When it
    cannot be computed, the filter's matrix stays and a warning says why."""
    tuning = _position_only(cfg.estimator.ekf_tuning().resolved(train))
    q_scale, r_scale = extra.get("tuning_scales", (1.0, 1.0))
    theta = torch.as_tensor(state["theta"], dtype=torch.float64)
    P_filter = torch.as_tensor(state["P_theta"], dtype=torch.float64)
    state["tuning"] = _tuning_dict(dataclasses.replace(
        tuning, q_state=tuple(q_scale * x for x in tuning.q_state),  # type: ignore[arg-type]
        r=tuple(r_scale * x for x in tuning.r)))  # fmt: skip
    try:
        q_scale, r_scale = noise_model(
            final, train, tuning, theta, q_scale=q_scale, r_scale=r_scale
        )
        polished, pem, trace = pem_refine(
            final, train, tuning, theta, q_scale=q_scale, r_scale=r_scale, iterations=8
        )
    except TorchfricError as err:
        extra.setdefault("covariance_warnings", []).append(
            f"the ± σ are the filter's own P_θθ (too narrow as a rule): {err}"
        )
        return
    if len(trace) > 1:  # the prediction-error maximum lies elsewhere: the model moves there
        final.set_theta(polished)
        state["filter_theta"], state["theta"] = theta, polished.clone()
        extra["polished"] = {"steps": len(trace) - 1, "loglik_gain": trace[-1] - trace[0]}
        say(
            f"  prediction-error polish: {len(trace) - 1} Newton step(s) from the kept pass, "
            f"innovation log-likelihood +{trace[-1] - trace[0]:.3g}"
        )
    state["filter_P_theta"] = P_filter
    state["P_theta"] = pem.cov
    extra["covariance"] = {**pem.to_dict(), "noise_model": {
        "q_state": [q_scale * x for x in tuning.q_state], "r": [r_scale * x for x in tuning.r],
        "measure": tuning.measure}}  # fmt: skip
    ident = pem.identifiability
    extra["identifiability"] = {**ident.to_dict(), "messages": _messages(ident)}
    say(
        f"  covariance: prediction-error sandwich over {pem.samples} samples "
        f"({pem.blocks} blocks, bandwidth {pem.bandwidth})"
        + ("" if ident.ok else f"; {len(_messages(ident))} identifiability note(s)")
    )


def _position_only(tuning: Any) -> Any:
    """The tuning with q as the only measurement (its own R entry). The reconstructed velocity
    is q filtered, not a second sensor: counting it as one counts q's information twice, and a
    causal differentiator's lag biases M (measured: +0.03 % at 2 σ on every seed of a
    Coulomb-friction axis). A run that measures q̇ alone (``measure = "velocity"``) keeps it."""
    from ..estimators.ekf import MEASUREMENTS

    if tuning.measure != "both":
        return tuning
    r = tuple(tuning.r)[MEASUREMENTS["both"].index(0)]
    return dataclasses.replace(tuning, measure="position", r=(r,))


def _messages(ident: Any) -> list[str]:
    """The identifiability lines: those that involve a white-box parameter as they are, those
    inside the black-box curve marked "(within the friction curve)" (the curve itself can
    still be determined: two neurons that trade off draw the same curve)."""
    out = []
    for (names, _), message in zip(ident.groups, ident.messages, strict=True):
        physical = any(n.startswith(PHYSICAL) for n in names)
        out.append(message if physical else f"(within the friction curve) {message}")
    return sorted(out, key=lambda m: m.startswith("(within"))


def _tuning_dict(tuning: Any) -> dict[str, Any]:
    return {
        k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(tuning).items()
    }
