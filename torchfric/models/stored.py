"""Friction modules rebuilt from the physical values a spec or checkpoint stores.

`ArmModel.spec` stores each friction parameter by name in physical units (``W1``, ``sigma``, …);
`stored_friction` turns such a record back into the module, whatever its kind, with the
constructor's own argument names. Values at the edge of their domain are nudged inside it: a
log-stored parameter whose exp underflowed to 0.0 becomes the smallest positive double, and a
bounded tanh slope (`OddTanhFriction.min_slope`) stored at its bound moves just above it; a
caller with the exact θ (`load_checkpoint`) sets it afterwards.
"""

from __future__ import annotations

from typing import Any

from .friction import Friction, make_friction

__all__ = ["stored_friction"]

_TINY = 5e-324  # smallest positive double
_POSITIVE = {"sigma", "Fc", "Fs", "vs"}  # friction parameters stored as logarithms

# Parameter name → constructor argument, per friction kind.
_FRICTION_ARG: dict[str, dict[str, str]] = {
    "tanh": {"W1": "w1", "W2": "w2"},
    "polytopic": {"a": "a", "b": "b", "c": "c", "sigma": "sigma"},
    "coulomb": {"Fc": "fc"},
    "stribeck": {"Fc": "fc", "Fs": "fs", "vs": "vs"},
}


def stored_friction(f: dict[str, Any], log_positive: bool) -> Friction:
    """The friction module of a spec's ``"friction"`` record ``{kind, size, kwargs, values}``."""
    lo = float(f["kwargs"].get("min_slope", 0.0)) if log_positive else 0.0
    values = {
        _FRICTION_ARG[f["kind"]].get(k, k.lower()): (
            [max(x, _TINY) for x in v] if isinstance(v, list) else max(v, _TINY)
        )
        if k in _POSITIVE
        else ([max(x, lo * (1.0 + 1e-12)) for x in v] if lo and k == "W1" else v)
        for k, v in f["values"].items()
    }
    return make_friction(f["kind"], int(f["size"]), **f["kwargs"], **values)
