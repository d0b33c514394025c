"""Room `config`: the run configuration, from TOML to a checked, frozen `Config` and back.

- `config`: `Config` (loading, ``--set`` overrides, `SCHEMA`, writing TOML back);
- `sections`: ``[data]``, ``[model]``, ``[simulation]``, ``[log]``, ``[track]``;
- `estimator`: ``[estimator]``, which holds the estimators' own settings objects;
- `schema`: the vocabulary, `Check` and did-you-mean messages every section uses;
- `toml_io`: the TOML writer and ``--set`` values;
- `reference`: docs/config.md, generated from the schema (``python -m
  torchfric.app.config.reference``).

This room imports nothing else of the app layer. Other rooms import its names from here.
"""

from ...lazy import lazy_names

_LAZY: dict[str, str] = {
    **dict.fromkeys(
        ["Config", "MAX_CONFIG_BYTES", "MAX_NAME", "SCHEMA", "SECTIONS", "TOP_KEYS",
         "TOP_TYPES", "apply_overrides"],
        "config",
    ),
    **dict.fromkeys(
        ["AUTO_SIZES", "DataConfig", "LogConfig", "ModelConfig", "SimulationConfig",
         "TrackConfig"],
        "sections",
    ),
    **dict.fromkeys(
        ["ENSEMBLE_KEYS", "ESTIMATORS", "ESTIMATOR_KEYS", "MAX_EPOCHS", "MAX_PASSES",
         "EstimatorConfig"],
        "estimator",
    ),
    **dict.fromkeys(
        ["INIT_KEYWORDS", "RIG_PREFIX", "RIG_VALIDATION", "VELOCITY_SOURCES", "is_number",
         "show", "suggest"],
        "schema",
    ),
    **dict.fromkeys(["parse_value", "to_toml", "toml_value"], "toml_io"),
}  # fmt: skip

__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)
__all__ = sorted(_LAZY)
