"""Measured experiments: the `Experiment` record, file readers, velocity reconstruction, data
checks, and the synthetic rig (`torchfric.data.rig`), the embedded default data set.

Modules: `experiment` (the record and its validation), `readers` (load_experiment, save_csv;
`guards` checks a file before it is read), `velocity` (derivatives of the position), `checks`
(data_warnings, position_step), `convert` (array conversion shared by them), and the rig: `rig`
(the named experiments and their files), `rig_model` (parameters and simulation),
`excitation` (inputs).

Everything here depends only on numpy/torch and torchfric's leaf modules (errors, files,
resources); the estimators and the app layer import from here, never the other way.
"""

from .checks import data_warnings, position_step
from .experiment import Experiment, make_experiment, validate_experiment
from .readers import load_experiment, load_segments, save_csv
from .velocity import (
    DEFAULT_CUTOFF_HZ,
    VELOCITY_METHODS,
    highpass_derivative,
    quiet_cutoff_hz,
    reconstruct_velocity,
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
    "load_segments",
    "make_experiment",
    "position_step",
    "quiet_cutoff_hz",
    "reconstruct_velocity",
    "save_csv",
    "validate_experiment",
    "zero_phase_acceleration",
    "zero_phase_derivative",
]
