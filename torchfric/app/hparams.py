"""What a run gives TensorBoard's HParams tab: its config keys and its final metrics.

`hparam_values` flattens the resolved config into dotted keys with scalar values (the types the
HParams tab sorts and filters: numbers, strings, and booleans as "true"/"false"; lists and
missing values as text), and `final_metrics` picks the numbers that compare runs from
``metrics.json``, under the ``final/`` tags that `TensorBoardLog.log_hparams` also logs as
scalars: the HParams tab reads a metric's value from the scalar of the same tag in the run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

__all__ = ["hparam_values", "final_metrics"]

# metrics.json keys that compare runs, in this order (present ones only)
_FINAL_KEYS = ("inertia", "best_pass", "passes", "epochs", "converged", "seconds")


def _text(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_text(v) for v in value) + "]"
    return str(value)


def hparam_values(config: Mapping[str, Any], prefix: str = "") -> dict[str, float | str]:
    """The config (`Config.to_dict`) as ``{"estimator.passes": 10, "data.train":
    "[rig:identification]", "estimator.compile": "true", …}``: tables become dotted keys,
    an empty table is the text "{}"."""
    out: dict[str, float | str] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(hparam_values(value, f"{name}.") if value else {name: "{}"})
        elif isinstance(value, int | float) and not isinstance(value, bool):
            out[name] = value
        else:
            out[name] = _text(value)
    return out


def final_metrics(metrics: Mapping[str, Any]) -> dict[str, float]:
    """The run's final numbers by TensorBoard tag: ``final/inertia``, ``final/best_pass``,
    ``final/passes`` (``final/epochs``), ``final/converged`` (1 or 0), ``final/seconds`` and
    ``final/validation/<record>/fit_q`` and ``…/fit_qdot``. Missing or non-finite ones are left
    out."""
    out: dict[str, float] = {}
    for key in _FINAL_KEYS:
        value = metrics.get(key)
        if isinstance(value, bool):
            value = 1.0 if value else 0.0
        if isinstance(value, int | float) and math.isfinite(value):
            out[f"final/{key}"] = float(value)
    for name, fits in (metrics.get("validation") or {}).items():
        for key in ("fit_q", "fit_qdot"):
            value = fits.get(key)
            if isinstance(value, int | float) and math.isfinite(value):
                out[f"final/validation/{name}/{key}"] = float(value)
    return out
