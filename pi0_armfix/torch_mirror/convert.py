"""Orbax checkpoint -> PyTorch: `model.safetensors`, `config.json`, `norm_stats.json`.

  python -m pi0_armfix.torch_mirror.convert --checkpoint=DIR --output=DIR [--step=N] [--ema]

What `--checkpoint` may be and what the output holds: `pi0_armfix/torch_mirror/checkpoint.py`.
Load the result with `pi0_armfix.torch_mirror.checkpoint.load_converted(DIR)`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from absl import app, flags

from pi0_armfix import console

from pi0_armfix.torch_mirror.checkpoint import (CONFIG_FILE, MODEL_FILE, NORM_STATS_FILE, read_checkpoint,
                                                write_converted)


_CHECKPOINT = flags.DEFINE_string("checkpoint", None, "Run workdir / checkpoints folder / step "
                                  "folder, or an openpi checkpoint folder (with params/).")
_OUTPUT = flags.DEFINE_string("output", None, "Folder for model.safetensors, config.json, norm_stats.json.")
_STEP = flags.DEFINE_integer("step", None, "Step of a run's checkpoints folder (default: latest).")
_EMA = flags.DEFINE_bool("ema", False, "Convert a run's EMA parameters.")
_PRESET = flags.DEFINE_string("preset", "", "Model preset of an openpi checkpoint (default pi0).")
_ACTION_HORIZON = flags.DEFINE_integer("action_horizon", 0, "Action horizon of an openpi checkpoint "
                                       "(0: the preset's).")
_NORM_STATS = flags.DEFINE_string("norm_stats", "", "norm_stats.json to ship instead of the checkpoint's.")


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    console.quiet_library_logging()  # orbax logs a line per array read; the bar says it
    try:
        arrays, config, norm_stats = read_checkpoint(
            _CHECKPOINT.value, step=_STEP.value, ema=_EMA.value, preset=_PRESET.value,
            action_horizon=_ACTION_HORIZON.value, norm_stats=_NORM_STATS.value, say=print)
        out = write_converted(_OUTPUT.value, arrays, config, norm_stats, source=_CHECKPOINT.value)
    except (ValueError, KeyError, OSError) as e:  # CheckpointError, a mismatch, a bad file
        raise SystemExit(f"pi0_armfix.torch_mirror.convert: {e}") from None
    count = sum(int(np.prod(a.shape)) for a in arrays.values())
    print(f"wrote {out / MODEL_FILE} ({len(arrays)} arrays, {count:,} parameters), {CONFIG_FILE}"
          + (f", {NORM_STATS_FILE}" if norm_stats is not None else " (no norm stats in the checkpoint)"))



def cli() -> None:
    """The `pi0-armfix-convert` console script (also `python -m pi0_armfix.torch_mirror.convert`)."""
    flags.mark_flags_as_required(["checkpoint", "output"])
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.torch_mirror.convert"))


if __name__ == "__main__":
    cli()
