"""Estimators: what turns data and a model into identified parameters.

- `propagation`: the sample-interval flows with their exact Jacobians (`make_propagator`;
  a dynamic model's stiff-stable step);
- `ekf`: the continuous–discrete EKF's maths — pure predict/update functions on an `EKFState`,
  Joseph form and Cholesky, the propagator (RK4 and its Jacobians), one filter pass;
- `passes`: the one pass loop (iterate, check health, roll back, keep the best, stop on
  tolerance) shared by `identify` (the single EKF, the paper's method) and `ensemble` (a batch
  of EKFs over starts and tunings, with `selection` picking a member by open-loop FIT);
- `output_error` (with `shooting`): simulation-error training by multiple shooting;
- `prefit`: the inverse-dynamics least-squares start; `uncertainty`: friction bands from P_θθ;
  `metrics`: FIT and simulation scores;
- `settings`: each estimator's settings dataclass (the config's sections build these);
- `observers`: the one `Callback` protocol every estimator reports through.

Estimators import models, data and accel; they do no file I/O and print nothing.
"""

from .ekf import EKFState, Innovation, predict, update
from .ensemble import EnsembleResult, MemberSummary, identify_ekf_ensemble
from .identify import identify_ekf
from .metrics import fit_percent, score_simulation
from .observers import (
    Callback,
    CallbackList,
    EKFCallback,
    EnsembleCallback,
    OECallback,
    RunEnd,
    RunStart,
)
from .output_error import EpochRecord, OEResult, identify_output_error
from .passes import EKFResult, PassRecord
from .prefit import PrefitResult, prefit
from .settings import EKFTuning, EnsembleSpec, OETuning
from .uncertainty import friction_band

__all__ = [
    "EKFState",
    "Innovation",
    "predict",
    "update",
    "EnsembleResult",
    "MemberSummary",
    "identify_ekf_ensemble",
    "identify_ekf",
    "fit_percent",
    "score_simulation",
    "Callback",
    "CallbackList",
    "EKFCallback",
    "EnsembleCallback",
    "OECallback",
    "RunEnd",
    "RunStart",
    "EpochRecord",
    "OEResult",
    "identify_output_error",
    "EKFResult",
    "PassRecord",
    "PrefitResult",
    "prefit",
    "EKFTuning",
    "EnsembleSpec",
    "OETuning",
    "friction_band",
]
