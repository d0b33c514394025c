"""Room `sweep`: many runs over a search space, the best config kept (``torchfric sweep``).

- `driver`: `run_sweep` (the study, its workers, pruning, resuming);
- `space`: the search space file and drawing a trial's values;
- `trial`: one trial, an ordinary run of the config with the trial's values;
- `study`: the Optuna study and its storage; `ray_tune`: the same trials through Ray Tune;
- `outputs`: trials.csv, best.toml, sweep.png and the summary.

Imports the `config`, `artifacts` and `run` rooms. Other rooms import its names from here.
"""

from ...lazy import lazy_names

_LAZY: dict[str, str] = {"run_sweep": "driver", "summary_lines": "outputs"}

__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)
__all__ = sorted(_LAZY)
