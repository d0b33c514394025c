"""torchfric: grey-box identification of machines with friction (Hensen et al.).

Public API (the CLI is a thin layer over it)::

    arm = torchfric.ArmModel(friction=torchfric.OddTanhFriction(3), inertia=0.05, viscous=0.01, c_m=16.0)
    x = torchfric.simulate(arm, t, u, x0)
    result = torchfric.identify_ekf(arm, experiments, tuning)
    arm = torchfric.load_checkpoint("checkpoints/arm_tanh_ekf.pt")
    result = torchfric.fit("config.toml", **overrides)   # the CLI's train, same defaults
"""

from typing import TYPE_CHECKING

from .lazy import lazy_names
from .version import __version__

# Every name loads on first use (PEP 562), so that `import torchfric` costs nothing until a name
# is used and `torchfric --help` never imports torch. Name → the module that defines it.
_LAZY: dict[str, str] = {
    **dict.fromkeys(
        ["Experiment", "load_experiment", "make_experiment", "reconstruct_velocity", "save_csv"],
        "data",
    ),
    **dict.fromkeys(["DivergenceError", "TorchfricError"], "errors"),
    **dict.fromkeys(
        [
            "Callback",
            "EKFCallback",
            "EKFResult",
            "EKFState",
            "EKFTuning",
            "EnsembleResult",
            "EnsembleSpec",
            "Innovation",
            "OECallback",
            "OEResult",
            "OETuning",
            "PassRecord",
            "PrefitResult",
            "fit_percent",
            "friction_band",
            "identify_ekf",
            "identify_ekf_ensemble",
            "identify_output_error",
            "predict",
            "prefit",
            "score_simulation",
            "update",
        ],
        "estimators",
    ),  # fmt: skip
    **dict.fromkeys(
        [
            "FRICTIONS",
            "ArmModel",
            "CoulombFriction",
            "Friction",
            "OddTanhFriction",
            "PolytopicFriction",
            "StribeckFriction",
            "export_model",
            "make_friction",
            "simulate",
        ],
        "models",
    ),  # fmt: skip
    # The app layer (config files, checkpoints, runs) sits above everything else; the public
    # face reaches these few names of it.
    "Config": "app.config",
    "load_checkpoint": "app.artifacts",
    "read_checkpoint": "app.artifacts",
    "save_checkpoint": "app.artifacts",
    "fit": "app.run",
    "TrainResult": "app.run",
}

if TYPE_CHECKING:  # what the names are, for type checkers and editors
    from .data import Experiment, load_experiment, make_experiment, reconstruct_velocity, save_csv
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
        export_model,
        make_friction,
        simulate,
    )


__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)

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
    "TrainResult",
    "export_model",
    "fit",
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
