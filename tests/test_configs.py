"""The experiment configs: one shared base, two scales, each trains at tiny scale."""

import importlib.util
import json

import jax
import ml_collections
import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import demo_root  # noqa: F401  (a pytest fixture)
from pi0_armfix import console, train
from pi0_armfix.action_space import MANIPULATION_ROLES, ActionLayout
from pi0_armfix.configs import base
from pi0_armfix.data import selection
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.policies.sampling import LEVERS, Sampling
from pi0_armfix import sharding
from pi0_armfix.training import checkpoint

CONFIGS = ("arm_focused", "very_arm_focused", "simple_arm_focused", "uniform", "original",
           "arm_focused_balanced", "arm_curriculum", "loss_balanced", "uncertainty", "arm_delta",
           "arm_delta_focused", "arm_delta_per_timestep", "arm_delta_correlated_noise",
           "arm_delta_flow_samples", "gripper_switch", "arm_recipe", "arm_weights_3x",
           "state_dropout", "state_noise", "no_state", "arm_focused_openpi_augment",
           "arm_focused_delta_base", "arm_focused_previous_action", "arm_focused_lora")
# Trained at tiny scale: every strategy, and every lever (arm_recipe holds delta actions,
# per-timestep stats, correlated noise and switch emphasis; K flow samples on its own).
TRAINED = ("arm_focused", "very_arm_focused", "simple_arm_focused", "uniform", "original",
           "arm_focused_balanced", "arm_curriculum", "loss_balanced", "uncertainty",
           "arm_delta_flow_samples", "arm_recipe", "state_dropout", "no_state",
           "arm_focused_delta_base")
B1K = ActionLayout.preset("b1k_r1pro")


def load(name: str, arg: str | None = None) -> ml_collections.ConfigDict:
    path = tf.REPO_ROOT / "pi0_armfix" / "configs" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.get_config(arg)


def flat_keys(config: ml_collections.ConfigDict) -> set[str]:
    def walk(node, prefix):
        for key, value in node.items():
            if isinstance(value, ml_collections.ConfigDict) and key != "group_weights":
                yield from walk(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}"
    return set(walk(config, ""))


def test_every_config_file_is_listed():
    found = {p.stem for p in (tf.REPO_ROOT / "pi0_armfix" / "configs").glob("*.py")} - {"base", "__init__"}
    assert found == set(CONFIGS)


@pytest.mark.parametrize("scale", [None, "b1k", "b1k2026", "g1"])
@pytest.mark.parametrize("name", CONFIGS)
def test_config_has_exactly_the_keys_of_the_base(name, scale):
    assert flat_keys(load(name, scale)) == flat_keys(base.get_config(scale))


@pytest.mark.parametrize("name, strategy, arm_weight", [
    ("arm_weights_3x", "per_group", 3.0), ("very_arm_focused", "per_group", 5.0),
    ("arm_focused_balanced", "per_group", 3.0), ("arm_curriculum", "per_group", 3.0),
    ("uniform", "uniform", None), ("original", "original", None),
    ("loss_balanced", "loss_balanced", 1.0), ("uncertainty", "uncertainty", 1.0),
    ("arm_delta", "uniform", None), ("arm_delta_focused", "per_group", 3.0),
    ("gripper_switch", "per_group", 3.0), ("arm_recipe", "per_group", 3.0),
    ("arm_focused", "uniform", None), ("state_dropout", "uniform", None),
    ("state_noise", "uniform", None), ("no_state", "uniform", None),
])
def test_config_selects_its_strategy_and_arm_weight(name, strategy, arm_weight):
    config = load(name)
    assert config.loss.strategy == strategy
    if arm_weight is not None:
        weights = dict(config.loss.group_weights)
        B1K.check_group_weights(weights)
        assert {weights[g] for g in B1K.groups_with_role(*MANIPULATION_ROLES)} == {arm_weight}
        assert weights["base"] == weights["torso"] == 1.0


def test_simple_arm_focused_spells_the_3x_weights_dim_by_dim():
    weights = np.asarray(load("simple_arm_focused").loss.dimension_weights)
    B1K.check_dimension_weights(weights)
    for g in B1K.group_names:
        assert set(weights[B1K.group_dims(g)]) == {3.0 if g in B1K.groups_with_role(*MANIPULATION_ROLES) else 1.0}
    assert not weights[B1K.real_dim:].any()


DELTA_CONFIGS = {"arm_delta", "arm_delta_focused", "arm_delta_per_timestep",
                 "arm_delta_correlated_noise", "arm_delta_flow_samples", "arm_recipe",
                 "arm_focused", "arm_focused_openpi_augment", "arm_focused_previous_action",
                 "arm_focused_lora"}
STATE_LEVERS = {"state_dropout": ("state_dropout", 0.5), "state_noise": ("state_noise", 0.3),
                "no_state": ("use_state", False)}


def test_the_main_job_is_the_delta_recipe_and_the_seeds_3x_keeps_its_own_name():
    assert load("arm_focused").loss.flow_samples == 4
    assert load("arm_weights_3x").data == base.get_config().data


@pytest.mark.parametrize("scale, conv_stem", [(None, 3), ("b1k", 0), ("b1k2026", 0)])
def test_the_main_job_has_a_conv_stem_at_the_demo_scale_only(scale, conv_stem):
    model = model_config_lib.from_model_config(load("arm_focused", scale).model)
    assert model.siglip.conv_stem == conv_stem


@pytest.mark.parametrize("scale, jitter_p", [(None, 0.0), ("b1k", 0.5), ("b1k2026", 0.5)])
def test_the_main_job_has_no_colour_jitter_at_the_demo_scale_only(scale, jitter_p):
    model = model_config_lib.from_model_config(load("arm_focused", scale).model)
    assert model.augment.jitter_p == jitter_p


@pytest.mark.parametrize("name", sorted(STATE_LEVERS))
def test_state_lever_configs_change_one_model_key_of_uniform(name):
    key, value = STATE_LEVERS[name]
    config, plain = load(name), load("uniform")
    assert config.model[key] == value
    config.model[key] = plain.model[key]
    assert config == plain


def test_demo_augmentation_is_colour_only_and_b1k_uses_openpis():
    demo, b1k = (model_config_lib.from_model_config(base.get_config(s).model).augment
                 for s in (None, "b1k"))
    assert (demo.crop_scale, demo.rotate_degrees) == (1.0, 0.0) and demo.jitter_p > 0
    assert (b1k.crop_scale, b1k.rotate_degrees) == (0.95, 5.0)


def test_model_sizes_at_zero_are_the_presets():
    config = base.get_config()
    assert model_config_lib.from_model_config(config.model) == model_config_lib.get_preset(
        "demo", augment=model_config_lib.from_model_config(config.model).augment)


def test_model_sizes_change_a_tower_and_attention_changes_both_experts():
    config = base.get_config()
    config.model.sizes.siglip.patch_size = 4
    config.model.sizes.paligemma.width = 256
    config.model.sizes.attention.num_kv_heads = 2
    model = model_config_lib.from_model_config(config.model)
    demo = model_config_lib.get_preset("demo")
    assert (model.siglip.patch_size, model.siglip.width) == (4, demo.siglip.width)
    assert model.num_image_tokens == 64  # (32 / 4) ** 2
    assert (model.paligemma.width, model.action_expert.width) == (256, demo.action_expert.width)
    assert model.paligemma.num_kv_heads == model.action_expert.num_kv_heads == 2


def test_a_conv_stem_keeps_one_token_per_patch():
    config = base.get_config()
    config.model.sizes.siglip.conv_stem = 3
    model = model_config_lib.from_model_config(config.model)
    img = flow_model.param_shapes(model)["PaliGemma"]["img"]
    assert model.num_image_tokens == model_config_lib.get_preset("demo").num_image_tokens
    assert [img[f"stem_{i}"]["kernel"].shape[-1] for i in range(3)] == [16, 32, 64]
    assert img["embedding"]["kernel"].shape == (1, 1, 64, 64)  # 8 px = 3 halvings, then 1 px


def test_a_conv_stem_that_does_not_divide_the_patch_is_named():
    config = base.get_config()
    config.model.sizes.siglip.conv_stem = 4  # 2**4 does not divide the demo's 8 px patches
    with pytest.raises(ValueError, match=r"siglip.conv_stem=4 must be >= 0 with 2\*\*conv_stem"):
        model_config_lib.from_model_config(config.model)


def test_the_main_job_on_a_pi0_preset_names_the_conv_stem_and_its_fix():
    config = load("arm_focused")  # built at the demo scale: the conv stem is set
    config.model.preset = "pi0"  # 14 px patches
    for preset in ("pi0", "pi05"):
        config.model.preset = preset
        with pytest.raises(ValueError, match=r"siglip.conv_stem=3 .* conv_stem=0 is SigLIP's own"
                                             r".*--config.model.sizes.siglip.conv_stem=0$"):
            model_config_lib.from_model_config(config.model)


def test_a_negative_model_size_is_named():
    config = base.get_config()
    config.model.sizes.siglip.width = -8
    with pytest.raises(ValueError, match=r"model.sizes.siglip.width = -8 must be >= 0"):
        model_config_lib.from_model_config(config.model)


def test_openpi_augment_config_is_the_main_job_with_openpis_crop_and_rotation():
    config, main = load("arm_focused_openpi_augment"), load("arm_focused")
    assert (config.model.augment.crop_scale, config.model.augment.rotate_degrees) == (0.95, 5.0)
    config.model.augment = main.model.augment
    assert config == main


def test_only_the_balanced_curriculum_and_delta_configs_change_the_data():
    assert load("arm_focused_balanced").data.balanced_norm
    phases = load("arm_curriculum").data.curriculum
    assert [p[1] for p in phases] == [{"arm_heavy": 1.0}, {"arm_heavy": 0.3, "full": 0.7}]
    assert phases[0][0] == base.get_config().train.total_steps // 5
    for name in (set(CONFIGS) - {"arm_focused_balanced", "arm_curriculum",
                                 "arm_focused_delta_base"} - DELTA_CONFIGS):
        assert load(name).data == base.get_config().data


@pytest.mark.parametrize("scale, state_preset", [(None, "b1k_baseline23"), ("b1k", "b1k_r1pro"),
                                                 ("b1k2026", "b1k2026_r1pro")])
def test_delta_configs_make_torso_and_arms_relative_through_a_state_preset(scale, state_preset):
    for name in DELTA_CONFIGS:
        data = load(name, scale).data
        assert tuple(data.delta_action_mask) == ("torso", "left_arm", "right_arm")
        assert selection.state_preset(data) == state_preset and not data.state_indices


@pytest.mark.parametrize("scale", [None, "b1k", "b1k2026"])
def test_the_delta_base_config_is_the_main_job_with_the_base_relative(scale):
    config, main = load("arm_focused_delta_base", scale), load("arm_focused", scale)
    assert tuple(config.data.delta_action_mask) == ("base", "torso", "left_arm", "right_arm")
    config.data.delta_action_mask = main.data.delta_action_mask
    assert config == main


def test_b1k_scale_is_full_pi0_on_a_root_given_on_the_command_line():
    config = load("arm_focused", "b1k")
    assert config.model.preset == "pi0"
    assert config.data.root is None
    assert config.sharding.fsdp == -1


def test_unknown_scale_is_an_error_naming_it():
    with pytest.raises(ValueError, match="'tpu'"):
        load("arm_focused", "tpu")


def test_b1k_scale_without_a_data_root_fails_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="data.root is unset"):
        train.train_and_evaluate(load("arm_focused", "b1k"), str(tmp_path))
    assert not any(tmp_path.iterdir())


@pytest.mark.slow  # a training per config; the fast lane's training is test_serve.py's run
@pytest.mark.parametrize("name", TRAINED)
def test_config_trains_at_tiny_scale(name, tmp_path, demo_root):
    arm_heavy = tmp_path / "arm_heavy.json"
    arm_heavy.write_text(json.dumps({"episodes": [1, 3]}))  # the tiny demo is too short to filter
    workdir = tmp_path / "run"
    config = load(name)
    config.update_from_flattened_dict(
        tf.tiny_overrides(demo_root, data__arm_heavy_episodes=str(arm_heavy)))
    record = train.train_and_evaluate(config, str(workdir))
    assert all(np.isfinite(record[f"loss/{g}"]) for g in B1K.group_names)

    records = tf.records(workdir)
    assert [r["step"] for r in records] == [1, 2]
    assert all(np.isfinite(r["loss"]) for r in records)
    state, _, _ = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).restore_for_eval(
        2, sharding.make_mesh(1), items=("params", "balancer", "loss_params"))
    weights = [[r[f"weight/{g}"] for g in B1K.group_names] for r in records]
    if name == "loss_balanced":  # equal at step 1 (no EMA yet), then from the group losses
        assert int(state["balancer"]["count"]) == 2
        assert np.ptp(weights[0]) < 1e-6
        assert np.ptp(weights[1]) > 1e-3
    elif name == "uncertainty":  # the log-variances are trained
        assert np.abs(jax.device_get(state["loss_params"]["log_vars"])).min() > 0
    elif name == "arm_recipe":  # the chunk statistics sit beside the norm stats
        per_timestep = json.loads((workdir / "norm_stats_per_timestep.json").read_text())
        horizon = model_config_lib.get_preset("tiny").action_horizon
        assert np.asarray(per_timestep["norm_stats"]["actions"]["std"]).shape == (horizon, 23)
        assert np.load(workdir / "action_chunk_correlation.npy").shape == (horizon * 23,) * 2
    elif name == "arm_focused_balanced":  # the run's stats are the balanced ones
        config = load(name)
        config.update_from_flattened_dict({"data.root": str(demo_root), "eval.episodes": 2})
        horizon = model_config_lib.from_model_config(config.model).action_horizon
        plain = dataset_lib.dataset_norm_stats(DataSpec.from_config(config, B1K), action_horizon=horizon,
                                            progress=False)["actions"]
        balanced = json.loads((workdir / "norm_stats.json").read_text())["norm_stats"]["actions"]
        arm = B1K.group_dims("left_arm")
        assert not np.allclose(np.asarray(balanced["std"])[arm], plain.std[arm])
        np.testing.assert_allclose(balanced["mean"], plain.mean, rtol=1e-6)


def test_the_package_and_the_top_level_hold_no_symbolic_link_so_sdists_and_every_platform_see_the_configs():
    links = [p for p in [*tf.REPO_ROOT.iterdir(), *(tf.REPO_ROOT / "pi0_armfix").rglob("*")]
             if p.is_symlink()]
    assert not links
    assert (tf.REPO_ROOT / "pi0_armfix" / "configs" / "base.py").is_file()


def test_a_config_path_from_any_folder_is_the_installed_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    resolved = console.installed_config("--config=configs/arm_focused.py:b1k")
    assert resolved == f"--config={console.configs_dir() / 'arm_focused.py'}:b1k"


def test_the_demo_state_preset_is_named_once_and_is_what_the_world_writes_and_the_data_reads():
    from pi0_armfix.data import selection as selection_lib
    from pi0_armfix.sim import world as world_lib
    from pi0_armfix.state_space import DEMO_STATE_PRESET, STATE_PRESETS

    preset = STATE_PRESETS[DEMO_STATE_PRESET]
    assert world_lib.STATE_DIM == preset.stored_width
    assert selection_lib.state_preset({"root": ""}) == DEMO_STATE_PRESET
    delta = base.get_config()
    base.use_arm_delta_actions(delta)
    assert delta.data.state_preset == DEMO_STATE_PRESET
    sources = [p for p in (tf.REPO_ROOT / "pi0_armfix").rglob("*.py")
               if f'"{DEMO_STATE_PRESET}"' in p.read_text()]
    assert [p.name for p in sources] == ["state_space.py"]  # a literal in one module only


def test_the_previous_action_config_is_the_main_job_relative_to_the_previous_command():
    config, main = load("arm_focused_previous_action"), load("arm_focused")
    assert config.data.delta_reference == "previous_action"
    config.data.delta_reference = main.data.delta_reference
    assert config == main


def test_levers_that_do_not_fit_the_model_are_refused_before_any_work(tmp_path, demo_root):
    config = load("arm_focused")
    config.update_from_flattened_dict(tf.tiny_overrides(demo_root, eval__n_exec=8))
    with pytest.raises(ValueError, match=r"n_exec = 8 \(eval.n_exec or --n_exec\) must be in "
                                         r"\[1, H = 4\]"):
        train.train_and_evaluate(config, str(tmp_path / "run"))
    assert not (tmp_path / "run").exists()


def test_no_shipped_config_sets_how_its_policy_is_executed():
    for name in console.config_names():
        for scale in ("", "b1k", "b1k2026", "g1"):
            config = load(name, scale)
            assert config.eval.execution == "adopted", (name, scale)
            assert {k: config.eval[k] for k in LEVERS} == dict.fromkeys(LEVERS), (name, scale)


def test_a_study_of_uniform_and_arm_focused_executes_both_alike_in_the_demo_world():
    from pi0_armfix.study import run as study_run

    executions = []
    for name in ("uniform", "arm_focused"):
        config = load(name)
        command = study_run.train_command(name, 0, 4500, tf.REPO_ROOT, ["eval.execution=adopted"])
        overrides = dict(a.removeprefix("--config.").split("=", 1) for a in command
                         if a.startswith("--config.eval."))
        config.update_from_flattened_dict({k: config.eval[k.removeprefix("eval.")].__class__(v)
                                           for k, v in overrides.items()})
        executions.append(Sampling.for_run(config))
    assert executions[0] == executions[1]
    assert (executions[0].n_exec, executions[0].temporal_ensemble, executions[0].group_counts(),
            executions[0].deadbands()) == (8, 0.01, {"base": 4, "torso": 8}, {"torso": 2.0})


def test_the_adopted_execution_is_the_demo_worlds_alone():
    for scale in ("b1k", "g1"):
        assert Sampling.for_run(load("arm_focused", scale)) == Sampling()
    on_a_demo_written_elsewhere = load("arm_focused")
    on_a_demo_written_elsewhere.data.root = "/data/demo"
    assert Sampling.for_run(on_a_demo_written_elsewhere) == Sampling()
    assert Sampling.for_run(load("arm_focused"), execution="none") == Sampling()


@pytest.mark.parametrize("preset", model_config_lib.PRESETS)
def test_the_main_job_fits_its_execution_to_every_preset_without_a_flag(preset):
    config = load("arm_focused")
    config.model.preset = preset
    config.model.sizes.siglip.conv_stem = 3 if preset == "demo" else 0  # the demo's stem alone
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    sampling = Sampling.for_run(config)
    sampling.check(B1K, horizon)
    assert sampling.executed(horizon) == max(horizon // 4, 1)


def test_a_run_that_sets_a_lever_keeps_it_over_the_execution_and_a_flag_over_both():
    config = load("arm_focused")
    config.eval.deadband = ""
    assert Sampling.for_run(config).deadbands() == {}
    assert Sampling.for_run(config, deadband="base=0.2").deadbands() == {"base": 0.2}
    assert Sampling.for_run(config).group_counts() == {"base": 4, "torso": 8}


def test_an_unknown_scale_is_refused_naming_every_scale():
    with pytest.raises(ValueError, match=r"':b1k2026' \(BEHAVIOR-1K 2026\) or ':g1'"):
        base.get_config("h1")


def test_the_banner_names_every_lever_of_the_main_job_and_its_execution():
    from pi0_armfix import train_setup
    from pi0_armfix.training.run_spec import RunSpec
    config = load("arm_focused")
    line = train_setup.levers(RunSpec.resolve(config), Sampling.for_run(config))
    assert line == ("relative to the state: torso, left_arm, right_arm; 4 flow draws per prefix; "
                    "a 3-conv stem; executed: group_draws base=4+torso=8, n_exec 8, "
                    "temporal_ensemble 0.01, deadband torso=2")
    uniform = load("uniform")
    assert train_setup.levers(RunSpec.resolve(uniform), Sampling.for_run(uniform, "none")) == (
        "executed: every lever off")


def test_the_g1_scales_evaluations_follow_a_changed_number_of_steps():
    from pi0_armfix.training.run_spec import RunSpec
    config = load("arm_focused", "g1")
    config.data.root = "/data/g1"
    config.train.total_steps = 400
    RunSpec.resolve(config)
    assert config.eval.every == 100  # four evaluations over the 400 steps, the last at the end
