"""torchfric: grey-box identification of machines with friction (Hensen et al.).

Public API (the CLI is a thin layer over it)::

    arm = torchfric.ArmModel(friction=torchfric.OddTanhFriction(3), inertia=0.05, viscous=0.01, c_m=16.0)
    x = torchfric.simulate(arm, t, u, x0)
    result = torchfric.identify_ekf(arm, experiments, tuning)
    arm = torchfric.load_checkpoint("checkpoints/arm_tanh_ekf.pt")
"""

from importlib.metadata import PackageNotFoundError, version

from .arm import ArmModel
from .checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from .config import Config
from .data import Experiment, load_experiment, make_experiment, reconstruct_velocity, save_csv
from .ekf import EKFState, Innovation, predict, update
from .ensemble import EnsembleResult, EnsembleSpec, identify_ekf_ensemble
from .errors import DivergenceError, TorchfricError
from .export import export_model
from .friction import (
    FRICTIONS,
    CoulombFriction,
    Friction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
    make_friction,
)
from .identify import EKFCallback, EKFResult, EKFTuning, PassRecord, identify_ekf
from .metrics import fit_percent, score_simulation
from .output_error import OECallback, OEResult, OETuning, identify_output_error
from .prefit import PrefitResult, prefit
from .simulate import simulate
from .uncertainty import friction_band

try:
    __version__ = version("torchfric")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+local"

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
