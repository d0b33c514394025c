"""Reference implementations the EKF tests compare against (test helpers, not library code)."""

from __future__ import annotations

from torch import Tensor
from torch.func import jacrev

from torchfric.estimators.ekf import Propagator
from torchfric.models.arm import ArmModel
from torchfric.models.simulate import rk4_step

__all__ = ["make_reference_flow"]


def make_reference_flow(model: ArmModel, substeps: int) -> Propagator:
    """Reference for tests: the same RK4 map as `torchfric.estimators.ekf.make_propagator`,
    Φ_x by `torch.func.jacrev` through all stages."""

    def flow(z: Tensor, u: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        x, theta = z[:2], z[2:]
        fric, arm = model.split(theta)
        h = dt / substeps
        for _ in range(substeps):
            x = rk4_step(model, x, u, h, fric, arm)
        return x, x

    def propagate(z: Tensor, u: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        jac, x_next = jacrev(flow, has_aux=True)(z, u, dt)
        return x_next, jac

    return propagate
