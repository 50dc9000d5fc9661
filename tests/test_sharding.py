"""Mesh and parameter rule table of docs/design.md §6."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

from pi0_armfix import sharding

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_large_matrix_is_sharded_along_its_largest_divisible_axis():
    assert sharding.partition_spec("llm/mlp/kernel", (18, 2048, 16384), 4) == P(None, None, "fsdp")


def test_largest_axis_that_fsdp_does_not_divide_is_skipped():
    # 3 does not divide 257153; it divides 2049 (= 3 * 683), the smaller axis.
    assert sharding.partition_spec("embedder/input_embedding", (257153, 2049), 3) == P(None, "fsdp")


def test_array_without_a_divisible_axis_is_replicated():
    assert sharding.partition_spec("w", (1025, 1023), 2) == P()


def test_vectors_and_small_arrays_are_replicated():
    assert sharding.partition_spec("dense/kernel", (65536,), 4) == P()
    assert sharding.partition_spec("dense/kernel", (8, 16), 4) == P()


def test_norm_scales_and_biases_are_replicated_whatever_their_size():
    assert sharding.partition_spec("layers/pre_attention_norm/scale", (18, 2048, 2048), 2) == P()
    assert sharding.partition_spec("head/bias", (4096, 4096), 2) == P()


def test_fsdp_of_one_replicates_everything():
    assert sharding.partition_spec("llm/mlp/kernel", (2048, 16384), 1) == P()


def test_first_matching_rule_wins():
    rules = ((r".*frozen.*", "replicate"), (r".*", "fsdp"))
    assert sharding.partition_spec("frozen/kernel", (4096, 4096), 2, rules) == P()
    assert sharding.partition_spec("trained/kernel", (4096, 4096), 2, rules) == P(None, "fsdp")


def test_unknown_rule_is_an_error_naming_the_parameter():
    with pytest.raises(ValueError, match="bogus.*'w'"):
        sharding.partition_spec("w", (4096, 4096), 2, ((".*", "bogus"),))


def test_fsdp_that_does_not_divide_the_devices_is_a_config_error():
    n = len(jax.devices())
    with pytest.raises(ValueError, match="sharding.fsdp"):
        sharding.make_mesh(n + 1)


def test_mesh_axes_are_batch_and_fsdp_and_auto():
    mesh = sharding.make_mesh(-1)
    assert mesh.axis_names == ("batch", "fsdp")
    assert mesh.shape["fsdp"] == len(jax.devices())
    assert all(t == jax.sharding.AxisType.Auto for t in mesh.axis_types)


def test_batch_size_not_divisible_by_devices_is_a_config_error():
    mesh = sharding.make_mesh(1)
    with pytest.raises(ValueError, match="train.batch_size = 0"):
        sharding.check_batch_size(0, mesh, "train.batch_size")


def _run_on_cpu_devices(n: int, code: str) -> str:
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={n}",
               JAX_PLATFORMS="cpu", PYTHONPATH=REPO_ROOT)
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                            capture_output=True, text=True, timeout=300, cwd=REPO_ROOT)
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_optimizer_moments_and_batch_are_placed_like_their_params_on_four_devices():
    out = _run_on_cpu_devices(4, """
        import jax, jax.numpy as jnp, optax
        from pi0_armfix import sharding
        mesh = sharding.make_mesh(2)
        params = {"mlp": {"kernel": jnp.ones((256, 512))}, "norm": {"scale": jnp.ones((512,))}}
        state = {"params": params, "opt": optax.adam(1e-3).init(params)}
        sh = sharding.tree_shardings(jax.eval_shape(lambda: state), mesh)
        print(sh["params"]["mlp"]["kernel"].spec, sh["opt"][0].mu["mlp"]["kernel"].spec,
              sh["params"]["norm"]["scale"].spec, sh["opt"][0].nu["norm"]["scale"].spec, sep="|")
        batch = jax.device_put(jnp.zeros((8, 3)), sharding.batch_sharding(mesh))
        shards = batch.addressable_shards
        print(sorted({s.data.shape[0] for s in shards}), len(shards))
    """)
    specs, rows = out.strip().splitlines()
    assert specs == "P(None, 'fsdp')|P(None, 'fsdp')|P()|P()"
    assert rows == "[2] 4"


def test_pi0_parameters_are_almost_all_sharded_and_never_along_the_layer_axis():
    with open(os.path.join(REPO_ROOT, "tests", "reference", "openpi_param_tree.json")) as f:
        tree = json.load(f)["pi0"]
    sharded = total = 0
    for name, (shape, _) in tree.items():
        spec = sharding.partition_spec(name, shape, 8)
        size = int(np.prod(shape))
        total += size
        if spec != P():
            sharded += size
            stacked = name.startswith(("PaliGemma/llm/layers/",
                                       "PaliGemma/img/Transformer/encoderblock/"))
            assert not (stacked and spec[0] == "fsdp"), name
    assert sharded / total > 0.999
