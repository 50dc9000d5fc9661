"""Orbax checkpoints of a run (docs/design.md §6): round trip, atomicity, clear errors."""

import os
import shutil
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_armfix import sharding
from pi0_armfix.training import checkpoint

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NORM_STATS = {"norm_stats": {"actions": {"mean": [0.5, 1.0], "std": [2.0, 3.0]}}}


def _state(value: float) -> dict:
    return {"step": jnp.int32(value), "params": {"w": jnp.full((64, 32), value, jnp.float32)},
            "balancer": {"ema": jnp.arange(6, dtype=jnp.float32) * value}}


DATA_STATE = {"step": 3, "global_batch_size": 8, "seed": 0}


def _abstract(state, mesh):
    return jax.tree.map(lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                        state, sharding.tree_shardings(state, mesh))


def _config():
    return {"loss": {"strategy": "per_group"}, "seed": 3}


def test_restore_returns_the_saved_state_and_data_iterator_state(tmp_path):
    ckpts = checkpoint.Checkpoints(tmp_path / "checkpoints", every=1, keep=2)
    ckpts.save(3, _state(3.0), DATA_STATE, NORM_STATS, _config())
    ckpts.wait()
    state, data_state = ckpts.restore(3, _abstract(_state(0.0), sharding.make_mesh(1)))
    jax.tree.map(np.testing.assert_array_equal, state, _state(3.0))
    assert data_state == DATA_STATE


def test_retention_keeps_the_latest_keep_confirmed_checkpoints(tmp_path):
    ckpts = checkpoint.Checkpoints(tmp_path, every=1, keep=2)
    for step in (1, 2, 3):
        ckpts.save(step, _state(step), DATA_STATE, NORM_STATS, _config())
        ckpts.confirm(step)
    ckpts.close()
    assert checkpoint.Checkpoints(tmp_path, read_only=True).all_steps() == [2, 3]


def test_retention_never_deletes_the_last_confirmed_checkpoint(tmp_path):
    # keep=1: step 2 is saved but its next step never ran, so step 1 stays until 2 is confirmed.
    ckpts = checkpoint.Checkpoints(tmp_path, every=1, keep=1)
    ckpts.save(1, _state(1.0), DATA_STATE, NORM_STATS, _config())
    ckpts.confirm(1)
    ckpts.save(2, _state(2.0), DATA_STATE, NORM_STATS, _config())
    ckpts.close()
    assert checkpoint.Checkpoints(tmp_path, read_only=True).all_steps() == [1, 2]


def test_a_set_aside_checkpoint_leaves_the_steps_and_is_kept_under_its_reason(tmp_path):
    ckpts = checkpoint.Checkpoints(tmp_path / "checkpoints", every=1, keep=1)
    for step in (1, 2):
        ckpts.save(step, _state(step), DATA_STATE, NORM_STATS, _config())
    moved = ckpts.set_aside(2, "nonfinite")
    assert moved == tmp_path / "checkpoints.nonfinite" / "2" and (moved / "state").is_dir()
    assert ckpts.all_steps() == [1] and ckpts.latest_step() == 1
    ckpts.close()


def _damage(step_dir, how):
    """Deletes or truncates the array data file of a saved step's state."""
    data_file = next(p for p in (step_dir / "state" / "d").iterdir())
    if how == "delete":
        data_file.unlink()
    else:
        with open(data_file, "r+b") as f:
            f.truncate(data_file.stat().st_size // 2)


@pytest.mark.parametrize("how", ["delete", "truncate"])
def test_a_damaged_latest_checkpoint_is_named_set_aside_and_the_previous_one_restored(tmp_path,
                                                                                     how):
    ckpts = checkpoint.Checkpoints(tmp_path / "checkpoints", every=1)
    for step in (1, 2):
        ckpts.save(step, _state(step), {"step": step}, NORM_STATS, _config())
    ckpts.wait()
    _damage(tmp_path / "checkpoints" / "2", how)
    said = []
    step, state, data_state = ckpts.restore_latest(
        _abstract(_state(0.0), sharding.make_mesh(1)), say=said.append)
    assert (step, data_state) == (1, {"step": 1})
    jax.tree.map(np.testing.assert_array_equal, state, _state(1.0))
    assert len(said) == 1 and f"checkpoint {tmp_path / 'checkpoints' / '2'} is damaged" in said[0]
    assert "resuming from step 1" in said[0]
    assert (tmp_path / "checkpoints.damaged" / "2").is_dir() and ckpts.all_steps() == [1]


def test_when_every_checkpoint_is_damaged_restore_latest_says_so_and_moves_nothing(tmp_path):
    ckpts = checkpoint.Checkpoints(tmp_path, every=1)
    ckpts.save(1, _state(1.0), DATA_STATE, NORM_STATS, _config())
    ckpts.wait()
    _damage(tmp_path / "1", "delete")
    with pytest.raises(ValueError, match=r"no checkpoint in .* can be read: checkpoint .*1 is "
                                         r"damaged .*train.resume=new"):
        ckpts.restore_latest(_abstract(_state(0.0), sharding.make_mesh(1)))
    assert ckpts.all_steps() == [1]


def test_restore_for_eval_reads_state_norm_stats_and_config_without_a_target(tmp_path):
    ckpts = checkpoint.Checkpoints(tmp_path, every=1)
    ckpts.save(1, _state(2.0), DATA_STATE, NORM_STATS, _config())
    ckpts.wait()
    state, norm_stats, config = checkpoint.Checkpoints(tmp_path, read_only=True).restore_for_eval(
        1, sharding.make_mesh(1))
    np.testing.assert_array_equal(state["params"]["w"], _state(2.0)["params"]["w"])
    assert norm_stats == NORM_STATS
    assert config.loss.strategy == "per_group" and config.seed == 3


def test_a_process_killed_while_finalizing_a_save_leaves_the_previous_checkpoint_intact(tmp_path):
    # The child saves step 1, then dies inside orbax's atomic rename of step 2.
    code = textwrap.dedent(f"""
        import os, jax.numpy as jnp, ml_collections
        from orbax.checkpoint._src.path import atomicity
        from pi0_armfix.training import checkpoint
        config = {{"seed": 0}}
        ckpts = checkpoint.Checkpoints({str(tmp_path)!r}, every=1)
        ckpts.save(1, {{"w": jnp.full((8,), 1.0)}}, {{"step": 1}}, {{}}, config)
        ckpts.wait()
        async def die(*args, **kwargs):
            os._exit(9)
        for cls in (atomicity.AtomicRenameTemporaryPath, atomicity.CommitFileTemporaryPath):
            cls.finalize = die
        ckpts.save(2, {{"w": jnp.full((8,), 2.0)}}, {{"step": 2}}, {{}}, config)
        ckpts.wait()
    """)
    env = dict(os.environ, PYTHONPATH=REPO_ROOT, JAX_PLATFORMS="cpu")
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 9, result.stderr
    assert any("tmp" in name for name in os.listdir(tmp_path)), os.listdir(tmp_path)

    ckpts = checkpoint.Checkpoints(tmp_path, every=1)
    assert ckpts.latest_step() == 1
    state, data_state = ckpts.restore(1, _abstract({"w": jnp.zeros((8,))}, sharding.make_mesh(1)))
    np.testing.assert_array_equal(state["w"], np.full((8,), 1.0))
    assert data_state == {"step": 1}


def test_a_disk_without_room_for_the_state_is_a_save_error_before_anything_is_written(
        tmp_path, monkeypatch):
    ckpts = checkpoint.Checkpoints(tmp_path, every=1)
    ckpts.save(1, _state(1.0), DATA_STATE, NORM_STATS, _config())
    ckpts.wait()
    disk_usage = shutil.disk_usage
    monkeypatch.setattr(checkpoint.shutil, "disk_usage",
                        lambda path: disk_usage(path)._replace(free=1000))
    with pytest.raises(checkpoint.SaveError,
                       match=r"checkpoint 2 needs about 8.\d KiB but .* has 1000 B free: free "
                             r"space on that disk, then rerun to resume from checkpoint 1"):
        ckpts.save(2, _state(2.0), DATA_STATE, NORM_STATS, _config())
    assert sorted(os.listdir(tmp_path)) == ["1"]


def test_a_save_that_fails_in_the_background_is_reported_at_the_next_check_naming_the_step(
        tmp_path, monkeypatch):
    ckpts = checkpoint.Checkpoints(tmp_path, every=1)
    ckpts.save(1, _state(1.0), DATA_STATE, NORM_STATS, _config())
    ckpts.wait()
    ckpts.save(2, _state(2.0), DATA_STATE, NORM_STATS, _config())
    ckpts.wait()

    def full_disk():  # what tensorstore raises from orbax's writer thread on a full disk
        raise ValueError('RESOURCE_EXHAUSTED: Error writing "w/0": Failed to write 8685 bytes to '
                         "file 4: No space left on device [os_error_code='28']")

    ckpts._saving = 3  # noqa: SLF001 - as if a save of step 3 were in flight
    monkeypatch.setattr(ckpts._manager, "check_for_errors", full_disk)  # noqa: SLF001
    with pytest.raises(checkpoint.SaveError,
                       match=r"checkpoint 3 could not be written in .*No space left on device.*"
                             r"the disk is full: free space on it, then rerun to resume from the "
                             r"last complete checkpoint \(2\)"):
        ckpts.check_for_errors()
