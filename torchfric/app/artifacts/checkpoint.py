"""Checkpoints: self-describing dicts of tensors and plain types, written atomically.

A checkpoint is what `build_checkpoint` returns, saved with `save_checkpoint`::

    {"format": "torchfric-checkpoint", "format_version": 1, "torchfric_version": str,
     "created": ISO-8601 str, "name": str, "config": Config.to_dict(),
     "model": ArmModel.spec(), "theta": Tensor (k,) (estimation coordinates),
     "theta_names": [str], "parameters": {name: float (physical)},
     "estimator": {"method": str, "state": {...}}, "metrics": {...},
     "data": {path or "rig:NAME": sha256 hex}, "complete": bool}

It contains nothing but tensors, str, int, float, bool, None, lists, tuples and dicts, so it loads
with ``torch.load(path, weights_only=True)`` — the only way torchfric reads one (`read_checkpoint`).
Files that would need full unpickling, truncated or corrupt files, and checkpoints of a newer
format are refused with a one-line `TorchfricError`. A checkpoint of an older format is migrated
on reading (`_FORMAT_MIGRATIONS`) or, where no migration exists, refused with one line naming the
version found, the versions read and the fix. The stored config is migrated to the current
schema by `checkpoint_config` (keys that older torchfric versions wrote and the current schema
rejects are dropped or normalised).

Writes go to a temporary file in the target folder, are flushed and fsync'ed, then renamed over
the target (`os.replace`) and the folder is fsync'ed: a crash at any moment leaves either the
previous checkpoint or the new one, never a broken file.
"""

from __future__ import annotations

import datetime
import hashlib
import io
import os
import pathlib
import pickle
import zipfile
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from ...errors import TorchfricError
from ...files import atomic_write_bytes
from ...models.arm import ArmModel
from ...version import __version__

if TYPE_CHECKING:
    from ..config import Config

__all__ = [
    "check_checkpoint_target",
    "FORMAT",
    "FORMAT_VERSION",
    "build_checkpoint",
    "save_checkpoint",
    "read_checkpoint",
    "load_checkpoint",
    "checkpoint_model",
    "checkpoint_config",
    "sha256_file",
]

FORMAT = "torchfric-checkpoint"
FORMAT_VERSION = 2
"""Bump when the layout changes incompatibly; readers refuse newer versions and migrate older
ones through `_FORMAT_MIGRATIONS`. 2: a polytopic friction's spec names its construction
beyond the outermost centres (``extrapolation``, issue 23); format 1 had only the Gaussian one."""


def _pin_gaussian_polytopic(ckpt: dict[str, Any]) -> dict[str, Any]:
    """Format 1 → 2: a polytopic model of format 1 was trained with (and must keep) the
    paper's Gaussian validity functions, not the affine continuation that is now the default."""
    model = dict(ckpt["model"])
    friction = dict(model["friction"])
    if friction["kind"] == "polytopic":
        friction["kwargs"] = {"extrapolation": "gaussian", **friction.get("kwargs", {})}
    model["friction"] = friction
    return {**ckpt, "model": model}


_FORMAT_MIGRATIONS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {
    1: _pin_gaussian_polytopic,
}
"""Format ``v`` → a function that turns a format-``v`` checkpoint dict into format ``v + 1``
(it sets ``format_version``). When FORMAT_VERSION is bumped, add the previous version here so
that existing checkpoints keep loading; a version without a path to FORMAT_VERSION is refused."""

_REQUIRED = ("model", "theta", "theta_names")
_PLAIN = (str, int, float, bool, type(None))
_ZIP_MAGIC = b"PK\x03\x04"


def sha256_file(path: str | os.PathLike[str]) -> str:
    """SHA-256 hex digest of a file's bytes (the data fingerprints of a checkpoint)."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    except OSError as exc:
        raise TorchfricError(f"cannot fingerprint {str(path)!r}: {exc.strerror}") from None
    return digest.hexdigest()


def _sanitise(value: Any, where: str) -> Any:
    """`value` with tensors detached to compact CPU copies, numpy scalars made Python numbers and
    tuples kept; anything else that is not a plain type raises (so weights_only can load it)."""
    if isinstance(value, Tensor):
        if value.layout != torch.strided or value.is_quantized:
            raise TorchfricError(f"{where} is a {value.layout} tensor; store a dense tensor")
        return value.detach().to("cpu", copy=True).contiguous()
    if type(value) in _PLAIN:
        return value
    if isinstance(value, bool | int | float | str):  # subclasses (np.float64, IntEnum, …)
        return _base(value)
    if hasattr(value, "dtype") and hasattr(value, "item") and getattr(value, "shape", None) == ():
        return _sanitise(value.item(), where)  # numpy / 0-d scalar types
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if type(k) not in (str, int):
                raise TorchfricError(
                    f"{where} has a key {k!r} of type {type(k).__name__}; use str keys"
                )
            out[k] = _sanitise(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, list | tuple):
        items = [_sanitise(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return items if isinstance(value, list) else tuple(items)
    raise TorchfricError(
        f"{where} is a {type(value).__module__}.{type(value).__qualname__}; a checkpoint holds "
        "only tensors, str, int, float, bool, None, lists, tuples and dicts (convert it, e.g. "
        "float(x), torch.as_tensor(x), dataclasses.asdict(x))"
    )


def _base(value: bool | int | float | str) -> bool | int | float | str:
    for base in (bool, int, float, str):
        if isinstance(value, base):
            return base(value)
    raise AssertionError(value)  # unreachable: the caller checked the types


def build_checkpoint(
    model: ArmModel,
    *,
    config: Any,
    estimator_state: Mapping[str, Any],
    metrics: Mapping[str, Any],
    data_fingerprints: Mapping[str, str],
    name: str,
    complete: bool,
    method: str | None = None,
) -> dict[str, Any]:
    """The checkpoint dict of `model` (see the module docstring).

    Args:
        model: the model; its θ is stored exactly and its physical values by name.
        config: a `torchfric.config.Config` or its `to_dict()`.
        estimator_state: whatever the estimator needs to resume (e.g. ``P_theta``, the pass
            index, the history as a list of dicts), tensors and plain types only.
        metrics: e.g. ``{"inertia": …, "validation": {file: {"fit_q": …}}}``.
        data_fingerprints: data path or ``"rig:NAME"`` → SHA-256 hex (`sha256_file`).
        name: the run name.
        complete: False for per-pass snapshots of a run in progress, True for the final model.
        method: estimator name; default ``config["estimator"]["method"]``.
    """
    if not isinstance(model, ArmModel):
        raise TorchfricError(f"model must be a torchfric ArmModel, got {type(model).__name__}")
    cfg = config.to_dict() if hasattr(config, "to_dict") else config
    if not isinstance(cfg, Mapping):
        raise TorchfricError(f"config must be a Config or a dict, got {type(config).__name__}")
    if method is None:
        method = str(cfg.get("estimator", {}).get("method", "ekf"))
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "torchfric_version": __version__,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "name": str(name),
        "config": dict(cfg),
        "model": model.spec(),
        "theta": model.get_theta(),
        "theta_names": list(model.theta_names),
        "parameters": model.physical_parameters(),
        "estimator": {"method": method, "state": dict(estimator_state)},
        "metrics": dict(metrics),
        "data": {str(k): str(v) for k, v in data_fingerprints.items()},
        "complete": bool(complete),
    }


def save_checkpoint(path: str | os.PathLike[str], payload: Mapping[str, Any]) -> None:
    """Write `payload` to `path` atomically (temp file, fsync, rename, fsync of the folder).

    Parent folders are created. A payload value that is not a tensor or plain type is refused
    before anything is written, so the file always loads with ``weights_only=True``.
    """
    if not isinstance(payload, Mapping):
        raise TorchfricError(f"a checkpoint payload must be a dict, got {type(payload).__name__}")
    clean = _sanitise(payload, "checkpoint")
    target = pathlib.Path(path)
    if target.is_dir():
        raise TorchfricError(f"checkpoint path {str(target)!r} is a directory; give a file name")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TorchfricError(
            f"cannot create folder {str(target.parent)!r}: {exc.strerror}"
        ) from None
    buffer = io.BytesIO()
    torch.save(clean, buffer)
    atomic_write_bytes(target, buffer.getvalue(), what="checkpoint")


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The raw checkpoint dict, read with ``torch.load(weights_only=True)`` after checks."""
    p = pathlib.Path(path)
    if not p.is_file():
        what = "is a directory" if p.is_dir() else "not found"
        raise TorchfricError(
            f"checkpoint {str(p)!r} {what} (working directory {os.getcwd()}); give the path of a "
            ".pt file written by torchfric train"
        )
    with open(p, "rb") as f:
        magic = f.read(4)
    bad = f"{p} is truncated or not a torchfric checkpoint"
    if magic != _ZIP_MAGIC:
        raise TorchfricError(f"{bad} (not a PyTorch zip archive); re-create it with torchfric")
    try:
        with zipfile.ZipFile(p) as z:
            broken = z.testzip()  # CRC of every member: catches flipped or missing bytes
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise TorchfricError(f"{bad} ({exc}); re-create it or use an earlier snapshot") from None
    if broken is not None:
        raise TorchfricError(f"{bad} (member {broken!r} fails its CRC check); it is corrupt")
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise TorchfricError(
            f"{p} contains arbitrary Python objects (not only tensors and plain types); torchfric "
            "refuses to unpickle it because that could run code from the file"
        ) from None
    except Exception as exc:  # torch raises RuntimeError/EOFError/… for damaged archives
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise TorchfricError(f"{bad} ({first})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        found = (
            f"format = {ckpt.get('format')!r}" if isinstance(ckpt, dict) else type(ckpt).__name__
        )
        raise TorchfricError(
            f"{p} is not a torchfric checkpoint ({found}, expected format = {FORMAT!r}); "
            "give a file written by torchfric train"
        )
    version = ckpt.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise TorchfricError(f"{p} has an invalid format_version {version!r}; the file is damaged")
    if version > FORMAT_VERSION:
        raise TorchfricError(
            f"{p} has checkpoint format {version}, written by a newer torchfric "
            f"({ckpt.get('torchfric_version', '?')}); this one reads format <= {FORMAT_VERSION}: "
            "upgrade torchfric"
        )
    if version < FORMAT_VERSION:
        ckpt = _migrate_format(ckpt, version, p)
    missing = [k for k in _REQUIRED if k not in ckpt]
    if missing:
        raise TorchfricError(f"{p} lacks {', '.join(missing)}; the checkpoint is incomplete")
    return ckpt


def load_checkpoint(path: str | os.PathLike[str]) -> ArmModel:
    """The `ArmModel` stored in a checkpoint, θ set exactly (physical values as identified)."""
    return checkpoint_model(read_checkpoint(path), path)


def checkpoint_model(ckpt: Mapping[str, Any], path: str | os.PathLike[str]) -> ArmModel:
    """The `ArmModel` of a checkpoint already read (`read_checkpoint`); `path` names it in
    messages."""
    try:
        model = ArmModel.from_spec(ckpt["model"])
    except TorchfricError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise TorchfricError(f"{path}: the model description is damaged ({exc!r})") from None
    names = list(ckpt["theta_names"])
    if names != model.theta_names:
        raise TorchfricError(
            f"{path}: stored theta_names {names} do not match the model's {model.theta_names}; "
            "the checkpoint is inconsistent"
        )
    theta = ckpt["theta"]
    if not isinstance(theta, Tensor):
        raise TorchfricError(f"{path}: theta is a {type(theta).__name__}, expected a tensor")
    model.set_theta(theta.to(torch.float64))
    return model


def _oldest_readable() -> int:
    """The oldest format version with a chain of migrations up to FORMAT_VERSION."""
    v = FORMAT_VERSION
    while v - 1 in _FORMAT_MIGRATIONS:
        v -= 1
    return v


def _migrate_format(ckpt: dict[str, Any], version: int, path: pathlib.Path) -> dict[str, Any]:
    """`ckpt` (format `version` < FORMAT_VERSION) migrated step by step to FORMAT_VERSION."""
    oldest = _oldest_readable()
    if version < oldest:
        readable = str(FORMAT_VERSION) if oldest == FORMAT_VERSION else f"{oldest}-{FORMAT_VERSION}"
        raise TorchfricError(
            f"{path} has checkpoint format {version} (written by torchfric "
            f"{ckpt.get('torchfric_version', '?')}); this torchfric ({__version__}) reads "
            f"format {readable} and cannot migrate format {version}: re-create it with torchfric "
            "train from its config, or load it with the torchfric version that wrote it"
        )
    while version < FORMAT_VERSION:
        try:
            ckpt = _FORMAT_MIGRATIONS[version](dict(ckpt))
        except TorchfricError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise TorchfricError(
                f"{path}: cannot migrate checkpoint format {version} to {version + 1} ({exc!r}); "
                "the file is damaged or not a torchfric checkpoint"
            ) from None
        version += 1
        ckpt["format_version"] = version
    return ckpt


def checkpoint_config(raw: Mapping[str, Any]) -> Config:
    """The config stored in checkpoint dict `raw` (`read_checkpoint`), migrated to the current
    schema; ``Config()`` when the checkpoint holds none.

    Migrations (what older torchfric versions wrote that the current schema rejects):

    - ``estimator.ensemble*`` keys of a run whose method is not "ekf" are dropped (those runs
      never used them; older versions stored their own defaults there);
    - keys and sections the current schema does not know are dropped (a setting that no longer
      exists cannot apply).

    Data paths are kept as stored and not checked (``check_files=False``): evaluating or
    exporting a checkpoint does not need its training files. A config that still does not
    validate raises a one-line `TorchfricError` naming the checkpoint.
    """
    from ..config import Config

    if not isinstance(raw, Mapping):
        raise TorchfricError(f"a checkpoint must be a dict, got {type(raw).__name__}")
    stored = raw.get("config")
    if not stored:
        return Config()
    name = raw.get("name", "?")
    if not isinstance(stored, Mapping):
        raise TorchfricError(
            f"checkpoint {name!r}: its config is a {type(stored).__name__}, not a table; the "
            "checkpoint is damaged"
        )
    cfg = _migrate_config(stored)
    try:
        return Config.from_dict(cfg, check_files=False)
    except TorchfricError as exc:
        raise TorchfricError(
            f"checkpoint {name!r} (torchfric {raw.get('torchfric_version', '?')}): its stored "
            f"config does not validate under torchfric {__version__}: {exc}"
        ) from None


def _migrate_config(stored: Mapping[str, Any]) -> dict[str, Any]:
    """`stored` (a `Config.to_dict` of some torchfric version) reduced to the keys the current
    schema knows (`torchfric.config.SCHEMA`), with the ensemble keys of non-EKF runs dropped:
    older versions wrote their own defaults there for every method (ensemble = 0,
    ensemble_q_scales = ensemble_r_scales = [1.0]), which the schema now accepts only with
    method = "ekf"."""
    from ..config import ENSEMBLE_KEYS, SCHEMA

    out: dict[str, Any] = {}
    for key, value in stored.items():
        if key and key in SCHEMA and isinstance(value, Mapping):
            out[key] = {k: v for k, v in value.items() if k in SCHEMA[key]}
        elif key in SCHEMA[""] or key in SCHEMA:
            out[key] = value  # a malformed section is left for from_dict to report
    est = out.get("estimator")
    if isinstance(est, dict) and est.get("method", "ekf") != "ekf":
        for key in ENSEMBLE_KEYS:
            est.pop(key, None)
    return out


def check_checkpoint_target(path: pathlib.Path) -> None:
    """``--checkpoint PATH`` may replace only an earlier torchfric checkpoint, never other files."""
    if path.is_dir():
        raise TorchfricError(f"--checkpoint {path} is a directory; give a .pt file name")
    if path.exists():
        try:
            read_checkpoint(path)
        except TorchfricError:
            raise TorchfricError(
                f"--checkpoint {path} exists and is not a torchfric checkpoint; torchfric "
                "replaces only its own checkpoints there: give another file name"
            ) from None
