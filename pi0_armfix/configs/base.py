"""The shared base of every experiment config: all keys, with the demo-scale defaults.

An experiment file (`pi0_armfix/configs/arm_focused.py`, ...) calls `get_config(arg)` and changes
only the `loss` (and, for a few, the `data`) section. `arg` picks the scale:

    ''    (no argument)  demo: the `demo` model on the embedded demo dataset, a CPU run of minutes.
    'b1k'                full pi0 on BEHAVIOR-1K 2025 as published (LeRobot v2.1, the 256-D state)
                         at `--config.data.root`.
    'b1k2026'            full pi0 on BEHAVIOR-1K 2026 as published (LeRobot v3.0, the 61-D state,
                         concatenated GOP-8 videos, prompts from meta/tasks.jsonl), the same
                         recipe with the 2026 state preset; statistics computed from the data.
    'g1'                 the `demo` model on a Unitree G1 with Inspire hands as LeRobot records
                         it, at `--config.data.root` (layout `g1_inspire`: each arm's 7 joints,
                         each hand's 6 finger joints, joint positions at 30 fps, the state in the
                         same order; its head camera scaled to the preset's 32 px), held out: the
                         last 20 episodes; learning curves every quarter of the run.
                         docs/data.md, "A real robot".

The config is locked by the entrypoint: every key a run can set exists here, and an unknown key on
the command line is an error.
"""

import ml_collections
from ml_collections import config_dict

from pi0_armfix.action_space import MANIPULATION_ROLES, ActionLayout
from pi0_armfix.state_space import DEMO_STATE_PRESET

SCALES = ("", "b1k", "b1k2026", "g1")
# The state preset of each B1K release (pi0_armfix.data.selection): its 23-D state in the action
# order, grippers the sum of their two fingers.
B1K_STATE_PRESETS = {"b1k": "b1k_r1pro", "b1k2026": "b1k2026_r1pro"}

# The layout preset of each scale's robot (pi0_armfix.action_space).
LAYOUT_PRESETS = {"": "b1k_r1pro", "b1k": "b1k_r1pro", "b1k2026": "b1k_r1pro",
                  "g1": "g1_inspire"}


def group_weights(arm_weight: float = 1.0, layout: str = "b1k_r1pro") -> dict[str, float]:
    """Static weights of every group of a layout preset (a missing key is an error, never a
    silent default): the manipulation groups (roles arm, hand, gripper) at `arm_weight`, the rest
    (base, torso) at 1."""
    action_layout = ActionLayout.preset(layout)
    manipulation = action_layout.groups_with_role(*MANIPULATION_ROLES)
    return {g: float(arm_weight) if g in manipulation else 1.0 for g in action_layout.group_names}


def dimension_weights(weights: dict[str, float], layout: str = "b1k_r1pro") -> tuple[float, ...]:
    """`[action_dim]` weights from group weights: each dim its group's weight, 0 elsewhere."""
    action_layout = ActionLayout.preset(layout)
    vec = action_layout.membership() @ [weights[g] for g in action_layout.group_names]
    return tuple(float(w) for w in vec)


def use_arm_delta_actions(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """The joint groups (roles torso, arm, hand) as targets relative to the current state; base
    velocity and grippers stay absolute (B1K 2025's winners' representation). The state must be
    in the action order: the release's preset at the b1k / b1k2026 scales, the G1's own order
    (`data.state_groups`) at g1; at the demo scale the demo's (`state_space.DEMO_STATE_PRESET`,
    also for a demo written elsewhere by `tools.make_demo_dataset`; another dataset names its own
    preset or `data.state_groups`)."""
    layout = ActionLayout.preset(config.layout.preset)
    config.data.delta_action_mask = layout.groups_with_role("torso", "arm", "hand")
    if not config.data.state_preset and config.data.state_groups is None:
        config.data.state_preset = DEMO_STATE_PRESET
    return config


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
    """All keys of a run. `arg`: '' (demo scale), 'b1k' or 'b1k2026' (full pi0 on a B1K 2025 /
    2026 LeRobot root)."""
    scale = arg or ""
    if scale not in SCALES:
        raise ValueError(f"config argument {arg!r} is not a scale; use no argument (demo), "
                         "':b1k' (BEHAVIOR-1K 2025), ':b1k2026' (BEHAVIOR-1K 2026) or ':g1' (a "
                         "Unitree G1 with Inspire hands)")

    config = ml_collections.ConfigDict()
    config.seed = 0

    config.model = ml_collections.ConfigDict()
    config.model.preset = "demo"  # tiny | demo | pi0
    config.model.dtype = ""  # '' = the preset's; float32 | bfloat16 (activations; params float32)
    config.model.pretrained = ""  # path to pretrained params ('' = random init)
    config.model.action_horizon = 0  # H of an action chunk; 0 = the preset's
    config.model.tokenizer = ""  # sentencepiece model file ('' = the demo's offline tokenizer)
    # Padded action/state width of the model; 0 = the preset's (32, pi0's). Must equal
    # layout.action_dim; only for actions wider than 32 (pretrained pi0 params need 32).
    config.model.action_dim = 0
    # The towers' sizes in place of the preset's, 0 = the preset's: the learning-efficiency
    # variants of the demo preset (RESULTS.md). `attention` sets both experts (they share every
    # attention layer); pretrained params need the preset's sizes.
    config.model.sizes = ml_collections.ConfigDict(dict(
        siglip=dict(width=0, depth=0, mlp_dim=0, num_heads=0, patch_size=0, conv_stem=0),
        paligemma=dict(width=0, mlp_dim=0),
        action_expert=dict(width=0, mlp_dim=0),
        attention=dict(depth=0, num_heads=0, num_kv_heads=0, head_dim=0)))
    # Levers against copying the state (pi0 only; pi0.5 writes the state into its prompt):
    # openpi's LoRA fine-tuning: the experts named here ("paligemma", "action_expert") get its
    # adapters (rank 16 / 32) and keep their own weights frozen in bfloat16; () = all weights train.
    config.model.lora = ()
    # Speed and memory of the step, the same function (docs/gpu.md): what a rematerialized layer
    # keeps for the backward pass (model.config.REMAT_POLICIES), and the attention's kernel
    # ("einsum": XLA's einsums; "fused": jax.nn.dot_product_attention, which the pinned JAX runs
    # as its XLA implementation: docs/gpu.md).
    config.model.remat_policy = "nothing_saveable"
    config.model.attention = "einsum"
    config.model.use_state = True  # False: the no-state ablation (a zero state, train and sample)
    config.model.state_dropout = 0.0  # P(a training sample's state is zeroed)
    config.model.state_noise = 0.0  # std of noise on the normalized state in training (DART-style)
    # Train-time image augmentation (openpi's semantics; crop and rotate touch the head camera
    # only). The demo's 32 px cameras carry metric cues in pixel positions (1 px of the head
    # camera is ~5 cm of target distance), so the demo default is colour-only (the main job
    # turns the colour jitter off too: arm_focused.py); b1k uses openpi's.
    config.model.augment = ml_collections.ConfigDict(dict(
        crop_scale=1.0, rotate_degrees=0.0, brightness=0.3, contrast=0.4, saturation=0.5,
        hue=0.1, jitter_p=0.5))

    config.loss = ml_collections.ConfigDict()
    # uniform | original | per_group | per_dimension | loss_balanced | uncertainty
    config.loss.strategy = "per_group"
    config.loss.group_weights = group_weights(1.0, LAYOUT_PRESETS[scale])
    config.loss.dimension_weights = ()  # per_dimension only: action_dim weights, 0 on padding
    config.loss.delta_weighting = False
    config.loss.weight_warmup_steps = 0  # group weights ramp 1.0 -> target (0 = off)
    config.loss.ema_decay = 0.99  # loss_balanced: EMA of each group's unweighted loss
    config.loss.w_min = 0.1  # loss_balanced: clamp of the adaptive weights
    config.loss.w_max = 10.0
    config.loss.min_log_var = -5.0  # uncertainty: lower clamp of the learned log-variances
    # Levers beside the weights (any strategy):
    config.loss.flow_samples = 1  # K noise/time draws per sample against one prefix pass (1 = pi0)
    config.loss.noise_beta = 1.0  # noise N(0, beta I + (1 - beta) chunk correlation); 1 = N(0, I)
    config.loss.switch_weight = 1.0  # weight of the steps near a gripper switch (1 = off)
    config.loss.switch_window = 3  # ... within this many steps of the switch

    config.layout = ml_collections.ConfigDict()
    config.layout.preset = LAYOUT_PRESETS[scale]
    # An explicit layout wins over the preset: groups {name: (start, stop)}, real_dim, action_dim.
    config.layout.groups = config_dict.placeholder(object)  # a dict; `object` makes it overridable
    config.layout.real_dim = config_dict.placeholder(int)
    config.layout.action_dim = 32
    config.layout.velocity_groups = ()  # with layout.groups: groups that are velocity commands
    # With layout.groups: {group: role}, roles base | torso | arm | gripper | other (the default).
    # The arm-heavy filter, the curriculum and the evaluation defaults read them.
    config.layout.roles = config_dict.placeholder(object)

    config.data = ml_collections.ConfigDict()
    config.data.root = ""  # '' = embedded demo dataset, generated on first use into a cache folder
    config.data.format = "lerobot"  # lerobot | rlds
    config.data.cameras = config_dict.placeholder(object)  # {batch camera: stored}; None = auto
    config.data.images = True  # False: read no camera (all-zero, masked): data without its videos
    config.data.action_key = "action"  # LeRobot: the stored action feature
    config.data.state_key = "observation.state"  # LeRobot: the stored state feature
    # LeRobot: a named selection of the stored state into the action order (pi0_armfix.
    # state_space: 'b1k_r1pro' for B1K 2025's 256-D state, 'b1k2026_r1pro' for B1K 2026's 61-D,
    # 'b1k_baseline23' for the baseline's 23-D
    # order); '' = data.state_indices, or on the embedded demo state_space.DEMO_STATE_PRESET.
    config.data.state_preset = ""
    config.data.state_indices = ()  # LeRobot: dims of the stored state to keep (() = all)
    config.data.action_indices = ()  # LeRobot: dims of the stored actions to keep (() = all)
    config.data.video_tolerance_frames = 0.5  # a row's timestamp vs its video frame (frames)
    # Episodes whose video file of a read camera is missing (a partial download or mirror): False
    # refuses, naming them all in one line; True leaves them out of training and evaluation and
    # names them in one warning line (the held-out split is the last eval.episodes of the rest).
    config.data.skip_missing_videos = False
    # How camera frames are read (pi0_armfix.data.pipeline.video_stream): 'random' = each sample's
    # frame on request (short-GOP video, re-encoded copies, images); 'stream' = episodes decoded
    # front to back, several open at once, through a window shuffle (long-GOP video: B1K 2025's HEVC
    # has one keyframe per episode; a curriculum's weights choose the episodes opened); 'auto' =
    # 'stream' when keyframes lie more than 32 frames apart, else 'random'. The banner says which
    # and why.
    config.data.video_access = "auto"
    # True: every video frame is decoded once, at the model's image size, into an on-disk cache
    # (pi0_armfix.data.formats.image_store; h * w * 3 bytes per frame and camera) that training
    # and evaluation then read by row: the same pixels as decoding on request, without the
    # decoding's CPU per sample. For small images of a modest set (the G1's 32k frames: ~1 min
    # once, ~75 MB); B1K's frames at 224 px would fill a disk.
    config.data.frame_cache = False
    config.data.stream_episodes = 16  # 'stream': episodes open (decoding) at once
    config.data.stream_shuffle = 256  # 'stream': samples mixed by the window shuffle
    # 'stream': every k-th frame of an episode is a sample (from a first frame drawn per reading);
    # the frames between are decoded, not converted. k times as many episodes are read for the
    # same samples, for ~k times the decoding per sample. On the demo, 4 won back the base's and
    # the grippers' held-out skill that 1 lost against random access, and part of the arms'
    # (RESULTS.md), at ~1/3 of the samples/s (~110 on 2 cores at B1K's resolution): raise it
    # where the cores allow.
    config.data.stream_stride = 4
    config.data.probe_episodes = 4  # episodes whose files and first/last frames are read first
    config.data.split = "train"  # RLDS: the split to read
    config.data.norm = ""  # zscore | quantile; '' = the model's (pi0: zscore, pi0.5: quantile)
    config.data.norm_stats = ""  # norm_stats.json (openpi format); '' = compute into the workdir
    config.data.balanced_norm = False  # compute balanced stats (equal per-group motion) instead
    config.data.balanced_max_scale = 10.0  # balanced stats: cap on each group's change of scale
    # Phases (until_step, {source: weight}), sources `full` and `arm_heavy`; () = `full` throughout.
    config.data.curriculum = ()
    config.data.arm_heavy_episodes = ""  # filter_arm_heavy_episodes JSON; '' = default thresholds
    # Action dims made relative: group names, e.g. ("torso", "left_arm", "right_arm"), or dim
    # indices; () = absolute.
    config.data.delta_action_mask = ()
    # What they are relative to: 'state' (the current state, which must hold the same joints in
    # the action order: data.state_groups or a preset), or 'previous_action' (the action commanded
    # one frame before, which holding the previous action exploits where a command sits at an
    # offset from the measured state or is a velocity; at an episode's first frame, in the
    # command's units, the state where data.state_groups places the joint plus the training
    # split's mean offset of the command from it, else the training split's mean action:
    # transforms.EpisodeStart; no state map needed; a policy needs it at
    # inference: the closed loop and the harness pass the last executed action, a server client
    # sends it: docs/serving.md).
    config.data.delta_reference = "state"
    config.data.norm_per_timestep = False  # action stats per chunk position h ([H, A])
    config.data.chunk_stats_chunks = 20_000  # chunks sampled for per-timestep stats / correlation
    config.data.state_groups = config_dict.placeholder(object)  # the state's {group: (start, stop)}
    config.data.num_workers = 0  # grain worker processes (0 = in the main process)
    config.data.prefetch = 8  # batches buffered ahead of the step

    config.train = ml_collections.ConfigDict()
    # The demo's main-job budget: 4500 steps of batch 32 is ~2 epochs of the 100 training
    # episodes, where `arm_focused` beats holding the previous action on the base, both arms and
    # both grippers (README, "Results at a glance"); 1500 (0.7 epoch) is too short for any config
    # to.
    config.train.total_steps = 4500
    config.train.batch_size = 32  # global, over all processes
    # Gradients of the batch as the mean over this many strided parts computed one after another:
    # the activation memory of batch_size / microbatches, one optimizer step per batch.
    config.train.microbatches = 1
    config.train.log_every = 25
    config.train.checkpoint_every = 500
    config.train.keep_checkpoints = 3  # good checkpoints kept (the last good one never goes)
    # A workdir resumed with another config (seed, model, loss, layout, data, batch size): 'auto'
    # refuses naming the keys; 'force' resumes anyway; 'new' archives the old run, starts over.
    config.train.resume = "auto"
    config.train.save_on_preemption = True  # SIGTERM/SIGINT: save the current step, then exit

    config.optim = ml_collections.ConfigDict()
    config.optim.lr = 1e-3  # peak of the warmup-cosine schedule
    config.optim.warmup_steps = 50
    config.optim.end_lr_factor = 0.1  # final lr = lr * end_lr_factor
    config.optim.b1 = 0.9
    config.optim.b2 = 0.95
    config.optim.eps = 1e-8
    config.optim.weight_decay = 1e-4
    config.optim.clip_norm = 1.0  # global-norm gradient clipping
    config.optim.ema_decay = 0.0  # EMA of params (0 = off)

    config.sharding = ml_collections.ConfigDict()
    config.sharding.fsdp = 1  # size of the fsdp mesh axis (-1 = all devices); batch axis = the rest

    config.eval = ml_collections.ConfigDict()
    config.eval.every = 1500  # 0 = no evaluation during training
    # Held-out evaluations spread evenly over the run, the last at its end, in place of
    # eval.every (resolved at the start, so that a changed train.total_steps keeps them); 0 =
    # eval.every decides.
    config.eval.evaluations = 0
    # Held out: the dataset's last N episodes, never trained on. The demo's 20 are 4 of each of
    # its 5 tasks (episode i runs task i % 5).
    config.eval.episodes = 20
    config.eval.num_steps = 10  # Euler steps of sample_actions
    # A flow policy is a sampler: each held-out chunk is sampled this many times and scored as the
    # single draw (what a robot executes: the headline), the mean of the draws (its own spread
    # averaged away) and the energy score of the draws (a proper scoring rule).
    config.eval.num_draws = 8
    # How the policy is executed (held-out evaluation, closed loop, server, study): a choice of
    # those commands, never of what a config trains (pi0_armfix.policies.sampling,
    # docs/closed_loop.md "Execution"). 'adopted': the world's adopted execution (the demo
    # world's: replanning every quarter of the horizon with temporal ensembling, the base the
    # mean of 4 draws, the torso of 8 held within 2 action stds; elsewhere every lever off);
    # 'none': every lever off. A study sets it alike for every config it compares
    # (`--execution`).
    config.eval.execution = "adopted"
    # The levers one at a time, in place of the execution's (None: the execution's; no shipped
    # config sets one, so that configs compared in a table execute alike): each executed chunk
    # the mean of this many draws (the grippers' hysteresis, when set, sees the mean) ...
    config.eval.average_draws = config_dict.placeholder(int)
    # ... each draw from the initial noise scaled by this, in (0, 1]
    config.eval.temperature = config_dict.placeholder(float)
    config.eval.batch_size = 32
    config.eval.max_chunks = 512  # chunks tiling the held-out episodes (each step once), at most
    config.eval.gripper_groups = ()  # gripper switch precision/recall/F1; () = the gripper role
    config.eval.switch_tolerance = 2  # steps by which a predicted gripper switch may miss
    # (open_above, close_below) of the grippers' hysteresis in action units
    # (pi0_armfix.policies.hysteresis; B1K 2025's winners: about (0.9, -0.98)); () = commands
    # pass as sampled.
    config.eval.gripper_hysteresis = config_dict.placeholder(tuple)
    # Actions executed per chunk before replanning (0: half the horizon), each new chunk
    # following the last one's unexecuted tail (real-time chunking), ACT's temporal ensembling
    # (its decay m > 0; 0: off); per-group draws ("base=4+torso=8": those groups the mean of k
    # draws) and a per-group deadband ("base=0.2+torso=0.5": a group holds still where it is
    # commanded less motion than k action stds), which the held-out evaluation measures too.
    config.eval.n_exec = config_dict.placeholder(int)
    config.eval.rtc = config_dict.placeholder(bool)
    config.eval.temporal_ensemble = config_dict.placeholder(float)
    config.eval.group_draws = config_dict.placeholder(str)
    config.eval.deadband = config_dict.placeholder(str)
    config.eval.plot_groups = ()  # trajectory plots; () = the layout's arm and gripper roles

    if scale in B1K_STATE_PRESETS:
        config.model.preset = "pi0"
        config.model.augment.crop_scale = 0.95  # openpi's train-time augmentation
        config.model.augment.rotate_degrees = 5.0
        config.model.tokenizer = config_dict.placeholder(str)  # PaliGemma's sentencepiece model
        config.data.root = config_dict.placeholder(str)  # required: a LeRobot B1K root
        config.data.state_preset = B1K_STATE_PRESETS[scale]  # the release's state -> 23-D
        config.data.num_workers = 8
        config.data.prefetch = 4
        config.train.total_steps = 30_000
        config.train.batch_size = 32
        config.train.log_every = 50
        config.train.checkpoint_every = 1_000
        config.optim.lr = 2.5e-5
        config.optim.warmup_steps = 1_000
        config.optim.b2 = 0.95
        config.optim.weight_decay = 1e-10
        config.optim.ema_decay = 0.99
        config.sharding.fsdp = -1
        config.eval.every = 2_000
        config.eval.episodes = 20
    if scale == "g1":
        layout = ActionLayout.preset(LAYOUT_PRESETS[scale])
        config.data.root = config_dict.placeholder(str)  # required: a LeRobot G1 root
        config.data.state_groups = dict(layout.groups)  # the state is in the action order
        # Its 640x480 AV1 (a keyframe every 2 frames) decoded once into the frame cache: decoding
        # on request took ~40 % of 2 cores beside two training runs. 2 worker processes keep the
        # reads off the training step's critical path.
        config.data.frame_cache = True
        config.data.num_workers = 2
        config.eval.evaluations = 4
    return config
