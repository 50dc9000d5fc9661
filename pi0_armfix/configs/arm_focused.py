"""The project's arm fix (the main job): torso and arm joints as delta actions relative to the
current state, base and grippers absolute, and K = 4 flow-matching draws per prefix pass, with a
uniform loss; with the demo model, a conv stem in the vision tower, and in the demo world no colour
jitter. On a G1 (`:g1`) the relative groups are both arms and both hands. Delta
actions remove the state-copy shortcut (the current joint positions explain most of an absolute arm
target, so a uniform loss learns to repeat them); the extra draws give the small deltas more
gradient per prefix compute; the conv stem lets the 32 px cameras' arm targets be learned within
the budget, and without the jitter the base is learned within it too. How its policy executes is
the commands' choice, alike for every config (`eval.execution`, `policies/sampling.py`).
The seed's 3x weighting is `arm_weights_3x`. What it does, measured over seeds against doing
nothing: README, "Results at a glance".

  python -m pi0_armfix.train --config=configs/arm_focused.py
"""

from pi0_armfix.configs import base


def get_config(arg=None):
    config = base.use_arm_delta_actions(base.get_config(arg))
    config.loss.strategy = "uniform"
    config.loss.flow_samples = 4
    if config.model.preset == "demo":
        # Three stride-2 convolutions before the 8 px patches, one token per patch as before:
        # the demo's arms learn in the main job's 4500 steps (RESULTS.md, "The main job with a
        # conv stem in the vision tower"). The pi0 presets keep SigLIP's own stem, whose
        # parameters openpi's checkpoints hold.
        config.model.sizes.siglip.conv_stem = 3
    if not arg:
        # The demo world never changes its colours; with the stem, the jitter only slows the
        # base (RESULTS.md, "The main job without colour jitter"). Real cameras keep it (b1k, g1).
        config.model.augment.jitter_p = 0.0
    return config
