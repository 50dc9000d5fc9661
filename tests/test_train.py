"""The training entrypoint and step (docs/design.md §6): outputs of a run, failures, loss
weights."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import base
from pi0_armfix.data.formats import sources
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.training import checkpoint
from pi0_armfix import train_setup as setup_lib
from pi0_armfix import wall_time
from pi0_armfix.training import step as step_lib

B1K = ActionLayout.preset("b1k_r1pro")


# ---------------------------------------------------------------------- a run and its outputs

@pytest.mark.slow  # a whole training run: the slow lane
def test_run_logs_metrics_evaluates_plots_and_prints_per_group_losses(tmp_path, cache_dir,
                                                                       demo_root):
    workdir = tmp_path / "run"
    result = tf.run_train("configs/arm_weights_3x.py", workdir,
                          tf.tiny_overrides(demo_root, train__total_steps=4,
                                            train__log_every=2, eval__every=4), cache_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    for group in B1K.group_names:
        assert group in result.stdout.split("last logged losses")[1]
    assert "held-out evaluation" in result.stdout
    banner = result.stdout.split("compiling the train step")[0]
    for line in ("config    ", f"run       {workdir}", "devices   1 x cpu in 1 process(es); mesh",
                 "model     tiny: ", f"data      {demo_root}: 8 episodes (2 held out), ",
                 "loss      per_group base 1, left_arm 3,", "schedule  4 steps of batch 8"):
        assert line in banner, line
    assert "first step compiled and ran in" in result.stdout
    last_bar = result.stderr.replace("\r", "\n").strip().splitlines()[-1]
    # every group on the bar, the arms and grippers first (a narrow terminal cuts the end)
    assert "| left_arm " in last_bar and " base " in last_bar and " right_gripper " in last_bar

    lines = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    training, evaluation = [r for r in lines if "loss" in r], [r for r in lines if "err/base" in r]
    assert [r["step"] for r in training] == [2, 4] and [r["step"] for r in evaluation] == [4]
    expected = {"loss", "grad_norm", "lr", "phase", "steps_per_sec", "data_wait"}
    expected |= {f"{kind}/{g}" for kind in ("loss", "weight") for g in B1K.group_names}
    assert expected <= training[-1].keys()
    assert 0 <= training[-1]["data_wait"] <= 1
    assert {f"{prefix}{kind}/{g}" for prefix in ("", "persistence/", "state_copy/")
            for kind in ("err", "skill", "motion_gain", "motion_ratio")
            for g in B1K.group_names} | {"gripper_switch/f1"} <= evaluation[0].keys()
    assert training[-1]["weight/left_arm"] == pytest.approx(3 * training[-1]["weight/base"])

    assert list((workdir / "tensorboard").glob("events.out.tfevents.*"))
    for figure in ("group_losses.png", "trajectories_4.png", "stagnation.png"):
        assert (workdir / "plots" / figure).stat().st_size > 10_000
    assert checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).all_steps() == [2, 4]
    assert json.loads((workdir / "config.json").read_text())["loss"]["strategy"] == "per_group"

    spent = wall_time.load(workdir / wall_time.FILE)
    assert list(spent["parts"]) == [
        "open and check the data", "statistics", "data pipeline and evaluator",
        "state (initialized or restored)", "first step (compiled)", "evaluation at step 4",
        "other steps"]
    assert all(s >= 0 for s in spent["parts"].values())
    assert sum(spent["parts"].values()) <= spent["total"]
    assert "wall time by part (s): open and check the data " in result.stdout


@pytest.mark.slow  # a whole training run: the slow lane
def test_a_pi05_run_trains_evaluates_and_records_its_quantile_normalization(tmp_path, cache_dir,
                                                                            demo_root):
    workdir = tmp_path / "run"
    result = tf.run_train("configs/arm_focused.py", workdir,
                          tf.tiny_overrides(demo_root, model__preset="pi05_tiny", eval__every=2),
                          cache_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "model     pi05_tiny: " in result.stdout
    assert json.loads((workdir / "config.json").read_text())["data"]["norm"] == "quantile"
    records = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    assert any("motion_gain/left_arm" in r for r in records)


def test_unknown_config_key_is_an_error(tmp_path, cache_dir, demo_root):
    result = tf.run_train("configs/arm_focused.py", tmp_path / "run",
                          {"loss.arm_weight": 3.0}, cache_dir)
    assert result.returncode != 0
    assert "--config.loss.arm_weight: the config has no key 'arm_weight'" in result.stderr
    assert not (tmp_path / "run").exists()


def test_nan_data_with_supplied_norm_stats_is_named_before_the_first_step(tmp_path,
                                                                          monkeypatch):
    from data_fixtures import make_episodes, write_dataset
    from pi0_armfix.data.statistics import stats as stats_lib

    monkeypatch.setenv("PI0_ARMFIX_CACHE", str(tmp_path / "cache"))
    episodes = make_episodes(6, cameras={})
    episodes[1]["actions"][2, 9] = np.inf
    root = write_dataset(tmp_path / "ds", episodes, "v2.1")
    unit = stats_lib.NormStats(mean=np.zeros(23), std=np.ones(23), q01=-np.ones(23),
                               q99=np.ones(23))
    stats_lib.save_norm_stats(tmp_path / "norm_stats.json", {"actions": unit, "state": unit})
    config = base.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(
        root, data__norm_stats=str(tmp_path / "norm_stats.json")))
    with pytest.raises(ValueError, match=r"actions of episode 1 \(file .*episode_000001"
                                         r"\.parquet\) holds inf in dim 9"):
        train.train_and_evaluate(config, str(tmp_path / "run"))
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_second_process_on_a_locked_workdir_stops_at_once(tmp_path, cache_dir, demo_root):
    from pi0_armfix.training import workdir_lock

    (tmp_path / "run").mkdir()
    held = workdir_lock.lock_workdir(tmp_path / "run")
    try:
        result = tf.run_train("configs/uniform.py", tmp_path / "run", tf.tiny_overrides(demo_root),
                              cache_dir)
    finally:
        held.close()
    assert result.returncode != 0 and "Traceback" not in result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert f"workdir {tmp_path / 'run'} is in use by a run (pid {os.getpid()} on host" in line
    assert "train in another --workdir" in line
    assert not (tmp_path / "run" / "checkpoints").exists()
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


@pytest.mark.slow  # several processes: the slow lane
def test_the_lock_of_a_dead_run_does_not_block_and_a_finished_run_releases_it(tmp_path,
                                                                                 demo_root):
    from pi0_armfix.training import workdir_lock

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / workdir_lock.LOCK_FILE).write_text(
        '{"host": "gone", "pid": 999999, "started": "yesterday"}')  # its holder died
    config = base.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(demo_root))
    train.train_and_evaluate(config, str(tmp_path / "run"))
    workdir_lock.lock_workdir(tmp_path / "run").close()  # released at the end


def test_a_missing_config_file_ends_the_command_with_one_line_and_no_run_folder(tmp_path,
                                                                             cache_dir):
    # The parser's other one-line errors are console's (tests/test_console.py).
    result = tf.run_train("configs/nope.py", tmp_path / "run", {}, cache_dir)
    assert result.returncode != 0 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pi0_armfix.train: --config=")
    assert "nope.py: no such config file; give a path or the name of an installed config" in lines[0]
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("overrides, message", [
    ({"loss.group_weights.left_arm": -1.0}, r"loss.group_weights\['left_arm'\] = -1.0 is negative"),
    ({"loss.strategy": "per_grup"}, "unknown loss strategy 'per_grup'"),
    ({"loss.strategy": "uniform", "loss.delta_weighting": True}, "delta_weighting=True"),
    ({"layout.preset": "spot"}, "unknown layout preset 'spot'"),
    ({"model.preset": "huge"}, "unknown model preset 'huge'"),
    ({"sharding.fsdp": 3}, "sharding.fsdp = 3"),
    ({"train.batch_size": 0}, "train.batch_size = 0"),
    ({"train.log_every": 0}, "train.log_every = 0"),
    ({"optim.warmup_steps": -2}, "optim.warmup_steps = -2"),
    ({"optim.end_lr_factor": -5.0}, "optim.end_lr_factor = -5.0 must be in"),
    ({"optim.b1": 1.5}, r"optim.b1 = 1.5 must be in \[0, 1\)"),
    ({"eval.every": 1, "eval.plot_groups": ("left_hand",)},
     r"eval.plot_groups names \['left_hand'\]"),
    ({"eval.episodes": 8}, "eval.episodes = 8"),
    ({"data.root": "/nonexistent/b1k"}, "/nonexistent/b1k"),
    ({"data.norm_stats": "/nonexistent/norm_stats.json"}, "/nonexistent/norm_stats.json"),
])
def test_config_and_data_errors_fail_before_the_first_step(overrides, message, tmp_path,
                                                           demo_root):
    config = base.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(demo_root))
    config.update_from_flattened_dict(overrides)
    with pytest.raises(ValueError, match=message):
        train.train_and_evaluate(config, str(tmp_path / "run"))
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.slow  # a whole training process
def test_a_smoke_run_shorter_than_the_warmup_trains_and_says_so_once(tmp_path, cache_dir,
                                                                     demo_root):
    result = tf.run_train("configs/uniform.py", tmp_path / "run",
                          tf.tiny_overrides(demo_root, optim__warmup_steps=1000), cache_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    output = result.stdout + result.stderr
    assert output.count("optim.warmup_steps = 1000 is not shorter than train.total_steps = 2") == 1


def test_default_workdir_is_named_after_the_config_and_its_scale():
    assert train.default_workdir("configs/arm_focused.py") == "runs/arm_focused"
    assert train.default_workdir("configs/uniform.py:b1k") == "runs/uniform_b1k"


@pytest.mark.slow  # a whole training run: the slow lane
def test_run_without_workdir_checkpoints_into_runs_of_the_current_folder(tmp_path, cache_dir,
                                                                          demo_root):
    result = tf.run_train("configs/uniform.py", None, tf.tiny_overrides(demo_root), cache_dir,
                          cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    ckpts = checkpoint.Checkpoints(tmp_path / "runs" / "uniform" / "checkpoints", read_only=True)
    assert ckpts.all_steps() == [2]


def test_pretrained_params_are_the_state_at_step_zero(tmp_path, demo_root):
    # openpi's params layout: an orbax PyTree checkpoint of {"params": params}.
    model_config = model_config_lib.get_preset("tiny")
    params = jax.device_get(flow_model.init_params(model_config, jax.random.key(7)))
    with ocp.PyTreeCheckpointer() as checkpointer:
        checkpointer.save(tmp_path / "pretrained", {"params": params})
    prompts = sources.open_source({"root": str(demo_root)}, B1K).tasks
    spm = tokenizer_lib.cached_sentencepiece(prompts, model_config.vocab_size, tmp_path / "spm")
    config = base.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(
        demo_root, model__pretrained=str(tmp_path / "pretrained"), model__tokenizer=str(spm)))

    run = setup_lib.prepare(config, str(tmp_path / "run"))
    run.train_iter.close()
    run.checkpoints.close()
    jax.tree.map(np.testing.assert_array_equal, jax.device_get(run.state.params), params)
    assert int(run.state.step) == 0


def test_a_run_opens_its_dataset_once_and_builds_its_frame_store_once(tmp_path, demo_root,
                                                                     monkeypatch):
    from pi0_armfix.data.formats import frame_store
    from pi0_armfix.data.formats.lerobot import LeRobotSource

    monkeypatch.setenv("PI0_ARMFIX_CACHE", str(tmp_path / "cache"))
    opened, built = [], []
    open_source, build = LeRobotSource.__init__, frame_store._build
    monkeypatch.setattr(LeRobotSource, "__init__",
                        lambda self, *a, **k: opened.append(a) or open_source(self, *a, **k))
    monkeypatch.setattr(frame_store, "_build", lambda *a: built.append(a) or build(*a))
    config = base.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(demo_root, eval__every=1))

    run = setup_lib.prepare(config, str(tmp_path / "run"))
    next(run.train_iter)
    run.train_iter.close()
    run.checkpoints.close()
    assert len(opened) == 1 and len(built) == 1


# ---------------------------------------------------------------------- loss weights of a step

def _loss_cfg(**changes):
    loss_cfg = base.get_config().loss
    loss_cfg.update(changes)
    return loss_cfg


def _kwargs(loss_cfg, step, balancer=None, log_vars=None):
    loss_params = {} if log_vars is None else {"log_vars": log_vars}
    return step_lib.loss_kwargs(loss_cfg, B1K, jnp.int32(step), loss_params, balancer or {})


def test_group_weights_ramp_from_one_to_their_target_over_the_warmup():
    loss_cfg = _loss_cfg(group_weights=base.group_weights(3.0), weight_warmup_steps=10)
    for step, arm in ((0, 1.0), (5, 2.0), (10, 3.0), (50, 3.0)):
        weights = _kwargs(loss_cfg, step)["group_weights"]
        assert float(weights["left_arm"]) == pytest.approx(arm)
        assert float(weights["base"]) == pytest.approx(1.0)


def test_dimension_weights_ramp_from_one_on_real_dims_and_stay_zero_on_padding():
    target = np.asarray(base.dimension_weights(base.group_weights(3.0)))
    loss_cfg = _loss_cfg(strategy="per_dimension", dimension_weights=tuple(target),
                         weight_warmup_steps=4)
    np.testing.assert_allclose(_kwargs(loss_cfg, 0)["dimension_weights"], B1K.real_mask())
    np.testing.assert_allclose(_kwargs(loss_cfg, 4)["dimension_weights"], target)


def test_loss_balanced_weights_favour_the_group_with_the_smaller_loss_ema():
    loss_cfg = _loss_cfg(strategy="loss_balanced", weight_warmup_steps=0)
    ema = jnp.asarray([1.0, 1.0, 0.25, 1.0, 1.0, 1.0])  # left_arm's loss is 4x smaller
    kwargs = _kwargs(loss_cfg, 3, balancer={"ema": ema, "count": jnp.int32(3)})
    weights = step_lib.effective_group_weights(kwargs, B1K)
    assert float(weights[2]) == pytest.approx(4 * float(weights[0]))


def test_uncertainty_weight_is_the_precision_of_each_group():
    loss_cfg = _loss_cfg(strategy="uncertainty")
    log_vars = jnp.log(jnp.asarray([1.0, 2.0, 4.0, 1.0, 1.0, 1.0]))
    weights = step_lib.effective_group_weights(_kwargs(loss_cfg, 0, log_vars=log_vars), B1K)
    np.testing.assert_allclose(weights[:3], [1.0, 0.5, 0.25], rtol=1e-6)


def test_per_group_effective_weights_keep_their_ratios_and_mean_one_over_all_dims():
    kwargs = _kwargs(_loss_cfg(group_weights=base.group_weights(3.0)), 0)
    weights = np.asarray(step_lib.effective_group_weights(kwargs, B1K))
    sizes = np.asarray([len(B1K.group_dims(g)) for g in B1K.group_names])
    assert weights[2] == pytest.approx(3 * weights[0])
    assert (weights * sizes).sum() / B1K.action_dim == pytest.approx(1.0)


@pytest.mark.slow  # two processes of the train command
def test_print_config_shows_the_resolved_keys_and_help_points_to_them(tmp_path, cache_dir):
    command = tf.train_command("configs/arm_focused.py", None, {"train.total_steps": 7})
    printed = subprocess.run([*command, "--print_config"], env=tf.env(cache_dir),
                             cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert printed.returncode == 0, printed.stderr[-2000:]
    assert "total_steps: 7" in printed.stdout and "group_weights:" in printed.stdout
    assert not (tmp_path / "runs").exists()
    helped = subprocess.run([*command[:4], "--help"], env=tf.env(cache_dir), cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert "configs/base.py" in helped.stdout and "--print_config" in helped.stdout


@pytest.mark.slow  # a command in a subprocess per module: the slow lane
@pytest.mark.parametrize("module", ["pi0_armfix.train", "pi0_armfix.evaluate", "pi0_armfix.study",
                                    "pi0_armfix.serve", "pi0_armfix.tools.compute_norm_stats"])
def test_help_exits_0(module, cache_dir):
    result = subprocess.run([sys.executable, "-m", module, "--help"], env=tf.env(cache_dir),
                            cwd=tf.REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "--" in result.stdout


def test_the_study_commands_help_is_the_studys_documentation(cache_dir):
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.study", "--help"],
                            env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0
    assert "Every config x every seed" in result.stdout and "--closed_loop_episodes" in result.stdout
