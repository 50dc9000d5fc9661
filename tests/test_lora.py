"""openpi's LoRA fine-tuning path: adapters with its names, shapes and equations, its freeze rule,
the frozen weights in bfloat16 without optimizer state, a base checkpoint as the start, and
adapters folded away where the weights must be plain."""

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest
import torch
from flax import traverse_util

import train_fixtures as tf
from train_fixtures import demo_root  # noqa: F401  (a pytest fixture)
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.bench import step as bench_step
from pi0_armfix.data.formats import sources
from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model, gemma
from pi0_armfix.model.inputs import fake_observation
from pi0_armfix.model.pretrained import load_pretrained
from pi0_armfix.model import tokenizer as tokenizer_lib
from pi0_armfix.model.tree import flatten_tree
from pi0_armfix.tools import export_openpi
from pi0_armfix.torch_mirror import checkpoint as torch_checkpoint
from pi0_armfix import sharding
from pi0_armfix.training import checkpoint, freeze

BOTH = ("paligemma", "action_expert")


def _config(lora=BOTH):
    return model_config.from_model_config({"preset": "tiny", "lora": lora})


def _flat(tree):
    return {k: np.asarray(v) for k, v in flatten_tree(tree).items()}


def _unflatten(flat):
    return traverse_util.unflatten_dict({tuple(k.split("/")): v for k, v in flat.items()})


def test_each_expert_gets_openpis_rank():
    config = _config()
    assert (config.paligemma.lora_rank, config.action_expert.lora_rank) == (16, 32)
    assert _config(("action_expert",)).lora_experts == ("action_expert",)
    assert _config(()).lora_experts == ()


def test_a_misspelt_lora_names_the_key_and_the_experts():
    with pytest.raises(ValueError, match=r"model.lora = 'both'.*'paligemma', 'action_expert'"):
        _config("both")


def test_every_attention_and_mlp_weight_of_an_adapted_expert_gets_openpis_adapters():
    params = flatten_tree(flow_model.param_shapes(_config(("paligemma",))))
    adapters = {k: v.shape for k, v in params.items() if "lora" in k}
    layers = "PaliGemma/llm/layers/"
    rank = 16
    expected = {}
    for name in ("attn/q_einsum", "attn/kv_einsum", "attn/attn_vec_einsum"):
        w = params[f"{layers}{name}/w"].shape
        # openpi's LoRAConfig.axes = (-2, -1): a replaces the out axis, b the in axis.
        expected[f"{layers}{name}/lora_a"] = (*w[:-1], rank)
        expected[f"{layers}{name}/lora_b"] = (*w[:-2], rank, w[-1])
    depth, _, width, mlp = params[f"{layers}mlp/gating_einsum"].shape
    expected.update({f"{layers}mlp/gating_einsum_lora_a": (depth, 2, width, rank),
                     f"{layers}mlp/gating_einsum_lora_b": (depth, 2, rank, mlp),
                     f"{layers}mlp/linear_lora_a": (depth, mlp, rank),
                     f"{layers}mlp/linear_lora_b": (depth, rank, width)})
    assert adapters == expected


def test_without_lora_the_tree_has_no_adapters():
    assert not [k for k in flatten_tree(flow_model.param_shapes(_config(()))) if "lora" in k]


@pytest.mark.parametrize("eqn, a, b", [
    ("BTD,NDH->BTNH", "BTD,NDL->BTNL", "BTNL,NLH->BTNH"),
    ("BSD,2KDH->2BSKH", "BSD,2KDL->2BSKL", "2BSKL,2KLH->2BSKH"),
    ("BTNH,NHD->BTD", "BTNH,NHL->BTL", "BTL,NLD->BTD"),
])
def test_the_adapters_equations_are_openpis(eqn, a, b):
    assert gemma.lora_equations(eqn) == (a, b)


@pytest.mark.slow
def test_folding_the_adapters_into_the_weights_keeps_the_velocity():
    config = _config()
    flat = _flat(flow_model.init_params(config, jax.random.key(0)))
    # Adapters far from their small init, so that they change the velocity.
    flat = {k: v * 30 if "lora" in k else v for k, v in flat.items()}
    observation = fake_observation(config, 2)
    x = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    t = jnp.full((2,), 0.3)
    adapted = flow_model.velocity(_unflatten(flat), observation, x, t, config=config)
    folded = flow_model.velocity(_unflatten(gemma.merge_lora(flat)), observation, x, t,
                                 config=config.without_lora())
    plain = flow_model.velocity(_unflatten({k: v for k, v in flat.items() if "lora" not in k}),
                                observation, x, t, config=config.without_lora())
    np.testing.assert_allclose(folded, adapted, atol=1e-4)
    assert np.abs(np.asarray(plain - adapted)).max() > 0.1


@functools.cache
def _one_step(lora):
    """A step of `arm_focused_lora` with `model.lora = lora`, the learning rate at its peak from
    the first step: (the step, the state before and after, metrics)."""
    config = bench_step.load_config("arm_focused_lora", preset="tiny", batch=4)
    config.model.lora = lora
    config.optim.warmup_steps = 0
    bench = bench_step.Step(config)
    state = bench.init(jax.random.key(0))
    before = jax.device_get(state)
    with jax.set_mesh(bench.mesh):
        after, metrics = jax.jit(bench.step_fn)(state, bench.batch)
    return bench, before, jax.device_get(after), metrics


def _changed(before, after):
    a, b = _flat(before.params), _flat(after.params)
    return {k for k in a if not np.array_equal(a[k], b[k])}


@pytest.mark.slow
def test_a_lora_step_trains_the_adapters_and_everything_outside_the_experts_only():
    bench, before, after, metrics = _one_step(BOTH)
    params = _flat(before.params)
    frozen = {k for k in params if k.startswith("PaliGemma/llm/") and "lora" not in k}
    assert frozen and _changed(before, after) == set(params) - frozen
    assert {params[k].dtype for k in frozen} == {np.dtype(jnp.bfloat16)}
    assert {v.dtype for k, v in params.items() if k not in frozen} == {np.dtype(np.float32)}
    assert np.isfinite(float(metrics["loss"]))


@pytest.mark.slow
def test_the_optimizer_keeps_moments_for_the_trained_weights_only():
    _, before, _, _ = _one_step(BOTH)
    trained = sum(v.size for k, v in _flat(before.params).items()
                  if not (k.startswith("PaliGemma/llm/") and "lora" not in k))
    moments = sum(np.size(x) for x in jax.tree.leaves(before.opt_state) if np.ndim(x))
    assert moments == 2 * trained  # AdamW's mu and nu


@pytest.mark.slow
def test_adapting_the_prefix_only_trains_the_action_expert_whole():
    # openpi's freeze filter with paligemma_variant="gemma_2b_lora" alone.
    _, before, after, _ = _one_step(("paligemma",))
    changed = _changed(before, after)
    llm = [k for k in _flat(before.params) if k.startswith("PaliGemma/llm/")]
    expert = [k for k in llm if any(part.endswith("_1") for part in k.split("/"))]
    assert set(expert) <= changed
    assert not {k for k in llm if k not in expert and "lora" not in k} & changed


def test_without_lora_no_weight_is_frozen():
    params = flow_model.param_shapes(_config(()))
    trainable, frozen = freeze.split(params, _config(()))
    assert frozen == {} and flatten_tree(trainable).keys() == flatten_tree(params).keys()


def test_the_freeze_rule_names_the_expert_by_its_suffix():
    config = _config(("action_expert",))
    assert freeze.is_frozen(("PaliGemma", "llm", "layers", "mlp_1", "linear"), config)
    assert freeze.is_frozen(("PaliGemma", "llm", "final_norm_1", "scale"), config)
    assert not freeze.is_frozen(("PaliGemma", "llm", "layers", "mlp", "linear"), config)
    assert not freeze.is_frozen(("PaliGemma", "llm", "layers", "mlp_1", "linear_lora_a"), config)
    assert not freeze.is_frozen(("PaliGemma", "img", "head", "kernel"), config)


def _save_openpi(path, params):
    with ocp.PyTreeCheckpointer() as checkpointer:
        checkpointer.save(path, {"params": params})
    return path


@pytest.mark.slow  # a LoRA model's compile: the slow lane
def test_a_base_checkpoint_starts_a_lora_model_with_its_adapters_from_the_init(tmp_path):
    base = _flat(flow_model.init_params(_config(()), jax.random.key(3)))
    path = _save_openpi(tmp_path / "params", _unflatten(base))
    config = _config()
    restored = _flat(load_pretrained(path, config, seed=5))
    init = _flat(flow_model.init_params(config, jax.random.key(5)))
    assert set(restored) == set(init)
    for key, value in restored.items():
        np.testing.assert_array_equal(value, init[key] if "lora" in key else base[key])


@pytest.mark.slow  # a training
def test_a_lora_checkpoint_restores_with_its_own_adapters(tmp_path):
    config = _config()
    params = _flat(flow_model.init_params(config, jax.random.key(3)))
    restored = _flat(load_pretrained(_save_openpi(tmp_path / "params", _unflatten(params)),
                                     config, seed=5))
    for key, value in restored.items():
        np.testing.assert_array_equal(value, params[key])


def test_a_checkpoint_with_other_adapters_is_refused_naming_them(tmp_path):
    params = _flat(flow_model.init_params(_config(("paligemma",)), jax.random.key(3)))
    path = _save_openpi(tmp_path / "params", _unflatten(params))
    with pytest.raises(ValueError, match=r"missing keys .*q_einsum_1/lora_a"):
        load_pretrained(path, _config())


@pytest.fixture(scope="module")
def lora_run(tmp_path_factory, demo_root):  # noqa: F811
    """A tiny `arm_focused_lora` run of 2 steps from a base checkpoint: (its folder, the base)."""
    folder = tmp_path_factory.mktemp("lora")
    base = jax.device_get(flow_model.init_params(_config(()), jax.random.key(7)))
    _save_openpi(folder / "base", base)
    prompts = sources.open_source({"root": str(demo_root)}, ActionLayout.preset("b1k_r1pro")).tasks
    spm = tokenizer_lib.cached_sentencepiece(prompts, _config(()).vocab_size, folder / "spm")
    workdir = tf.trained_tiny_run("configs/arm_focused_lora.py", folder / "run", demo_root,
                                  model__pretrained=str(folder / "base"),
                                  model__tokenizer=str(spm), model__sizes__siglip__conv_stem=0,
                                  optim__warmup_steps=0)
    return workdir, _flat(base)


@pytest.mark.slow
def test_a_lora_run_keeps_the_base_weights_of_its_experts_and_trains_the_rest(lora_run):
    workdir, base = lora_run
    state, _, _ = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).restore_for_eval(
        2, sharding.make_mesh(1), items=("params",))
    trained = _flat(state["params"])
    for key, value in base.items():
        if key.startswith("PaliGemma/llm/"):
            np.testing.assert_array_equal(value.astype(jnp.bfloat16), trained[key])
        elif key != "PaliGemma/llm/final_norm/scale":
            assert not np.array_equal(value, trained[key]), key
    assert any("lora" in key for key in trained)


@pytest.mark.slow
def test_a_lora_run_exports_its_adapters_under_openpis_lora_variants(lora_run, tmp_path):
    workdir, _ = lora_run
    summary = export_openpi.export(workdir, tmp_path / "openpi", force=True)
    model = summary["openpi_config"]["model"]
    assert (model["paligemma_variant"], model["action_expert_variant"]) == (
        "gemma_2b_lora", "gemma_300m_lora")
    with ocp.PyTreeCheckpointer() as checkpointer:
        exported = flatten_tree(checkpointer.restore(tmp_path / "openpi" / "params")["params"])
    assert exported.keys() == flatten_tree(flow_model.param_shapes(_config())).keys()


@pytest.mark.slow
def test_the_torch_mirror_of_a_lora_run_folds_the_adapters_and_predicts_like_it(lora_run,
                                                                                tmp_path):
    workdir, _ = lora_run
    arrays, config, _ = torch_checkpoint.read_checkpoint(str(workdir))
    run_config = json.loads((workdir / "config.json").read_text())
    adapted = model_config.from_model_config(run_config["model"])
    assert adapted.lora_experts == BOTH and config == adapted.without_lora()
    assert not [k for k in arrays if "lora" in k]
    torch_checkpoint.write_converted(str(tmp_path / "torch"), arrays, config, None, source="run")
    model, _ = torch_checkpoint.load_converted(str(tmp_path / "torch"))
    state, _, _ = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).restore_for_eval(
        2, sharding.make_mesh(1), items=("params",))
    observation = fake_observation(adapted, 2, seed=3)
    x = np.random.default_rng(0).standard_normal((2, 4, 32), dtype=np.float32)
    t = np.array([0.3, 0.9], np.float32)
    expected = flow_model.velocity(state["params"], observation, x, t, config=adapted)
    with torch.no_grad():
        np.testing.assert_allclose(model.velocity(observation, x, t).numpy(), expected, atol=1e-4)
