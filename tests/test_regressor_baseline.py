"""The plain regressor baseline: trained on a config's data, scored on its held-out chunks."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import arm_focused
from pi0_armfix.tools import regressor_baseline as regressor
from train_fixtures import demo_root, tiny_overrides  # noqa: F401  (fixture)


def tiny_config(root):
    config = arm_focused.get_config()
    config.update_from_flattened_dict(tiny_overrides(root))
    return config


def test_chunk_loss_counts_only_the_valid_steps_of_the_trained_dims():
    predicted = jnp.asarray([[[1.0, 5.0], [2.0, 7.0], [9.0, 9.0]]])  # [1, H=3, A=2]
    actions = jnp.zeros((1, 3, 2))
    is_pad = jnp.asarray([[False, False, True]])
    dim_mask = jnp.asarray([1.0, 0.0])  # dim 1 is constant: no loss
    # Steps 0 and 1 of dim 0: (1 + 4) / 2.
    assert float(regressor.chunk_loss(predicted, actions, is_pad, dim_mask)) == pytest.approx(2.5)


@pytest.mark.parametrize("network", [
    "cnn", pytest.param("pi0", marks=pytest.mark.slow)])  # the slow lane compiles pi0
def test_each_network_maps_an_observation_batch_to_a_chunk(network, demo_root):
    data = regressor.ConfigData(tiny_config(demo_root), demo_root.parent / f"stats_{network}.json")
    batch = regressor.observation_of(data.chunks.batches[0])
    net = regressor.make_network(network, data.model, data.layout.action_dim)
    params = net.init(jax.random.key(0), batch)
    chunk = net.apply(params, batch, None, False)
    assert chunk.shape == (len(batch["state"]), data.model.action_horizon,
                           data.layout.action_dim)


@pytest.mark.slow  # whole regressor runs: the slow lane
def test_the_baseline_writes_every_seed_and_evaluation_beside_the_do_nothing_rows(demo_root,
                                                                                 tmp_path):
    result = regressor.run(tiny_config(demo_root), tmp_path, network="cnn", seeds=2, steps=6,
                           evaluations=2, lr=1e-3, command="the command", code="abc")
    written = json.loads((tmp_path / regressor.RESULT_FILE).read_text())
    assert written["seeds"].keys() == {"0", "1"} == result["seeds"].keys()
    for records in written["seeds"].values():
        assert [r["step"] for r in records] == [3, 6]
        assert 0 < records[0]["train_seconds"] <= records[1]["train_seconds"]
        assert np.isfinite(records[-1]["metrics"]["skill/left_arm"])
    table = (tmp_path / regressor.TABLE_FILE).read_text()
    assert "2 seed(s)" in table and "the command" in table and "abc" in table
    assert "*persistence (do nothing)*" in table and "*state copy (do nothing)*" in table
    assert table.count("\n| 3 |") == 1 and table.count("\n| 6 |") == 1


@pytest.mark.slow  # two trainings
def test_the_same_seed_trains_the_same_regressor(demo_root, tmp_path):
    first, second = (regressor.run(tiny_config(demo_root), tmp_path / name, network="cnn",
                                   seeds=1, steps=3, evaluations=1, lr=1e-3)
                     for name in ("a", "b"))
    metrics = [json.dumps(r["seeds"]["0"][0]["metrics"], sort_keys=True) for r in (first, second)]
    assert metrics[0] == metrics[1]


@pytest.mark.parametrize("change, message", [
    (dict(network="mlp"), "--network = 'mlp'"),
    (dict(steps=2, evaluations=3), "--evaluations = 3 is more than --steps = 2"),
    (dict(seeds=0), "--seeds = 0 must be positive"),
])
def test_a_bad_flag_is_named_before_any_training(change, message, demo_root, tmp_path):
    kwargs = dict(network="cnn", seeds=1, steps=2, evaluations=1, lr=1e-3) | change
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        regressor.run(tiny_config(demo_root), tmp_path, **kwargs)
    assert not (tmp_path / regressor.RESULT_FILE).exists()


@pytest.mark.slow  # two regressor runs: the slow lane
def test_a_stopped_run_keeps_its_finished_seeds_and_trains_only_the_rest(demo_root, tmp_path,
                                                                         monkeypatch):
    config = tiny_config(demo_root)
    first = regressor.run(config, tmp_path, network="cnn", seeds=1, steps=2, evaluations=1,
                          lr=1e-3)
    trained = []
    real = regressor.train_seed
    monkeypatch.setattr(regressor, "train_seed",
                        lambda data, seed, **kw: trained.append(seed) or real(data, seed, **kw))
    again = regressor.run(config, tmp_path, network="cnn", seeds=2, steps=2, evaluations=1,
                          lr=1e-3)
    assert trained == [1]
    assert json.dumps(again["seeds"]["0"]) == json.dumps(first["seeds"]["0"])  # NaN included
    table = (tmp_path / regressor.TABLE_FILE).read_text()
    assert "2 seed(s)" in table and "95 % t interval over the 2 seeds" in table


@pytest.mark.slow  # a regressor run: the slow lane
def test_an_output_of_other_settings_is_refused_before_any_training(demo_root, tmp_path):
    config = tiny_config(demo_root)
    regressor.run(config, tmp_path, network="cnn", seeds=1, steps=2, evaluations=1, lr=1e-3)
    with pytest.raises(ValueError, match=r"other settings \(lr, steps differ\): choose another"):
        regressor.run(config, tmp_path, network="cnn", seeds=1, steps=3, evaluations=1, lr=1e-2)


def test_a_group_that_never_moves_reads_n_a_with_the_reason_not_nan():
    layout = ActionLayout({"arm": (0, 2), "hand": (2, 3)}, real_dim=3, action_dim=4,
                          roles={"arm": "arm", "hand": "hand"})

    def record(seed):
        metrics = {"skill/arm": 0.1 * seed, "skill/hand": float("nan"),
                   "motion_gain/arm": 0.5, "gripper_switch/f1": 0.0}
        metrics |= {f"{who}/{k}": 0.0 for who in ("persistence", "state_copy")
                    for k in ("skill/arm", "skill/hand", "motion_gain/arm")}
        return [{"step": 10, "train_seconds": 1.0, "metrics": metrics}]

    result = {"network": "cnn", "command": "c", "code": "x",
              "seeds": {str(s): record(s) for s in range(3)}}
    text = regressor.report(result, layout, ())
    assert "hand n/a (it never moves in the held-out chunks" in text and "nan [" not in text


def test_a_switch_f1_without_any_switch_reads_n_a_not_nan():
    layout = ActionLayout({"arm": (0, 2), "gripper": (2, 3)}, real_dim=3, action_dim=4,
                          roles={"arm": "arm", "gripper": "gripper"})
    metrics = {"skill/arm": 0.1, "skill/gripper": 0.2, "motion_gain/arm": 0.5,
               "gripper_switch/f1": float("nan")}
    metrics |= {f"{who}/{k}": 0.0 for who in ("persistence", "state_copy")
                for k in ("skill/arm", "skill/gripper", "motion_gain/arm")}
    result = {"network": "cnn", "command": "c", "code": "x",
              "seeds": {"0": [{"step": 10, "train_seconds": 1.0, "metrics": metrics}]}}
    text = regressor.report(result, layout, ("gripper",))
    assert "n/a (no switch, predicted or true)" in text and "nan" not in text
