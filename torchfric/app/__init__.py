"""The application layer: what turns a config file into a run and a checkpoint, and the
commands around it (named ``app``, not ``runs``: ``runs/`` is where run directories go, and
the folder name that TensorBoard and many ``.gitignore`` files treat as generated output).

- `config` (with `schema`, `sections`, `estimator_config`, `toml_io`): the TOML schema, validated
  into frozen dataclasses; the ``[estimator]`` section holds the estimators' own settings objects;
- `loading`: the config's data → experiments, resource checks, the initial model;
- `runner`: `train` (run directory → data → model → estimator with observers → checkpoint);
- `observers`, `snapshots`: TensorBoard, progress lines and per-pass snapshots, as observers of
  the estimators' one `Callback` protocol;
- `evaluation`, `figures`: scores, warnings and figures of a finished model;
- `checkpoint`, `export`, `rundir`: the files a run owns (atomic, ``weights_only``);
- `cli`: the ``torchfric`` command.

This package imports everything below it; nothing below imports it. Importing it does not
import its modules (the CLI's ``--help`` stays light).
"""

__all__: list[str] = []
