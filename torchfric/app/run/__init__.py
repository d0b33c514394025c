"""Room `run`: one training run, from a `Config` to a finished run directory.

- `launch`: `fit` (``train`` as one Python call), torch's settings for a run, progress on
  stderr;
- `runner`: `train` (data → initial model → estimator with observers → checkpoint);
- `inputs`: the config's data → experiments, resource checks, the initial model, the
  estimate of a run's time and memory;
- `autosize`: ``model.size = "auto"`` and ``model.dynamic = "auto"``, the sizes and the two
  friction classes tried before the run proper;
- `confidence`: the kept θ's covariance (prediction-error sandwich) and identifiability;
- `assessment`: scores and warnings of a finished model;
- `outcome`: the kept pass, the parameter table and the summary lines;
- `monitors`: the validation scorer every observer reads, the kept model's figures and the
  progress lines; `tensorboard_log`: TensorBoard and its hparams; `snapshots`: per-pass
  snapshots and resuming (typed per method); `views`: report.html and the run's observers in
  their order (`run_observers`).

Imports the `config` and `artifacts` rooms. Other rooms import its names from here.
"""

from ...lazy import lazy_names

_LAZY: dict[str, str] = {
    **dict.fromkeys(
        ["fit", "override_strings", "progress_printer", "torch_settings", "train_on_stderr"],
        "launch",
    ),
    **dict.fromkeys(["TrainResult", "train"], "runner"),
    **dict.fromkeys(
        ["check_resources", "config_model", "device_named", "initial_model", "load_data", "load_record",
         "RunEstimate", "estimate_run"],
        "inputs",
    ),
    **dict.fromkeys(["candidate_sizes", "choose_size", "sized"], "autosize"),
    **dict.fromkeys(["auto_estimate", "choose_dynamic", "with_dynamic"], "autosize"),
    **dict.fromkeys(
        ["keep_best", "parameter_lines", "parameter_table", "summary_lines"], "outcome"
    ),
    **dict.fromkeys(
        ["evaluate_model", "missing_terms", "needed_terms", "result_warnings", "scoring_engine"],
        "assessment",
    ),
    "best_member_loglik": "monitors",
    "covariance_at": "confidence",
}  # fmt: skip

__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)
__all__ = sorted(_LAZY)
