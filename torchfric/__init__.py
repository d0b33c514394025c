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
from .estimators import (
    Callback,
    EKFCallback,
    EKFResult,
    EKFState,
    EKFTuning,
    EnsembleResult,
    EnsembleSpec,
    Innovation,
    OECallback,
    OEResult,
    OETuning,
    PassRecord,
    PrefitResult,
    fit_percent,
    friction_band,
    identify_ekf,
    identify_ekf_ensemble,
    identify_output_error,
    predict,
    prefit,
    score_simulation,
    update,
)
from .models import (
    FRICTIONS,
    ArmModel,
    CoulombFriction,
    Friction,
    OddTanhFriction,
    PolytopicFriction,
    StribeckFriction,
    make_friction,
    simulate,
)
from .version import __version__

# The app layer (config files, checkpoints, the export) sits above everything else and is
# imported only by the CLI; the public face reaches these few names lazily, on first use.
_FROM_APP = {
    "Config": "config",
    "load_checkpoint": "checkpoint",
    "read_checkpoint": "checkpoint",
    "save_checkpoint": "checkpoint",
    "export_model": "export",
}


def __getattr__(name: str):  # type: ignore[no-untyped-def]
    if name in _FROM_APP:
        import importlib

        value = getattr(importlib.import_module(f".app.{_FROM_APP[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'torchfric' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_FROM_APP))


__all__ = [
    "ArmModel",
    "Callback",
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
