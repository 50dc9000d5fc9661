"""Runs that survive users and clusters: non-finite steps, resumes with another config, damaged
checkpoints, preemption signals, orphaned workers."""

import json
import os
import re
import shutil
import signal
import subprocess
import time

import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix.configs import base
from pi0_armfix import train
from pi0_armfix.policies import restore
from pi0_armfix.training import finite_checkpoints
from pi0_armfix import sharding
from pi0_armfix.training import checkpoint, fingerprint, preemption
from pi0_armfix.training.run_spec import RunSpec
from pi0_armfix import train_setup as setup_lib

pytestmark = pytest.mark.slow  # the slow lane: fault injection into training runs


def _config(config_module=base, **overrides):
    config = config_module.get_config()
    config.update_from_flattened_dict(overrides)
    return config


# ---------------------------------------------------------------- a step that goes non-finite

def test_a_run_that_goes_non_finite_at_step_n_plus_1_keeps_checkpoint_n_minus_1_resumable(
        tmp_path, cache_dir, demo_root):
    # lr 1e5 after a warmup: the params grow for a few steps, then step N+1 is not finite. State N
    # was finite itself (its params merely huge) and is set aside; keep_checkpoints=1 keeps N-1.
    workdir = tmp_path / "run"
    overrides = tf.tiny_overrides(demo_root, train__total_steps=12, train__checkpoint_every=1,
                                  train__keep_checkpoints=1, optim__lr=1e5,
                                  optim__warmup_steps=20)
    blown = tf.run_train("configs/uniform.py", workdir, overrides, cache_dir)
    assert blown.returncode == 1 and "Traceback" not in blown.stderr
    line = blown.stderr.strip().splitlines()[-1]
    bad_step = int(re.search(r"step (\d+) has loss", line).group(1))
    n = bad_step - 1
    assert n >= 2, line  # the test needs a finite step before the one set aside
    assert f"Checkpoint {n}, the state it started from, was moved to {workdir}/checkpoints." \
           f"nonfinite/{n}; a rerun resumes from checkpoint {n - 1}" in line
    assert checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).all_steps() == [n - 1]
    assert (workdir / "checkpoints.nonfinite" / str(n) / "state").is_dir()

    resumed = tf.run_train("configs/uniform.py", workdir, {**overrides, "optim.lr": 1e-3},
                           cache_dir)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resumed from" in resumed.stdout and "optim.lr: 100000.0 -> 0.001" in resumed.stdout
    losses = [r["loss"] for r in tf.records(workdir) if "loss" in r]
    assert len(losses) == 12 and all(loss is not None for loss in losses)


def test_a_run_whose_folder_vanishes_stops_with_one_line_and_recreates_nothing(tmp_path,
                                                                               demo_root):
    workdir = tmp_path / "run"
    run = train.prepare(_config(**tf.tiny_overrides(demo_root, train__total_steps=4)),
                        str(workdir))
    shutil.rmtree(workdir)
    with pytest.raises(train.RunFolderVanished, match=rf"the run folder {workdir} \(its "
                                                       r"config.json\) vanished before step 1"):
        train.train_loop(run)
    assert not workdir.exists()


def test_a_state_with_non_finite_params_is_never_saved(tmp_path, demo_root):
    import jax
    import jax.numpy as jnp

    config = _config(**tf.tiny_overrides(demo_root, train__total_steps=3,
                                         train__checkpoint_every=1))
    run = setup_lib.prepare(config, str(tmp_path / "run"))
    step = run.train_step

    def poisoned(state, batch):  # step 2's update writes NaN params; its loss stays finite
        state, metrics = step(state, batch)
        if int(state.step) == 2:
            state = state.replace(params=jax.tree.map(lambda p: p * jnp.nan, state.params))
        return state, metrics

    run.train_step = poisoned
    with pytest.raises(finite_checkpoints.NonFiniteLossError,
                       match=r"the update of step 2 left non-finite parameters \(its loss and "
                             r"gradient were finite\): stopping. It was not saved; a rerun "
                             r"resumes from checkpoint 1"):
        train.train_loop(run)
    assert checkpoint.Checkpoints(tmp_path / "run" / "checkpoints", read_only=True
                                  ).all_steps() == [1]


# ---------------------------------------------------------------- resume with another config

@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, demo_root):
    """A finished 4-step run of configs/uniform.py on the tiny demo (checkpoints 2 and 4), and its
    overrides."""
    workdir = tmp_path_factory.mktemp("finished") / "run"
    overrides = tf.tiny_overrides(demo_root, loss__strategy="uniform", train__total_steps=4)
    train.train_and_evaluate(_config(**overrides), str(workdir))
    return workdir, overrides


@pytest.mark.parametrize("change, key", [
    ({"loss.strategy": "per_group"}, "loss.strategy: 'uniform' -> 'per_group'"),
    ({"layout.groups": {"base": (0, 3), "torso": (3, 7), "arms": (7, 23)}, "layout.real_dim": 23},
     "layout.groups.arms: (absent) -> [7, 23]"),
    ({"data.root": "COPY"}, "data.root: "),
])
def test_a_resume_with_another_layout_strategy_or_data_root_is_refused_naming_the_keys(
        finished_run, tmp_path, change, key):
    workdir, overrides = finished_run
    if change.get("data.root") == "COPY":
        change = {"data.root": str(shutil.copytree(overrides["data.root"], tmp_path / "other"))}
    before = sorted(p.name for p in workdir.iterdir())
    with pytest.raises(train.ConfigurationError) as refused:
        train.train_and_evaluate(_config(**{**overrides, **change}), str(workdir))
    message = str(refused.value)
    assert f"workdir {workdir} holds a run with another config" in message
    assert key in message
    assert "--config.train.resume=new" in message and "--config.train.resume=force" in message
    assert sorted(p.name for p in workdir.iterdir()) == before


def test_resume_force_goes_on_with_the_new_values_and_keeps_the_norm_stats(finished_run,
                                                                         tmp_path, capsys):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    other_root = shutil.copytree(finished_run[1]["data.root"], tmp_path / "other")
    stats = (workdir / "norm_stats.json").read_text()
    overrides = {**finished_run[1], "data.root": str(other_root), "train.total_steps": 6,
                 "train.resume": "force"}
    train.train_and_evaluate(_config(**overrides), str(workdir))
    assert "train.resume=force: going on with changed data.root" in capsys.readouterr().out
    assert checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).latest_step() == 6
    assert (workdir / "norm_stats.json").read_text() == stats
    assert json.loads((workdir / "config.json").read_text())["data"]["root"] == str(other_root)


def test_a_forced_resume_whose_restore_is_refused_leaves_the_run_folder_as_it_was(finished_run,
                                                                               tmp_path):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    kept = lambda: {p.name: p.read_bytes() for p in workdir.iterdir()  # noqa: E731
                    if p.is_file() and p.name != "run.lock"}  # the lock is this start's
    before = kept()
    forced = {**finished_run[1], "model.lora": ("action_expert",), "train.total_steps": 6,
              "train.resume": "force"}
    with pytest.raises(Exception, match="lora|LoRA|adapter"):
        train.train_and_evaluate(_config(**forced), str(workdir))
    assert kept() == before  # config.json above all: the run's own config still resumes it
    own = RunSpec.resolve(_config(**finished_run[1])).config_json  # as a rerun checks it
    assert fingerprint.check_resume(workdir, own, holds_run=True, may_write=False) == []


def test_resume_new_archives_the_old_run_and_starts_at_step_zero(finished_run, tmp_path, capsys):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    overrides = {**finished_run[1], "loss.strategy": "per_group", "train.resume": "new"}
    train.train_and_evaluate(_config(**overrides), str(workdir))
    assert "the previous run moved to" in capsys.readouterr().out
    archived = list((workdir / "archive").iterdir())
    assert len(archived) == 1 and (archived[0] / "checkpoints" / "4").is_dir()
    assert json.loads((archived[0] / "config.json").read_text())["loss"]["strategy"] == "uniform"
    assert [r["step"] for r in tf.records(workdir) if "loss" in r] == [1, 2, 3, 4]


def test_without_config_json_the_resume_check_reads_the_checkpoints_config(finished_run,
                                                                          tmp_path):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    (workdir / "config.json").unlink()
    with pytest.raises(train.ConfigurationError,
                       match=r"holds a run with another config .*checkpoints/4/config/metadata"
                             r".*loss.strategy: 'uniform' -> 'per_group'"):
        train.train_and_evaluate(_config(**{**finished_run[1], "loss.strategy": "per_group"}),
                                 str(workdir))


def test_resume_new_without_config_json_still_archives(finished_run, tmp_path, capsys):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    (workdir / "config.json").unlink()
    overrides = {**finished_run[1], "train.resume": "new"}
    train.train_and_evaluate(_config(**overrides), str(workdir))
    assert "the previous run moved to" in capsys.readouterr().out
    assert [r["step"] for r in tf.records(workdir) if "loss" in r] == [1, 2, 3, 4]


def test_a_run_folder_with_no_config_anywhere_is_refused_with_the_ways_out(tmp_path):
    workdir = tmp_path / "run"
    workdir.mkdir()
    (workdir / "norm_stats.json").write_text("{}")
    with pytest.raises(ValueError, match="neither its config.json nor a checkpoint's config.*"
                                         "train.resume=new"):
        fingerprint.check_resume(workdir, base.get_config().to_dict(), holds_run=True,
                                 may_write=False)


def test_optimizer_and_schedule_changes_resume_with_a_note(finished_run, tmp_path, capsys):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    overrides = {**finished_run[1], "train.total_steps": 5, "optim.lr": 5e-4}
    train.train_and_evaluate(_config(**overrides), str(workdir))
    out = capsys.readouterr().out
    assert "resuming with changed settings: optim.lr: 0.001 -> 0.0005; train.total_steps: 4 -> 5" \
        in out


# ---------------------------------------------------------------- preemption and Ctrl-C

def _start(workdir, overrides, cache_dir, log):
    return subprocess.Popen(tf.train_command("configs/uniform.py", workdir, overrides),
                            env=tf.env(cache_dir), cwd=tf.REPO_ROOT, stdout=log,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(predicate, process, what, timeout=600):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert process.poll() is None, f"the run ended before {what}: {process.stderr.read()}"
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.005)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_during_a_save_finishes_it_saves_the_current_step_and_exits_with_one_line(
        tmp_path, cache_dir, demo_root, signum):
    workdir = tmp_path / "run"
    overrides = tf.tiny_overrides(demo_root, train__total_steps=400, train__checkpoint_every=2,
                                  train__log_every=2)
    with open(tmp_path / "stdout.log", "w") as log:
        run = _start(workdir, overrides, cache_dir, log)
        saving = lambda: any(".orbax-checkpoint-tmp" in p.name  # noqa: E731
                             for p in (workdir / "checkpoints").glob("*"))
        _wait_for(saving, run, "save in flight")
        run.send_signal(signum)
        _, stderr = run.communicate(timeout=300)
    assert run.returncode == 128 + signum
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    line = stderr.strip().splitlines()[-1]
    name = signal.Signals(signum).name
    ckpts = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True)
    stopped_at = ckpts.latest_step()
    assert line == (f"pi0_armfix.train: stopped by {name} after step {stopped_at}: saved "
                    f"checkpoint {workdir / 'checkpoints' / str(stopped_at)}; rerun the same "
                    "command to resume")
    assert not any(".orbax-checkpoint-tmp" in p.name for p in (workdir / "checkpoints").iterdir())

    resumed = tf.run_train("configs/uniform.py", workdir,
                           {**overrides, "train.total_steps": stopped_at + 2}, cache_dir)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resumed from {workdir / 'checkpoints' / str(stopped_at)}" in resumed.stdout


def test_a_second_signal_abandons_at_once():
    said, before = [], signal.getsignal(signal.SIGTERM)
    with preemption.stop_on_signals(said.append) as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.due(0) and stop.name == "SIGTERM"
        with pytest.raises(preemption.Abandoned):
            os.kill(os.getpid(), signal.SIGINT)
    assert said == ["received SIGTERM: stopping after the current step (send it again to stop "
                    "at once)"]
    assert signal.getsignal(signal.SIGTERM) is before  # the handlers are restored


def test_save_on_preemption_off_keeps_the_last_regular_checkpoint(tmp_path, cache_dir,
                                                                  demo_root):
    workdir = tmp_path / "run"
    overrides = tf.tiny_overrides(demo_root, train__total_steps=400, train__checkpoint_every=1000,
                                  train__save_on_preemption=False)
    with open(tmp_path / "stdout.log", "w") as log:
        run = _start(workdir, overrides, cache_dir, log)
        _wait_for(lambda: (workdir / "metrics.jsonl").exists()
                  and (workdir / "metrics.jsonl").read_text().count("\n") >= 2, run, "2 steps")
        run.send_signal(signal.SIGTERM)
        _, stderr = run.communicate(timeout=300)
    assert run.returncode == 128 + signal.SIGTERM
    assert "no checkpoint was saved; rerun the same command to resume" in stderr
    assert not checkpoint.has_checkpoints(workdir / "checkpoints")


# ---------------------------------------------------------------- orphaned data workers

def _children(pid):
    result = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True)
    return [int(p) for p in result.stdout.split()]


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie is dead, only not yet reaped
        return f.read().split(")")[-1].split()[0] != "Z"


def test_data_workers_die_with_a_killed_run(tmp_path, cache_dir, demo_root):
    workdir = tmp_path / "run"
    overrides = tf.tiny_overrides(demo_root, train__total_steps=400, data__num_workers=2)
    with open(tmp_path / "stdout.log", "w") as log:
        run = _start(workdir, overrides, cache_dir, log)
        _wait_for(lambda: (workdir / "metrics.jsonl").exists()
                  and (workdir / "metrics.jsonl").read_text().count("\n") >= 1, run, "a step")
        workers = _children(run.pid)
        assert len(workers) >= 2, workers
        run.send_signal(signal.SIGKILL)
        run.wait()
    deadline = time.monotonic() + 30
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(p) for p in workers), "data workers outlived their run"


# ---------------------------------------------------------------- damaged checkpoints

def test_a_run_whose_latest_checkpoint_is_damaged_resumes_from_the_previous_after_saying_so(
        finished_run, tmp_path, capsys):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    data_file = next((workdir / "checkpoints" / "4" / "state" / "d").iterdir())
    data_file.write_bytes(data_file.read_bytes()[:10])  # truncated

    train.train_and_evaluate(_config(**{**finished_run[1], "train.total_steps": 6}), str(workdir))
    time.sleep(1)  # tensorstore's late callbacks of the failed read
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err and "Event loop is closed" not in captured.err
    assert f"warning: checkpoint {workdir / 'checkpoints' / '4'} is damaged (" in captured.out
    assert f"moved it to {workdir / 'checkpoints.damaged' / '4'}; resuming from step 2 " \
           "instead" in captured.out
    assert f"resumed from {workdir / 'checkpoints' / '2'}" in captured.out
    assert checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).latest_step() == 6
    assert [r["step"] for r in tf.records(workdir) if "loss" in r] == [1, 2, 3, 4, 5, 6]


def test_a_torn_last_metrics_line_does_not_block_a_resume(finished_run, tmp_path):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    with open(workdir / "metrics.jsonl", "a") as f:
        f.write('{"step": 5, "loss": 0.5, "gra')  # a kill mid-write
    train.train_and_evaluate(_config(**{**finished_run[1], "train.total_steps": 5}), str(workdir))
    assert [r["step"] for r in tf.records(workdir) if "loss" in r] == [1, 2, 3, 4, 5]


# ---------------------------------------------------------------- tracebacks become one line

def test_a_pretrained_folder_that_is_empty_or_not_orbax_is_named_before_the_data_pass(
        tmp_path, demo_root):
    (tmp_path / "empty").mkdir()
    (tmp_path / "weights").mkdir()
    (tmp_path / "weights" / "model.safetensors").write_bytes(b"\0" * 64)
    for folder, held in (("empty", "nothing"), ("weights", "['model.safetensors']")):
        config = _config(**tf.tiny_overrides(demo_root, model__pretrained=str(tmp_path / folder)))
        with pytest.raises(train.ConfigurationError) as error:
            train.train_and_evaluate(config, str(tmp_path / "run"))
        assert str(error.value) == (
            f"model.pretrained: '{tmp_path / folder}' is not an orbax checkpoint (it holds "
            f"{held}); point model.pretrained at an openpi params folder (e.g. <openpi "
            "checkpoint>/params, which holds _METADATA)")
        assert not (tmp_path / "run").exists()


def test_a_workdir_that_is_a_file_is_one_line(tmp_path, cache_dir, demo_root):
    (tmp_path / "notes.txt").write_text("not a run")
    result = tf.run_train("configs/uniform.py", tmp_path / "notes.txt", tf.tiny_overrides(demo_root),
                          cache_dir)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        f"pi0_armfix.train: --workdir {tmp_path / 'notes.txt'} is a file, not a folder: name a "
        "new or existing run folder")


def test_a_corrupt_image_met_mid_run_by_a_data_worker_is_one_line_naming_file_and_row(
        tmp_path, cache_dir):
    import pyarrow as pa
    import pyarrow.parquet as pq

    root = tf.write_tiny_demo(tmp_path / "demo")
    path = root / "data" / "chunk-000" / "episode_000005.parquet"  # not among the probed ones
    table = pq.read_table(path)
    feature = "observation.images.rgb.head"
    images = table.column(feature).to_pylist()
    images[1:-1] = [{"bytes": b"\x89PNG garbage", "path": None}] * (len(images) - 2)
    table = table.set_column(table.schema.get_field_index(feature), feature,
                             pa.array(images, type=table.schema.field(feature).type))
    pq.write_table(table, path)

    result = tf.run_train("configs/uniform.py", tmp_path / "run",
                          tf.tiny_overrides(root, train__total_steps=20, data__num_workers=2),
                          cache_dir)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert re.match(rf"pi0_armfix.train: reading the batch of step \d+: cannot decode the image "
                    rf"of {path} camera '{feature}' row \d+: ", line), line
    assert "fix or remove the named file, then rerun to resume" in line


def test_an_arm_heavy_list_with_ids_the_dataset_lacks_is_refused_naming_them(tmp_path,
                                                                            demo_root):
    listed = tmp_path / "arm_heavy.json"
    listed.write_text(json.dumps({"episodes": [1, 3, 41, 97]}))
    config = _config(**tf.tiny_overrides(
        demo_root, data__arm_heavy_episodes=str(listed),
        data__curriculum=((1, {"arm_heavy": 1.0}), (2, {"full": 1.0}))))
    with pytest.raises(train.ConfigurationError,
                       match=rf"data.arm_heavy_episodes \({listed}\) lists 2 episode\(s\) that .* "
                             r"does not have \(ids 41, 97\): it was made for other data"):
        train.train_and_evaluate(config, str(tmp_path / "run"))


# ---------------------------------------------------------------- evaluation of a damaged run

def _damage_state(step_dir):
    next(p for p in (step_dir / "state" / "d").iterdir()).unlink()


def test_evaluation_of_a_damaged_latest_checkpoint_falls_back_to_the_previous_step(
        finished_run, tmp_path, capsys):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    _damage_state(workdir / "checkpoints" / "4")
    run = restore.restore_run(workdir)
    assert run.step == 2
    assert "checkpoints/4 is damaged" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"checkpoints/4 is damaged .*the run's steps: \[2, 4\]"):
        restore.restore_run(workdir, step=4)


def test_evaluation_restores_the_params_and_not_the_optimizer_state(finished_run):
    ckpts = checkpoint.Checkpoints(finished_run[0] / "checkpoints", read_only=True)
    state, _, _ = ckpts.restore_for_eval(4, sharding.make_mesh(1))
    assert set(state) <= set(checkpoint.EVAL_ITEMS) and "params" in state


def test_a_run_past_a_lowered_total_steps_says_so_instead_of_finishing(finished_run, tmp_path):
    workdir = shutil.copytree(finished_run[0], tmp_path / "run")
    with pytest.raises(train.ConfigurationError,
                       match=r"holds a run at step 4, past train.total_steps = 2: nothing to "
                             r"train.*pi0_armfix.evaluate"):
        train.train_and_evaluate(_config(**{**finished_run[1], "train.total_steps": 2}),
                                 str(workdir))
