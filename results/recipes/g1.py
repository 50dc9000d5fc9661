"""The recipe of /work/data/g1 (pi0_armfix ea25edd).

Written by `python -m pi0_armfix.tools.write_config --root=/work/data/g1 --output=configs/g1.py`
from the set's feature names and the diagnosis of its data; every line below says why it was chosen.

  python -m pi0_armfix.train --config=configs/g1.py --workdir=runs/g1
  python -m pi0_armfix.study --configs=g1,g1:uniform --seeds=3 --closed_loop_episodes=0
    --workdir=runs/g1_study

`:uniform` is the same robot with a uniform loss and no lever: the baseline.

The diagnosis (pi0_armfix.tools.analyze_action_magnitudes):
  state copy: the current state explains >= 90% of ['left_arm', 'left_hand']'s targets and leaves
    them a small share of what the loss can still teach; weights multiply that residual. Try delta
    actions relative to the state first (data.delta_action_mask, pi0_armfix/configs/arm_focused.py),
    or state dropout (pi0_armfix/configs/state_dropout.py).
  offset: ['left_arm']'s actions sit at a steady offset from the measured state (left_arm 0.16 σ
    (holding errs 0.02 σ, copying 0.17 σ)): the state R2 hides it and holding the previous action
    exploits it. Give the policy the previous command: actions relative to it
    (data.delta_reference='previous_action', pi0_armfix/configs/arm_focused_previous_action.py).
  lag: ['right_arm', 'left_hand', 'right_hand']'s measured state trails the command (right_arm 5
    frames (copying errs 0.18 σ, 0.10 σ at the lag; holding 0.03 σ), left_hand 9 frames (copying
    errs 0.07 σ, 0.04 σ at the lag; holding 0.01 σ), right_hand 11 frames (copying errs 0.47 σ, 0.23
    σ at the lag; holding 0.05 σ)): the state shows where the command was, holding the previous
    action knows where it is. Give the policy the previous command: actions relative to it
    (data.delta_reference='previous_action', pi0_armfix/configs/arm_focused_previous_action.py).

The lever: the diagnosis: offset or lag on ['left_arm', 'left_hand', 'right_arm', 'right_hand'],
state copy on ['left_arm', 'left_hand']: those groups relative to the command one frame before (at
an episode's first frame, the training split's mean action).
"""

from pi0_armfix.configs import base

VARIANTS = ("", "uniform")


def get_config(arg=None):
    variant = arg or ""
    if variant not in VARIANTS:
        raise ValueError(f"configs/g1.py:{arg}: the variants are '' (the recipe) "
                         "and 'uniform' (the same robot, no lever)")
    config = base.get_config()
    # the LeRobot set this recipe was written from
    config.data.root = '/work/data/g1'
    # the set's action feature
    config.data.action_key = 'action'
    # the set's state feature
    config.data.state_key = 'observation.state'
    # left_arm: kLeftShoulderPitch .. kLeftWristYaw: named; a position command (the
    # finite-difference test: mean R2 on the state's change 0.00, on the state 0.96)
    # right_arm: kRightShoulderPitch .. kRightWristYaw: named; a position command (the
    # finite-difference test: mean R2 on the state's change 0.02, on the state 0.97)
    # left_hand: kLeftHandPinky .. kLeftHandThumbRotation: named; a position command (the
    # finite-difference test: mean R2 on the state's change 0.00, on the state 1.00)
    # right_hand: kRightHandPinky .. kRightHandThumbRotation: named; a position command (the
    # finite-difference test: mean R2 on the state's change 0.03, on the state 0.79)
    config.layout.groups = {
        'left_arm': (0, 7),
        'right_arm': (7, 14),
        'left_hand': (14, 20),
        'right_hand': (20, 26),
    }
    # the action feature's width
    config.layout.real_dim = 26
    # roles from the names (a binary dim with no body part: a gripper)
    config.layout.roles = {
        'left_arm': 'arm',
        'right_arm': 'arm',
        'left_hand': 'hand',
        'right_hand': 'hand',
    }
    # velocity commands: never made relative, never copied from the state
    config.layout.velocity_groups = ()
    # where the state holds each group's joints as positions, in order (by name, or the state dim
    # that explains the command best)
    config.data.state_groups = {
        'left_arm': (0, 7),
        'right_arm': (7, 14),
        'left_hand': (14, 20),
        'right_hand': (20, 26),
    }
    # every group once (what the per-group metrics and weights name)
    config.loss.group_weights = {
        'left_arm': 1.0,
        'right_arm': 1.0,
        'left_hand': 1.0,
        'right_hand': 1.0,
    }
    # the set's cameras are read
    config.data.images = True
    # the set's cameras by name (pi0_armfix/data/cameras.py's aliases)
    config.data.cameras = {'base_0_rgb': 'observation.images.cam_high'}
    # every frame decoded once at the model's image size, then read from disk
    config.data.frame_cache = True
    # episodes without their video files are left out
    config.data.skip_missing_videos = True
    # reads off the training step's critical path
    config.data.num_workers = 2
    # held out: the last 20% of the 93 episodes, within [2, 20]
    config.eval.episodes = 19
    # a held-out evaluation every quarter of the run
    config.eval.evaluations = 4
    # the baseline: openpi's plain mean over the dims
    config.loss.strategy = 'uniform'
    if variant == "uniform":
        return config
    # the diagnosis: offset or lag on ['left_arm', 'left_hand', 'right_arm', 'right_hand'], state
    # copy on ['left_arm', 'left_hand']: those groups relative to the command one frame before (at
    # an episode's first frame, the training split's mean action)
    config.data.delta_action_mask = ('left_arm', 'right_arm', 'left_hand', 'right_hand')
    config.data.delta_reference = 'previous_action'
    return config
