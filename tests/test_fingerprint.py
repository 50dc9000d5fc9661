"""What makes two starts on one run folder the same run (pi0_armfix.training.fingerprint)."""

from pi0_armfix.configs import base
from pi0_armfix.training import fingerprint


def test_fingerprint_keys_are_what_gives_the_saved_state_its_meaning():
    for key in ("seed", "model.preset", "loss.group_weights.left_arm", "layout.preset",
                "data.root", "data.curriculum", "train.batch_size"):
        assert fingerprint.is_fingerprint_key(key), key
    for key in ("optim.lr", "train.total_steps", "eval.every", "data.num_workers",
                "model.pretrained", "sharding.fsdp"):
        assert not fingerprint.is_fingerprint_key(key), key


def test_a_relative_and_an_absolute_data_root_of_one_folder_are_the_same_run(tmp_path,
                                                                            monkeypatch):
    monkeypatch.chdir(tmp_path)
    changed, _ = fingerprint.differences({"data": {"root": "demo"}},
                                         {"data": {"root": str(tmp_path / "demo")}})
    assert changed == []


def test_a_run_saved_before_a_key_existed_compares_as_if_it_held_the_keys_default():
    saved = {"data": {"root": "/d"}}  # a config.json written before data.video_access existed
    current = {"data": {"root": "/d", "video_access": "auto", "stream_episodes": 16,
                        "stream_shuffle": 256}}
    assert fingerprint.differences(saved, current) == ([], [])
    changed, _ = fingerprint.differences(saved, {"data": {"root": "/d", "video_access": "stream"}})
    assert changed == ["data.video_access: 'auto' -> 'stream'"]


# The fingerprint keys of configs/base.py's default config when runs on disk were saved (the
# study folders of RESULTS.md): a key added since must say in fingerprint.ADDED_KEYS what those
# runs did, or they could not resume.
SAVED_RUNS_KEYS = (
    "data.action_indices", "data.action_key", "data.arm_heavy_episodes",
    "data.balanced_max_scale", "data.balanced_norm", "data.cameras", "data.chunk_stats_chunks",
    "data.curriculum", "data.delta_action_mask", "data.format", "data.images", "data.norm",
    "data.norm_per_timestep", "data.norm_stats", "data.root", "data.split", "data.state_groups",
    "data.state_indices", "data.state_key", "data.state_preset", "layout.action_dim",
    "layout.groups", "layout.preset", "layout.real_dim", "layout.roles",
    "layout.velocity_groups", "loss.delta_weighting", "loss.dimension_weights",
    "loss.ema_decay", "loss.flow_samples", "loss.group_weights.base",
    "loss.group_weights.left_arm", "loss.group_weights.left_gripper",
    "loss.group_weights.right_arm", "loss.group_weights.right_gripper",
    "loss.group_weights.torso", "loss.min_log_var", "loss.noise_beta", "loss.strategy",
    "loss.switch_weight", "loss.switch_window", "loss.w_max", "loss.w_min",
    "loss.weight_warmup_steps", "model.action_dim", "model.action_horizon",
    "model.augment.brightness", "model.augment.contrast", "model.augment.crop_scale",
    "model.augment.hue", "model.augment.jitter_p", "model.augment.rotate_degrees",
    "model.augment.saturation", "model.preset", "model.sizes.action_expert.mlp_dim",
    "model.sizes.action_expert.width", "model.sizes.attention.depth",
    "model.sizes.attention.head_dim", "model.sizes.attention.num_heads",
    "model.sizes.attention.num_kv_heads", "model.sizes.paligemma.mlp_dim",
    "model.sizes.paligemma.width", "model.sizes.siglip.conv_stem", "model.sizes.siglip.depth",
    "model.sizes.siglip.mlp_dim", "model.sizes.siglip.num_heads",
    "model.sizes.siglip.patch_size", "model.sizes.siglip.width", "model.state_dropout",
    "model.state_noise", "model.tokenizer", "model.use_state", "seed", "train.batch_size",
)


def test_every_fingerprint_key_added_since_saved_runs_says_what_they_did():
    flat = fingerprint.flatten(base.get_config().to_dict())
    added = sorted(k for k in flat if fingerprint.is_fingerprint_key(k)
                   and k not in SAVED_RUNS_KEYS and k not in fingerprint.ADDED_KEYS)
    assert added == [], ("fingerprint keys added without a value for the runs saved before them: "
                         "add each to fingerprint.ADDED_KEYS")


def test_a_run_saved_before_the_step_options_and_the_frame_cache_resumes():
    saved = {"model": {"preset": "demo"}, "data": {"root": "/d"}}
    current = {"model": {"preset": "demo", "lora": [], "remat_policy": "nothing_saveable",
                         "attention": "einsum"}, "data": {"root": "/d", "frame_cache": True}}
    changed, _ = fingerprint.differences(saved, current)
    assert changed == []
