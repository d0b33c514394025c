"""Room `commands`: one module per ``torchfric`` command, each with its handler ``cmd_NAME``
(the parsed arguments → the exit status); `torchfric.app.cli` parses and dispatches.

- `init` (with `columns`, the header → column mapping): a starter config for a data file;
- `check`: a config and its data checked as ``train`` checks them, nothing written;
- `train`: a run and its summary; `evaluate`: ``evaluate`` and ``simulate``;
- `export`: the TorchScript module; `track`: the recursive EKF over a record;
- `sweep`: the command over the `sweep` room; `generate`: the synthetic rig's files.

Imports every room below it (`config`, `artifacts`, `run`, `sweep`); nothing imports it but
the CLI. Modules load only when their command runs.
"""

from ...lazy import lazy_names

_LAZY: dict[str, str] = {
    **dict.fromkeys(["cmd_init", "write_starter"], "init"),
    **dict.fromkeys(["check_run", "cmd_check"], "check"),
    **dict.fromkeys(["cmd_train", "print_result", "run_files"], "train"),
    **dict.fromkeys(["cmd_evaluate", "cmd_simulate"], "evaluate"),
    "cmd_export": "export",
    "cmd_track": "track",
    "cmd_sweep": "sweep",
    "cmd_generate": "generate",
}

__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)
__all__ = sorted(_LAZY)
