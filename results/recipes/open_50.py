"""The recipe of /work/data/open_50_video (pi0_armfix ea25edd).

Written by `python -m pi0_armfix.tools.write_config --root=/work/data/open_50_video
--output=configs/open_50.py`
from the set's feature names and the diagnosis of its data; every line below says why it was chosen.

  python -m pi0_armfix.train --config=configs/open_50.py --workdir=runs/open_50
  python -m pi0_armfix.study --configs=open_50,open_50:uniform --seeds=3 --closed_loop_episodes=0
    --workdir=runs/open_50_study

`:uniform` is the same robot with a uniform loss and no lever: the baseline.

The diagnosis (pi0_armfix.tools.analyze_action_magnitudes):
  offset: ['left_arm']'s actions sit at a steady offset from the measured state (left_arm 8.45 σ
    (holding errs 0.42 σ, copying 8.47 σ)): the state R2 hides it and holding the previous action
    exploits it. Give the policy the previous command: actions relative to it
    (data.delta_reference='previous_action', pi0_armfix/configs/arm_focused_previous_action.py).
  ['left_hand'] never move in these episodes (nothing to learn; left out).

The lever: the diagnosis: offset or lag on ['left_arm']: those groups relative to the command one
frame before (at an episode's first frame, the training split's mean action).
"""

from pi0_armfix.configs import base

VARIANTS = ("", "uniform")


def get_config(arg=None):
    variant = arg or ""
    if variant not in VARIANTS:
        raise ValueError(f"configs/open_50.py:{arg}: the variants are '' (the recipe) "
                         "and 'uniform' (the same robot, no lever)")
    config = base.get_config()
    # the LeRobot set this recipe was written from
    config.data.root = '/work/data/open_50_video'
    # the set's action feature
    config.data.action_key = 'actions'
    # the set's state feature
    config.data.state_key = 'state'
    # left_arm: left.joint_1.pos .. left.joint_6.pos: a joint or pose axis with no body part in its
    # name: taken as an arm; a position command (the finite-difference test: mean R2 on the state's
    # change 0.00, on the state 0.66)
    # left_gripper: left.joint_7.pos: binary (open/close) in the data; a position command (the
    # finite-difference test: mean R2 on the state's change 0.00, on the state 0.01)
    # right_arm: right.joint_1.pos .. right.joint_7.pos: a joint or pose axis with no body part in
    # its name: taken as an arm; a position command (the finite-difference test: mean R2 on the
    # state's change 0.03, on the state 0.71)
    # left_hand: left_hand.joint_1.pos .. left_hand.joint_10.pos: named; a position command (the
    # finite-difference test: mean R2 on the state's change 0.00, on the state 0.00)
    # right_hand: right_hand.joint_1.pos .. right_hand.joint_10.pos: named; a position command (the
    # finite-difference test: mean R2 on the state's change 0.01, on the state 0.74)
    config.layout.groups = {
        'left_arm': (0, 6),
        'left_gripper': (6, 7),
        'right_arm': (7, 14),
        'left_hand': (14, 24),
        'right_hand': (24, 34),
    }
    # the action feature's width
    config.layout.real_dim = 34
    # roles from the names (a binary dim with no body part: a gripper)
    config.layout.roles = {
        'left_arm': 'arm',
        'left_gripper': 'gripper',
        'right_arm': 'arm',
        'left_hand': 'hand',
        'right_hand': 'hand',
    }
    # velocity commands: never made relative, never copied from the state
    config.layout.velocity_groups = ()
    # where the state holds each group's joints as positions, in order (by name, or the state dim
    # that explains the command best)
    config.data.state_groups = {
        'left_arm': (0, 6),
        'left_gripper': (6, 7),
        'right_arm': (7, 14),
        'left_hand': (14, 24),
        'right_hand': (24, 34),
    }
    # every group once (what the per-group metrics and weights name)
    config.loss.group_weights = {
        'left_arm': 1.0,
        'left_gripper': 1.0,
        'right_arm': 1.0,
        'left_hand': 1.0,
        'right_hand': 1.0,
    }
    # the actions (34) or the state (34) are wider than pi0's 32: the model's width follows
    # (pretrained pi0 params need 32)
    config.layout.action_dim = 34
    config.model.action_dim = 34
    # the set's cameras are read
    config.data.images = True
    # the set's cameras by name (pi0_armfix/data/cameras.py's aliases)
    config.data.cameras = {'base_0_rgb': 'image'}
    # every frame decoded once at the model's image size, then read from disk
    config.data.frame_cache = True
    # episodes without their video files are left out
    config.data.skip_missing_videos = True
    # the probe found: episode 0, camera 'image', row 426: timestamp 14.2000 s lies 1.00 frames past
    # the episode's segment [0.0000 s, 14.2000 s) of
    # /work/data/open_50_video/video/image/chunk-000/file-000.mp4 (its last frame at 14.1667 s;
    # beyond it the file holds the next episode). If the data's timestamps run late by up to 1
    # frame(s), set data.video_tolerance_frames=1 to read the segment's last frame
    config.data.video_tolerance_frames = 1
    # reads off the training step's critical path
    config.data.num_workers = 2
    # held out: the last 20% of the 43 episodes, within [2, 20]
    config.eval.episodes = 9
    # a held-out evaluation every quarter of the run
    config.eval.evaluations = 4
    # the baseline: openpi's plain mean over the dims
    config.loss.strategy = 'uniform'
    if variant == "uniform":
        return config
    # the diagnosis: offset or lag on ['left_arm']: those groups relative to the command one frame
    # before (at an episode's first frame, the training split's mean action)
    config.data.delta_action_mask = ('left_arm',)
    config.data.delta_reference = 'previous_action'
    return config
