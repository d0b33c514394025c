"""Measured experiments: the `Experiment` record, file readers, velocity reconstruction, data
checks, and the synthetic rig (`torchfric.data.rig`), the embedded default data set.

Everything here depends only on numpy/torch and torchfric's leaf modules (errors, files,
resources); the estimators and the runs layer import from here, never the other way.
"""

from .experiment import (
    DEFAULT_CUTOFF_HZ,
    VELOCITY_METHODS,
    Experiment,
    data_warnings,
    highpass_derivative,
    load_experiment,
    make_experiment,
    reconstruct_velocity,
    save_csv,
    validate_experiment,
    zero_phase_acceleration,
    zero_phase_derivative,
)

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "VELOCITY_METHODS",
    "Experiment",
    "data_warnings",
    "highpass_derivative",
    "load_experiment",
    "make_experiment",
    "reconstruct_velocity",
    "save_csv",
    "validate_experiment",
    "zero_phase_acceleration",
    "zero_phase_derivative",
]
