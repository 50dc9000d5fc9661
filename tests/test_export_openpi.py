"""A run exported for openpi: the layout openpi reads, the refusals, and the same actions back."""

import dataclasses
import json
import subprocess
import sys

import ml_collections
import numpy as np
import orbax.checkpoint as ocp
import pytest

import train_fixtures as tf
from train_fixtures import arm_delta_run, cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import pretrained
from pi0_armfix.model.tree import flatten_tree
from pi0_armfix.policies import inference, restore
from pi0_armfix.tools import export_openpi

# Delta torso and arm actions on a state reordered into the action order, as on B1K.
CONFIG = "configs/arm_delta.py"


# Every test that reads the run is in the slow lane: the fast lane trains this run for serving only
# (test_serve.py); a second pytest worker would train it again for the export.
@pytest.fixture(scope="module")
def run(arm_delta_run):  # noqa: F811
    return arm_delta_run


@pytest.fixture(scope="module")
def exported(run, tmp_path_factory):
    output = tmp_path_factory.mktemp("export") / "openpi"
    summary = export_openpi.export(run, output, force=True)
    return output, summary


@pytest.mark.slow
def test_a_run_openpi_cannot_build_is_refused_in_one_line_naming_the_key(run, tmp_path):
    with pytest.raises(ValueError, match=r"model\.preset = 'tiny': openpi builds only") as err:
        export_openpi.export(run, tmp_path / "out")
    assert "--force" in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_the_command_prints_the_refusal_and_exits_nonzero(run, tmp_path, cache_dir):  # noqa: F811
    done = subprocess.run([sys.executable, "-m", "pi0_armfix.tools.export_openpi",
                           f"--checkpoint={run}", f"--output={tmp_path / 'out'}"],
                          capture_output=True, text=True, env=tf.env(cache_dir), cwd=tf.REPO_ROOT)
    assert done.returncode != 0
    assert done.stderr.strip().splitlines()[-1].startswith(
        "pi0_armfix.tools.export_openpi: openpi cannot reproduce")


@pytest.mark.slow
def test_the_export_has_openpis_layout(exported):
    output, summary = exported
    assert (output / "params" / "_METADATA").is_file()
    assert summary["openpi_config"]["asset_id"] == "demo"  # the data folder's name
    stats = json.loads((output / "assets" / "demo" / "norm_stats.json").read_text())
    assert set(stats) == {"norm_stats"} and set(stats["norm_stats"]) == {"state", "actions"}
    for entry in stats["norm_stats"].values():
        assert set(entry) == {"mean", "std", "q01", "q99"}
        assert len({len(v) for v in entry.values()}) == 1
    saved = json.loads((output / export_openpi.EXPORT_FILE).read_text())
    assert saved["step"] == summary["step"] == 2 and saved["preset"] == "tiny"
    assert saved["refused_without_force"][0].startswith("model.preset = 'tiny'")
    assert saved["openpi_config"]["delta_action_mask"] == [-3, 11, -1, 7, -1]


@pytest.mark.slow
def test_params_restore_the_way_openpi_restores_them(run, exported):
    output, _ = exported
    with ocp.PyTreeCheckpointer() as checkpointer:
        tree = checkpointer.metadata(output / "params").item_metadata.tree
        assert set(tree) == {"params"}
        restored = checkpointer.restore(output / "params", ocp.args.PyTreeRestore(
            item={"params": tree["params"]},
            restore_args={"params": {k: v for k, v in _restore_args(tree["params"]).items()}}))
    flat = flatten_tree(restored["params"])
    assert not any(path.endswith("/value") for path in flat)
    own = flatten_tree(restore.restore_run(run).params)
    assert flat.keys() == own.keys()
    for key, value in own.items():
        np.testing.assert_array_equal(flat[key], np.asarray(value))


def _restore_args(tree):
    return {k: _restore_args(v) if isinstance(v, dict) else ocp.RestoreArgs(
        restore_type=np.ndarray) for k, v in tree.items()}


@pytest.mark.slow
def test_the_exported_folder_gives_the_runs_actions(run, exported):
    output, _ = exported
    original = restore.restore_run(run)
    params = pretrained.load_pretrained(output / "params", original.model_config)
    stats = stats_lib.load_norm_stats(output / "assets" / "demo" / "norm_stats.json")
    loaded = dataclasses.replace(original, params=params,
                                 norm_stats={**original.norm_stats, **stats})
    rng = np.random.default_rng(0)
    policy = inference.RunPolicy(original, seed=3)
    twin = inference.RunPolicy(loaded, seed=3)
    observation = {key: rng.integers(0, 255, (16, 16, 3), np.uint8)
                   for key in policy.keys.cameras}
    observation |= {policy.keys.state: rng.normal(size=policy.stored_state_width),
                    policy.keys.prompt: ""}
    # A constant state dim reaches the twin as ~1e-12 (`CONSTANT_STATE_SPREAD`), not 0.
    np.testing.assert_allclose(twin.infer([observation]), policy.infer([observation]),
                               rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_inference_levers_are_caveats_that_openpi_leaves_to_the_client(run):
    restored = restore.restore_run(run, levers={"average_draws": 4, "temperature": 0.5,
                                                  "group_draws": "base=2", "rtc": True,
                                                  "deadband": "base=0.1"})
    caveats = export_openpi.openpi_caveats(restored)
    assert any(c.startswith("eval.average_draws = 4") for c in caveats)
    assert any(c.startswith("eval.temperature = 0.5") for c in caveats)
    assert any(c.startswith("eval.group_draws = 'base=2'") for c in caveats)
    assert any(c.startswith("eval.rtc = True: how this run's chunks are executed") for c in caveats)
    assert any(c.startswith("eval.deadband = 'base=0.1'") for c in caveats)
    assert not any("eval.average_draws" in c or "eval.temperature" in c
                   for c in export_openpi.openpi_caveats(restore.restore_run(run)))


@pytest.mark.slow
def test_an_unwritable_output_is_refused_in_one_line_before_the_run_is_read(run, tmp_path,
                                                                          monkeypatch):
    (tmp_path / "a_file").write_text("")
    monkeypatch.setattr(export_openpi.restore, "restore_run",
                        lambda *a, **k: pytest.fail("the run was read"))
    with pytest.raises(ValueError, match=r"cannot write the results into .*a_file/export .*"
                                         r"pass an --output on a writable file system"):
        export_openpi.export(run, tmp_path / "a_file" / "export", force=True)


@pytest.mark.slow
def test_bfloat16_halves_the_params(run, tmp_path):
    summary = export_openpi.export(run, tmp_path / "bf16", dtype="bfloat16", force=True)
    with ocp.PyTreeCheckpointer() as checkpointer:
        restored = checkpointer.restore(tmp_path / "bf16" / "params")
    assert {str(np.asarray(v).dtype) for v in flatten_tree(restored["params"]).values()} == {
        "bfloat16"}
    assert summary["dtype"] == "bfloat16"


@pytest.mark.slow
def test_an_output_folder_with_files_is_never_overwritten(run, tmp_path):
    (tmp_path / "kept.txt").write_text("mine")
    with pytest.raises(ValueError, match="is not empty"):
        export_openpi.export(run, tmp_path, force=True)
    assert (tmp_path / "kept.txt").read_text() == "mine"


@pytest.mark.slow
def test_a_step_folder_names_its_run_and_step(run):
    assert export_openpi.resolve_checkpoint(run / "checkpoints" / "2") == (run, 2)
    with pytest.raises(ValueError, match="neither a run folder"):
        export_openpi.resolve_checkpoint(run / "plots")


@pytest.mark.parametrize("mode", ["zscore", "quantile"])
def test_openpis_formula_on_the_exported_stats_is_the_runs_normalization(mode):
    rng = np.random.default_rng(1)
    mean, std = rng.normal(size=4), np.array([0.5, 2.0, 0.0, 1.0])  # dim 2 constant
    stats = stats_lib.NormStats(mean=mean, std=std, q01=mean - 2 * std, q99=mean + 2 * std)
    written, adjusted = export_openpi.openpi_norm_stats({"state": stats, "actions": stats}, mode,
                                                        pi05=False)
    assert adjusted == {"state": [2], "actions": [2]}
    exported = {key: stats_lib.NormStats(**{k: np.asarray(v) for k, v in value.items()})
                for key, value in written["norm_stats"].items()}
    run_map = normalize.Normalizer.from_stats(stats, mode)
    x = mean + rng.normal(size=(50, 4))
    np.testing.assert_allclose(normalize.openpi_normalize(x, exported["state"], mode), run_map(x),
                               rtol=1e-5, atol=1e-5)
    y = rng.normal(size=(50, 4))  # what a model samples, noise on the constant dim included
    openpi = exported["actions"]
    if mode == "zscore":  # openpi's unnormalize
        back = y * (openpi.std + 1e-6) + openpi.mean
    else:
        back = (y + 1.0) / 2.0 * (openpi.q99 - openpi.q01 + 1e-6) + openpi.q01
    np.testing.assert_allclose(back, run_map.inverse(y), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(back[:, 2], mean[2], rtol=0, atol=1e-5)


def test_pi05s_state_statistics_are_written_as_they_are():
    stats = stats_lib.NormStats(mean=np.zeros(2), std=np.array([1.0, 0.0]), q01=-np.ones(2),
                                q99=np.array([1.0, -1.0]))
    written, adjusted = export_openpi.openpi_norm_stats({"state": stats, "actions": stats},
                                                        "quantile", pi05=True)
    assert "state" not in adjusted and adjusted["actions"] == [1]
    assert written["norm_stats"]["state"]["q99"] == [1.0, -1.0]


def test_delta_masks_become_openpis_make_bool_mask_arguments():
    mask = np.array([False] * 3 + [True] * 4 + [True] * 7 + [False] + [True] * 7 + [False])
    assert export_openpi.bool_mask_runs(mask) == (-3, 11, -1, 7, -1)
    assert export_openpi.bool_mask_runs(np.array([True, True])) == (2,)


@pytest.mark.slow
def test_a_run_relative_to_the_previous_action_is_one_openpi_cannot_reproduce(run):
    restored = restore.restore_run(run)
    config = ml_collections.ConfigDict(restored.config.to_dict())
    config.data.delta_reference = "previous_action"
    problems = export_openpi.openpi_problems(dataclasses.replace(restored, config=config))
    assert any(p.startswith("data.delta_reference = 'previous_action'") for p in problems)


@pytest.mark.slow
def test_an_output_that_is_a_file_is_refused_in_one_line(run, tmp_path):
    existing = tmp_path / "notes.txt"
    existing.write_text("kept")
    with pytest.raises(ValueError, match=r"--output=.*notes.txt is a file; name a new folder"):
        export_openpi.export(run, existing, force=True)
    assert existing.read_text() == "kept"


@pytest.mark.slow  # a run of two checkpoints and an export in a subprocess
def test_exporting_past_a_damaged_latest_checkpoint_says_so_in_one_line(tmp_path, demo_root,
                                                                         cache_dir):  # noqa: F811
    run = tf.trained_tiny_run(CONFIG, tmp_path / "run", demo_root, train__total_steps=4)
    for data in (run / "checkpoints" / "4" / "state").glob("ocdbt.process_0/d/*"):
        data.unlink()  # the arrays of the latest checkpoint are gone
    done = subprocess.run([sys.executable, "-m", "pi0_armfix.tools.export_openpi",
                           f"--checkpoint={run}", f"--output={tmp_path / 'out'}", "--force"],
                          env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Exception ignored" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "checkpoints/4 is damaged" in lines[0] and "step 2" in lines[0]
