"""The grey-box model: friction modules, the arm (one vector field), and simulation.

- `friction`: black-box friction curves, odd and zero at zero by construction
  (`OddTanhFriction`, `PolytopicFriction`) and the white-box baselines, each with a pure
  ``evaluate(v, params)`` and a registry (`FRICTIONS`, `make_friction`);
- `arm`: `ArmModel`, whose right-hand side `arm_field` (with `arm_friction`) is the one vector
  field that simulation, the EKF, output error, the pre-fit and the TorchScript export all use;
- `simulate`: open-loop simulation on the sample grid with a zero-order hold, by torchdiffeq
  or by any engine registered in its `ENGINES` table (`torchfric.accel` registers "compiled");
- `torchscript`: the identified model as a TorchScript module that runs without torchfric
  (`export_model`), built from the same vector field.

Nothing here imports the data, estimators, accel or app layers.
"""

from .arm import ArmModel, arm_field, arm_friction
from .friction import (
    FRICTIONS,
    CoulombFriction,
    Friction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
    make_friction,
)
from .simulate import ENGINES, SOLVERS, auto_substeps, register_engine, rk4_step, simulate
from .torchscript import ExportedArm, export_model, save_exported

__all__ = [
    "ArmModel",
    "arm_field",
    "arm_friction",
    "FRICTIONS",
    "CoulombFriction",
    "Friction",
    "OddTanhFriction",
    "PolytopicFriction",
    "StribeckFriction",
    "make_friction",
    "ENGINES",
    "SOLVERS",
    "auto_substeps",
    "register_engine",
    "rk4_step",
    "simulate",
    "ExportedArm",
    "export_model",
    "save_exported",
]
