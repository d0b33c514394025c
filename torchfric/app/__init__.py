"""The application layer: what turns a config file into a run and a checkpoint, and the
commands around it (named ``app``, not ``runs``: ``runs/`` is where run directories go, and
the folder name that TensorBoard and many ``.gitignore`` files treat as generated output).

Five rooms, lowest first; a room imports only the rooms before it, through their faces:

- `config`: the TOML schema, validated into frozen dataclasses; the ``[estimator]`` section
  holds the estimators' own settings objects;
- `artifacts`: the files a run owns: checkpoint, run directory, figures, report.html;
- `run`: one training run (`train`, `fit`): its inputs, the estimator with its observers,
  the kept pass, the σ, the run's views;
- `sweep`: many runs over a search space (Optuna, Ray Tune);
- `commands`: one module per ``torchfric`` command, each with its handler;

and `cli`, the parser and its ``{command: handler}`` table. docs/architecture.md maps them.

This package imports everything below it; nothing below imports it. Importing it (or a room's
face) imports none of their modules: the CLI's ``--help`` stays light.
"""

__all__: list[str] = []
