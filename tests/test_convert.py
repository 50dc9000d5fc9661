"""Orbax -> safetensors conversion of the torch mirror (docs/design.md §1): CLI round trip, strict
key check, errors."""

import json
import os
import shutil
import subprocess
import sys

import jax
import numpy as np
import optax
import orbax.checkpoint as ocp
import pytest
import torch
from safetensors.torch import load_file, save_file

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import flow_model
from pi0_armfix.model.config import get_preset
from pi0_armfix.model.inputs import fake_observation
from pi0_armfix.model.tree import flatten_tree
from pi0_armfix.torch_mirror import checkpoint
from pi0_armfix.torch_mirror.params import ParameterMismatchError, torch_name
from pi0_armfix.training.checkpoint import Checkpoints
from pi0_armfix.training.state import create_train_state

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = get_preset("tiny")
NORM_STATS = {"norm_stats": {"actions": {"mean": [0.5] * 32, "std": [2.0] * 32,
                                         "q01": [-1.0] * 32, "q99": [1.0] * 32}}}


@pytest.fixture(scope="module")
def params():
    return flow_model.init_params(CONFIG, jax.random.key(1))


def _flat(tree):
    return {name: np.asarray(value) for name, value in flatten_tree(tree).items()}


def _write_run_checkpoint(workdir, params, step=5):
    """A run checkpoint as the trainer writes it: TrainState (with optimizer and EMA), config, stats."""
    state = create_train_state(params, model_config=CONFIG, tx=optax.adamw(1e-3),
                               loss_cfg={"strategy": "per_group"},
                               layout=ActionLayout.preset("b1k_r1pro"), ema_decay=0.99)
    state = state.replace(ema_params=jax.tree.map(lambda x: 0.5 * x, params))
    config = {"model": {"preset": "tiny", "dtype": "", "action_horizon": 0}}
    checkpoints = Checkpoints(os.path.join(workdir, "checkpoints"), every=1)
    data_state = {"step": step, "global_batch_size": 2, "seed": 0}
    checkpoints.save(step, state, data_state, NORM_STATS, config, force=True)
    checkpoints.wait()
    checkpoints.close()


def _write_openpi_checkpoint(folder, params):
    """openpi's layout: params/ holds {"params": nnx state} whose paths end in "value"; assets/."""
    nnx_state = jax.tree.map(lambda x: {"value": x}, params)
    with ocp.PyTreeCheckpointer() as checkpointer:
        checkpointer.save(os.path.join(folder, "params"), {"params": nnx_state})
    os.makedirs(os.path.join(folder, "assets", "b1k"))
    with open(os.path.join(folder, "assets", "b1k", "norm_stats.json"), "w") as f:
        json.dump(NORM_STATS, f)


def _run_cli(*args):
    return subprocess.run([sys.executable, "-m", "pi0_armfix.torch_mirror.convert", *args],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"})


@pytest.mark.slow  # a command in a subprocess: the slow lane
def test_cli_converts_a_run_checkpoint_that_loads_back_identical_and_predicts_like_flax(
        tmp_path, params):
    _write_run_checkpoint(str(tmp_path / "run"), params)
    result = _run_cli(f"--checkpoint={tmp_path / 'run'}", f"--output={tmp_path / 'torch'}")
    assert result.returncode == 0, result.stderr

    model, norm_stats = checkpoint.load_converted(str(tmp_path / "torch"))
    assert norm_stats == NORM_STATS
    assert model.config == CONFIG
    state_dict = model.state_dict()
    for name, value in _flat(params).items():
        np.testing.assert_array_equal(state_dict[torch_name(name)].numpy(), value)

    obs = fake_observation(CONFIG, 2, seed=3)
    x_t = np.random.default_rng(0).standard_normal((2, CONFIG.action_horizon, CONFIG.action_dim),
                                                   dtype=np.float32)
    t = np.array([0.3, 0.9], np.float32)
    expected = np.asarray(flow_model.velocity(params, obs, x_t, t, config=CONFIG))
    with torch.no_grad():
        np.testing.assert_allclose(model.velocity(obs, x_t, t).numpy(), expected, rtol=0, atol=1e-5)


def test_run_checkpoint_ema_params_are_converted_on_request(tmp_path, params):
    _write_run_checkpoint(str(tmp_path), params, step=7)
    arrays, config, _ = checkpoint.read_checkpoint(str(tmp_path / "checkpoints" / "7"), ema=True)
    assert config == CONFIG
    for name, value in _flat(params).items():
        np.testing.assert_array_equal(arrays[name], 0.5 * value)


def test_openpi_params_folder_converts_with_its_norm_stats(tmp_path, params):
    _write_openpi_checkpoint(str(tmp_path / "openpi"), params)
    arrays, config, norm_stats = checkpoint.read_checkpoint(str(tmp_path / "openpi"), preset="tiny")
    checkpoint.write_converted(str(tmp_path / "torch"), arrays, config, norm_stats, source="test")
    model, loaded_stats = checkpoint.load_converted(str(tmp_path / "torch"))
    assert loaded_stats == NORM_STATS
    for name, value in _flat(params).items():
        np.testing.assert_array_equal(model.state_dict()[torch_name(name)].numpy(), value)


def test_openpi_params_subfolder_itself_is_accepted(tmp_path, params):
    _write_openpi_checkpoint(str(tmp_path), params)
    assert checkpoint.locate(str(tmp_path / "params")) == ("openpi", tmp_path)


def test_strict_key_check_lists_missing_unexpected_and_mis_shaped_names(tmp_path, params):
    arrays = _flat(params)
    del arrays["action_out_proj/bias"]
    arrays["PaliGemma/llm/layers/mlp_2/linear"] = np.zeros((2, 3), np.float32)
    arrays["state_proj/kernel"] = np.zeros((7, 16), np.float32)
    with pytest.raises(ParameterMismatchError) as error:
        checkpoint.write_converted(str(tmp_path / "out"), arrays, CONFIG, None, source="ckpt_dir")
    message = str(error.value)
    for expected in ("ckpt_dir", "missing (1): action_out_proj.bias",
                     "unexpected (1): PaliGemma.llm.layers.mlp_2.linear",
                     "state_proj.kernel: (7, 16) != expected (32, 16)"):
        assert expected in message
    assert not (tmp_path / "out" / checkpoint.MODEL_FILE).exists()


def test_a_model_config_that_does_not_fit_the_params_is_a_value_error(tmp_path, params):
    _write_openpi_checkpoint(str(tmp_path), params)
    arrays, config, _ = checkpoint.read_checkpoint(str(tmp_path), preset="demo")
    with pytest.raises(ValueError, match="mis-shaped"):
        checkpoint.write_converted(str(tmp_path / "out"), arrays, config, None, source=str(tmp_path))


def test_load_converted_rejects_a_tampered_safetensors_file(tmp_path, params):
    checkpoint.write_converted(str(tmp_path), _flat(params), CONFIG, None, source="test")
    tensors = load_file(str(tmp_path / checkpoint.MODEL_FILE))
    tensors.pop("PaliGemma.img.head.bias")
    save_file(tensors, str(tmp_path / checkpoint.MODEL_FILE))
    with pytest.raises(ValueError, match="missing .*PaliGemma.img.head.bias"):
        checkpoint.load_converted(str(tmp_path))


def test_a_folder_that_is_not_a_checkpoint_is_a_value_error_naming_it(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path} is not a checkpoint"):
        checkpoint.read_checkpoint(str(tmp_path))
    with pytest.raises(ValueError, match="does not exist"):
        checkpoint.load_converted(str(tmp_path))


def test_a_step_that_was_not_saved_is_a_value_error_listing_the_saved_ones(tmp_path, params):
    _write_run_checkpoint(str(tmp_path), params, step=5)
    with pytest.raises(ValueError, match=r"step 9 .* saved steps: \[5\]"):
        checkpoint.read_checkpoint(str(tmp_path), step=9)


@pytest.mark.slow  # a command in a subprocess: the slow lane
def test_the_cli_says_which_step_it_converts_and_what_incomplete_step_it_passed_over(tmp_path,
                                                                                    params):
    _write_run_checkpoint(str(tmp_path / "run"), params, step=4)
    shutil.copytree(tmp_path / "run" / "checkpoints" / "4", tmp_path / "run" / "checkpoints" / "6")
    shutil.rmtree(tmp_path / "run" / "checkpoints" / "6" / "state")  # a damaged newer step
    result = _run_cli(f"--checkpoint={tmp_path / 'run'}", f"--output={tmp_path / 'torch'}")
    assert result.returncode == 0, result.stderr
    assert "incomplete newer step folder(s) ['6']" in result.stdout
    assert "converting step 4, the latest complete one" in result.stdout
    assert f"converting {tmp_path / 'run' / 'checkpoints' / '4'} (a run step)" in result.stdout


@pytest.mark.slow  # a command in a subprocess: the slow lane
def test_the_cli_reports_a_damaged_checkpoint_in_one_line_naming_it(tmp_path, params):
    _write_run_checkpoint(str(tmp_path / "run"), params, step=4)
    state = tmp_path / "run" / "checkpoints" / "4" / "state"
    (state / "manifest.ocdbt").write_bytes(b"")  # truncated to nothing
    result = _run_cli(f"--checkpoint={tmp_path / 'run'}", f"--output={tmp_path / 'torch'}")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith(f"pi0_armfix.torch_mirror.convert: {state} cannot be read")
    assert "the checkpoint is damaged; convert an earlier step with --step" in line


def test_a_damaged_latest_step_falls_back_to_the_last_good_one_as_evaluate_does(tmp_path,
                                                                                params):
    _write_run_checkpoint(str(tmp_path / "run"), params, step=4)
    shutil.copytree(tmp_path / "run" / "checkpoints" / "4", tmp_path / "run" / "checkpoints" / "6")
    (tmp_path / "run" / "checkpoints" / "6" / "state" / "manifest.ocdbt").write_bytes(b"")
    said = []
    arrays, _, _ = checkpoint.read_checkpoint(str(tmp_path / "run"), say=said.append)
    assert arrays and any("checkpoints/6/state cannot be read" in s for s in said)
    assert said[-1] == f"converting {tmp_path / 'run' / 'checkpoints' / '4'} (a run step)"
    with pytest.raises(ValueError, match="cannot be read"):  # a step asked for is not replaced
        checkpoint.read_checkpoint(str(tmp_path / "run"), step=6)


@pytest.mark.slow  # a command in a subprocess: the slow lane
def test_the_cli_reports_a_missing_folder_in_one_line(tmp_path):
    result = _run_cli(f"--checkpoint={tmp_path / 'nothing'}", f"--output={tmp_path / 'torch'}")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        f"pi0_armfix.torch_mirror.convert: checkpoint folder {tmp_path / 'nothing'} does not exist")
