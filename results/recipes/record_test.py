"""The recipe of /work/data/record_test (pi0_armfix 260f4b2).

Written by `python -m pi0_armfix.tools.write_config --root=/work/data/record_test
--output=configs/record_test.py`
from the set's feature names and the diagnosis of its data; every line below says why it was chosen.

  python -m pi0_armfix.train --config=configs/record_test.py --workdir=runs/record_test
  python -m pi0_armfix.study --configs=record_test:uniform,record_test --seeds=3
    --closed_loop_episodes=0 --workdir=runs/record_test_study

`:uniform` is the same robot with a uniform loss and no lever: the baseline.

The diagnosis (pi0_armfix.tools.analyze_action_magnitudes):
  lag: ['arm']'s measured state trails the command (arm 5 frames (copying errs 0.19 σ, 0.09 σ at the
    lag; holding 0.04 σ)): the state shows where the command was, holding the previous action knows
    where it is. Give the policy the previous command: actions relative to it
    (data.delta_reference='previous_action', pi0_armfix/configs/arm_focused_previous_action.py).

The lever: the diagnosis: offset or lag on ['arm']: those groups relative to the command one frame
before (at an episode's first frame, the state where data.state_groups holds the joints as
positions, else the training split's mean action).
"""

from pi0_armfix.configs import base

VARIANTS = ("", "uniform")


def get_config(arg=None):
    variant = arg or ""
    if variant not in VARIANTS:
        raise ValueError(f"configs/record_test.py:{arg}: the variants are '' (the recipe) "
                         "and 'uniform' (the same robot, no lever)")
    config = base.get_config()
    # the LeRobot set this recipe was written from
    config.data.root = '/work/data/record_test'
    # the set's action feature
    config.data.action_key = 'action'
    # the set's state feature
    config.data.state_key = 'observation.state'
    # arm: shoulder_pan.pos .. wrist_roll.pos: named; a position command (the finite-difference
    # test: mean R2 on the state's change 0.02, on the state 0.97)
    # gripper: gripper.pos: named; a position command (the finite-difference test: mean R2 on the
    # state's change 0.04, on the state 0.87)
    config.layout.groups = {'arm': (0, 5), 'gripper': (5, 6)}
    # the action feature's width
    config.layout.real_dim = 6
    # roles from the names (a binary dim with no body part: a gripper)
    config.layout.roles = {'arm': 'arm', 'gripper': 'gripper'}
    # velocity commands: never made relative, never copied from the state
    config.layout.velocity_groups = ()
    # where the state holds each group's joints as positions, in order (by name, or the state dim
    # that explains the command best)
    config.data.state_groups = {'arm': (0, 5), 'gripper': (5, 6)}
    # every group once (what the per-group metrics and weights name)
    config.loss.group_weights = {'arm': 1.0, 'gripper': 1.0}
    # no video file of the 4 episodes of /work/data/record_test is where meta/info.json's video_path
    # ('videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4') puts it (e.g.
    # /work/data/record_test/videos/observation.images.front/chunk-000/file-000.mp4): trained
    # without cameras. where the videos sit under another folder (video/ rather than videos/, say),
    # set video_path in /work/data/record_test/meta/info.json to their path; without videos, read no
    # camera (data.images=False), then set this True
    config.data.images = False
    # reads off the training step's critical path
    config.data.num_workers = 2
    # held out: the last of the 4 episodes (a set of fewer than 5 keeps the rest for training)
    config.eval.episodes = 1
    # a held-out evaluation every quarter of the run
    config.eval.evaluations = 4
    # the baseline: openpi's plain mean over the dims
    config.loss.strategy = 'uniform'
    if variant == "uniform":
        return config
    # the diagnosis: offset or lag on ['arm']: those groups relative to the command one frame before
    # (at an episode's first frame, the state where data.state_groups holds the joints as positions,
    # else the training split's mean action)
    config.data.delta_action_mask = ('arm',)
    config.data.delta_reference = 'previous_action'
    return config
