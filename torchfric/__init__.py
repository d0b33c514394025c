"""torchfric: grey-box identification of machines with friction (Hensen et al.).

Public API (the CLI is a thin layer over it)::

    arm = torchfric.ArmModel(friction=torchfric.OddTanhFriction(3), inertia=0.05, viscous=0.01, c_m=16.0)
    x = torchfric.simulate(arm, t, u, x0)
    result = torchfric.identify_ekf(arm, experiments, tuning)
    arm = torchfric.load_checkpoint("checkpoints/arm_tanh_ekf.pt")
"""


from .data import (
    Experiment,
    load_experiment,
    make_experiment,
    reconstruct_velocity,
    save_csv,
)
from .errors import DivergenceError, TorchfricError
from .estimators.ekf import EKFState, Innovation, predict, update
from .estimators.ensemble import EnsembleResult, EnsembleSpec, identify_ekf_ensemble
from .estimators.identify import EKFCallback, EKFResult, EKFTuning, PassRecord, identify_ekf
from .estimators.metrics import fit_percent, score_simulation
from .estimators.output_error import OECallback, OEResult, OETuning, identify_output_error
from .estimators.prefit import PrefitResult, prefit
from .estimators.uncertainty import friction_band
from .models.arm import ArmModel
from .models.friction import (
    FRICTIONS,
    CoulombFriction,
    Friction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
    make_friction,
)
from .models.simulate import simulate
from .runs.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from .runs.config import Config
from .runs.export import export_model
from .version import __version__

__all__ = [
    "ArmModel",
    "Config",
    "CoulombFriction",
    "DivergenceError",
    "EKFCallback",
    "EKFResult",
    "EKFState",
    "EKFTuning",
    "Experiment",
    "FRICTIONS",
    "Friction",
    "Innovation",
    "OddTanhFriction",
    "PassRecord",
    "PolytopicFriction",
    "PrefitResult",
    "StribeckFriction",
    "TorchfricError",
    "export_model",
    "fit_percent",
    "identify_ekf",
    "identify_ekf_ensemble",
    "EnsembleSpec",
    "EnsembleResult",
    "friction_band",
    "identify_output_error",
    "OECallback",
    "OEResult",
    "OETuning",
    "load_checkpoint",
    "load_experiment",
    "make_experiment",
    "make_friction",
    "predict",
    "prefit",
    "read_checkpoint",
    "reconstruct_velocity",
    "save_checkpoint",
    "save_csv",
    "score_simulation",
    "simulate",
    "update",
    "__version__",
]
