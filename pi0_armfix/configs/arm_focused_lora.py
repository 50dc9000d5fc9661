"""The main job fine-tuned the way openpi fits a 24 GB card (its `*_low_mem_finetune` configs):
LoRA adapters on both experts (rank 16 on the prefix expert, 32 on the action expert), the
experts' own weights frozen in bfloat16 with neither gradients nor AdamW moments, and no EMA; the
vision tower and the projections train, and the loss and levers are `arm_focused`'s. Meant for a
pretrained base model at `:b1k`, where the batch of 32 is computed as 4 microbatches of 8 (one
optimizer step; the activations of 8 samples at a time). Memory: docs/gpu.md.

  python -m pi0_armfix.train --config=configs/arm_focused_lora.py:b1k \
      --config.data.root=<B1K root> --config.model.pretrained=<pi0_base>/params
"""

from pi0_armfix.configs import arm_focused, base


def get_config(arg=None):
    config = arm_focused.get_config(arg)
    config.model.lora = ("paligemma", "action_expert")
    config.optim.ema_decay = 0.0
    if arg in base.B1K_STATE_PRESETS:  # the full-size model
        config.train.microbatches = 4
    return config
