"""Strict loading of openpi params checkpoints (written here with openpi's layout at tiny size)."""

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model
from pi0_armfix.model.pretrained import load_pretrained

TINY = model_config.get_preset("tiny")


@pytest.fixture(scope="module")
def params():
    return jax.tree.map(np.asarray, flow_model.init_params(TINY, jax.random.key(0)))


def _save(path, params):
    """openpi's layout: a PyTreeCheckpointer directory holding {"params": tree}."""
    with ocp.PyTreeCheckpointer() as checkpointer:
        checkpointer.save(path, {"params": params})
    return path


def _assert_equal_trees(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)


def test_openpi_params_checkpoint_restores(tmp_path, params):
    restored = load_pretrained(_save(tmp_path / "params", params), TINY)
    _assert_equal_trees(restored, params)


def test_nnx_value_leaves_of_training_checkpoints_are_stripped(tmp_path, params):
    wrapped = jax.tree.map(lambda x: {"value": x}, params)
    _assert_equal_trees(load_pretrained(_save(tmp_path / "params", wrapped), TINY), params)


def test_bfloat16_checkpoint_restores_as_float32(tmp_path, params):
    half = jax.tree.map(lambda x: x.astype(jax.numpy.bfloat16), params)
    restored = load_pretrained(_save(tmp_path / "params", half), TINY)
    assert all(leaf.dtype == np.float32 for leaf in jax.tree.leaves(restored))


def test_restores_with_shardings(tmp_path, params):
    sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    restored = load_pretrained(_save(tmp_path / "params", params), TINY,
                               shardings=jax.tree.map(lambda _: sharding, params))
    assert all(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves(restored))
    _assert_equal_trees(jax.tree.map(np.asarray, restored), params)


def test_missing_key_is_named(tmp_path, params):
    llm = {k: v for k, v in params["PaliGemma"]["llm"].items() if k != "final_norm_1"}
    partial = dict(params, PaliGemma=dict(params["PaliGemma"], llm=llm))
    with pytest.raises(ValueError, match=r"missing keys \(1\): PaliGemma/llm/final_norm_1/scale"):
        load_pretrained(_save(tmp_path / "params", partial), TINY)


def test_unexpected_key_is_named(tmp_path, params):
    extra = dict(params, time_mlp_in={"kernel": np.zeros((2, 2), np.float32)})
    with pytest.raises(ValueError, match=r"unexpected keys \(1\): time_mlp_in/kernel"):
        load_pretrained(_save(tmp_path / "params", extra), TINY)


def test_misshaped_key_is_named(tmp_path, params):
    bad = dict(params, state_proj={"kernel": np.zeros((8, 16), np.float32),
                                   "bias": params["state_proj"]["bias"]})
    with pytest.raises(ValueError, match=r"state_proj/kernel: checkpoint \(8, 16\) != model \(32, 16\)"):
        load_pretrained(_save(tmp_path / "params", bad), TINY)


def test_not_a_checkpoint_is_named(tmp_path):
    with pytest.raises(ValueError, match="nowhere"):
        load_pretrained(tmp_path / "nowhere", TINY)
