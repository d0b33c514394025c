"""Room `artifacts`: the files a run owns and what a user opens afterwards.

- `checkpoint`: the checkpoint file (atomic writes, ``weights_only`` loading, format
  migrations);
- `rundir`: claiming a run directory (never over an earlier run), its lock and marker;
- `figures`: the figures of a model (friction curve with its band, responses, residuals) as
  plain data, and drawn;
- `drawing`: those figures drawn from plain data, without torch;
- `painter`: the helper process that draws them while the run goes on;
- `report`: report.html, one self-contained page per run.

Imports the `config` room only. Other rooms import its names from here.
"""

from ...lazy import lazy_names

_LAZY: dict[str, str] = {
    **dict.fromkeys(
        ["build_checkpoint", "check_checkpoint_target", "checkpoint_config", "checkpoint_model",
         "load_checkpoint",
         "read_checkpoint", "save_checkpoint", "sha256_file"],
        "checkpoint",
    ),
    **dict.fromkeys(["RunDir", "claim_run_dir", "locked", "next_run_dir"], "rundir"),
    **dict.fromkeys(
        ["friction_figure", "friction_spec", "model_specs", "trajectory_spec"],
        "figures",
    ),
    **dict.fromkeys(["pixels", "png_bytes", "png_from_pixels", "render", "subplots"], "drawing"),
    **dict.fromkeys(["Painter", "shared_painter"], "painter"),
    "write_report": "report",
}  # fmt: skip

__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)
__all__ = sorted(_LAZY)
