"""A run's config is read once (pi0_armfix.training.run_spec, pi0_armfix.data.pipeline.data_spec): resolved
and checked before any I/O, every module handed its part."""

import sys

import ml_collections
import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import arm_focused, base
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.training.run_spec import RunSpec

# Where the config may be read: the resolver and the readers of one section each.
READERS = {"pi0_armfix.training.run_spec", "pi0_armfix.action_space", "pi0_armfix.model.config",
           "pi0_armfix.data.pipeline.data_spec"}


def _sections(config: ml_collections.ConfigDict) -> set[int]:
    """The ids of `config` and of every ConfigDict inside it."""
    ids = {id(config)}
    for value in config.values():
        if isinstance(value, ml_collections.ConfigDict):
            ids |= _sections(value)
    return ids


def _reading_modules(monkeypatch, config: ml_collections.ConfigDict) -> list[str]:
    """Records the pi0_armfix module of every key read of `config`, in order (a config built on
    the way, such as the base config's defaults, is not the run's)."""
    reads = []
    cls, watched = ml_collections.ConfigDict, _sections(config)
    for name in ("__getattr__", "__getitem__", "get", "to_dict", "to_json_best_effort"):
        original = getattr(cls, name)

        def recording(self, *args, _original=original, **kwargs):
            if id(self) not in watched:
                return _original(self, *args, **kwargs)
            frame = sys._getframe(1)
            while frame is not None and frame.f_globals.get("__name__", "").startswith(
                    "ml_collections"):
                frame = frame.f_back
            module = frame.f_globals.get("__name__", "") if frame is not None else ""
            if module.startswith("pi0_armfix"):
                reads.append(module)
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, recording)
    return reads


@pytest.mark.slow  # a training: the slow lane
def test_a_training_run_reads_its_config_once_while_resolving_it(tmp_path, demo_root,
                                                                 monkeypatch):
    config = arm_focused.get_config()
    config.update_from_flattened_dict(tf.tiny_overrides(demo_root, eval__every=2))
    reads = _reading_modules(monkeypatch, config)
    train.train_and_evaluate(config, str(tmp_path / "run"))
    assert reads and set(reads) <= READERS, sorted(set(reads) - READERS)
    entered = [m for i, m in enumerate(reads) if i == 0 or reads[i - 1] != m]
    # Each reader once, called from the resolver in turn.
    others = [m for m in entered if m != "pi0_armfix.training.run_spec"]
    assert len(others) == len(set(others)), entered


def test_every_config_check_fails_in_resolve_before_any_io(tmp_path):
    config = base.get_config()
    config.data.root = str(tmp_path / "missing")  # never opened: resolve fails first
    for key, value, match in (("loss.flow_samples", 0, "loss.flow_samples"),
                              ("train.log_every", 0, "train.log_every"),
                              ("optim.b1", 1.5, "optim.b1"),
                              ("data.curriculum", ((0, {"full": 1.0}),), "data.curriculum"),
                              ("data.delta_action_mask", (40,), "delta_action_mask")):
        bad = config.copy_and_resolve_references()
        bad.update_from_flattened_dict({key: value})
        with pytest.raises(ValueError, match=match):
            RunSpec.resolve(bad)


def test_resolve_records_the_models_normalization_in_the_config():
    config = base.get_config()
    config.data.norm = None
    spec = RunSpec.resolve(config)
    assert config.data.norm == spec.model.default_norm == spec.data.norm
    assert spec.config_json["data"]["norm"] == spec.data.norm


def test_a_data_spec_resolves_the_state_delta_dims_and_split():
    config = arm_focused.get_config()
    layout = ActionLayout.from_config(config.layout)
    spec = DataSpec.from_config(config, layout)
    assert spec.state_preset == "b1k_baseline23"  # the embedded demo's (data.root = '')
    assert spec.state_groups["left_arm"] == (7, 14)
    np.testing.assert_array_equal(np.flatnonzero(spec.delta_mask),
                                  [3, 4, 5, 6, *range(7, 14), *range(15, 22)])
    assert spec.heldout_episodes == config.eval.episodes and spec.seed == config.seed
    assert spec.curriculum.sources == ("full",)
