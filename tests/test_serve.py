"""A trained run as a policy: the inputs it builds, the policy server with openpi's real client,
malformed requests, the closed-loop evaluation and the latency benchmark."""

import asyncio
import json
import subprocess
import sys
import threading
import time

import numpy as np
import pyarrow.parquet as pq
import pytest
from openpi_client import msgpack_numpy as openpi_msgpack
from openpi_client.websocket_client_policy import WebsocketClientPolicy
from websockets.sync.client import connect

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import evaluate, inference, serve
from pi0_armfix.data import batching, sources
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.sim import world as world_lib
from pi0_armfix.sim.env import DemoWorldEnv

# Delta arm actions and the baseline-order state reordered into the action order: the policy
# must select, normalize and undo the delta as training did.
CONFIG = "configs/arm_delta.py"


@pytest.fixture(scope="module")
def run(tmp_path_factory, cache_dir, demo_root):  # noqa: F811
    workdir = tmp_path_factory.mktemp("run")
    trained = tf.run_train(CONFIG, workdir, tf.tiny_overrides(demo_root), cache_dir)
    assert trained.returncode == 0, trained.stderr[-3000:]
    return workdir


@pytest.fixture(scope="module")
def server(run):
    """A server on a free port, in a thread of this process; (server, its policy's twin)."""
    policy_server = serve.PolicyServer(inference.RunPolicy.from_workdir(run), "127.0.0.1", 0)
    loop, ready = asyncio.new_event_loop(), asyncio.Event()
    threading.Thread(target=lambda: loop.run_until_complete(policy_server.serve(ready)),
                     daemon=True).start()
    deadline = time.monotonic() + 60
    while not ready.is_set() and time.monotonic() < deadline:
        time.sleep(0.02)
    return policy_server


def _observation(seed=0):
    observation, _ = DemoWorldEnv().reset(seed=seed)
    return observation


def test_the_policy_builds_the_inputs_training_builds_and_undoes_the_delta(run, demo_root):  # noqa: F811
    policy = inference.RunPolicy.from_workdir(run)
    config, layout = policy.run.config, policy.layout
    table = sources.open_source(config.data, layout).load_table([0])
    transform = batching.BatchTransform(
        table, layout, norm_stats=policy.run.norm_stats,
        norm_mode=model_config_lib.norm_mode(config), action_horizon=policy.horizon,
        delta_mask=policy.delta_mask, tokenize=policy.tokenize)
    frames = np.array([5, 40])
    expected = transform(frames)
    stored = pq.read_table(demo_root / "data/chunk-000/episode_000000.parquet")
    raw_state = np.stack(stored.column("observation.state").to_numpy(zero_copy_only=False))
    observations = [{**{key: table.images(int(f))[camera]
                        for key, camera in inference.B1K_KEYS.cameras.items()},
                     "observation/state": raw_state[f], "prompt": table.tasks[0]} for f in frames]
    inputs, state = policy.model_inputs(observations)
    np.testing.assert_allclose(inputs["state"], expected["state"], atol=1e-6)
    for key in ("tokenized_prompt", "tokenized_prompt_mask"):
        np.testing.assert_array_equal(inputs[key], expected[key])
    for camera in inputs["image"]:
        np.testing.assert_array_equal(inputs["image"][camera], expected["image"][camera])
    true_chunks = table.actions[np.minimum(frames[:, None] + np.arange(policy.horizon),
                                           table.num_frames - 1)]
    np.testing.assert_allclose(policy.absolute(expected["actions"], state), true_chunks,
                               atol=1e-5)


def test_openpi_client_gets_the_metadata_and_the_policys_actions(server, run):
    client = WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    metadata = client.get_server_metadata()
    assert metadata["step"] == 2 and metadata["action_dim"] == 23
    assert metadata["observation_keys"]["observation/state"] == "state"
    twin = inference.RunPolicy.from_workdir(run)  # same run, same seed: the same first draw
    observation = _observation()
    server.policy._draws = 0
    result = client.infer(observation)
    assert result["actions"].shape == (metadata["action_horizon"], 23)
    assert result["actions"].dtype == np.float32 and result["server_timing"]["infer_ms"] > 0
    np.testing.assert_allclose(result["actions"], twin.infer([observation])[0], atol=1e-6)


def test_malformed_requests_get_an_error_and_the_server_keeps_serving(server):
    client = WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    observation = _observation()
    bad = {"missing state": ({k: v for k, v in observation.items()
                              if k != "observation/state"}, "lacks 'observation/state'"),
           "wrong width": ({**observation, "observation/state": np.zeros(5, np.float32)},
                           "must be 23 finite numbers"),
           "float image": ({**observation, "observation/wrist_image_left":
                            np.zeros((8, 8, 3), np.float32)}, "must be a uint8 image"),
           "no prompt": ({**observation, "prompt": 3}, "must be the task prompt")}
    for name, (request, message) in bad.items():
        with pytest.raises(RuntimeError, match=message):
            client.infer(request)
    with connect(f"ws://127.0.0.1:{server.port}", max_size=None) as raw:
        raw.recv()  # the metadata
        raw.send(b"\xc1 not msgpack")
        assert "not msgpack" in raw.recv()
        raw.send(openpi_msgpack.packb([1, 2, 3]))
        assert "must be an observation dict" in raw.recv()
    assert client.infer(observation)["actions"].shape[1] == 23


def test_arrays_round_trip_between_the_server_and_openpis_encoding():
    payload = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.int64(3), "c": "x"}
    for packed, unpack in ((serve.pack(payload), openpi_msgpack.unpackb),
                           (openpi_msgpack.packb(payload), serve.unpack)):
        restored = unpack(packed)
        np.testing.assert_array_equal(restored["a"], payload["a"])
        assert restored["b"] == 3 and restored["c"] == "x"


def test_closed_loop_evaluation_reports_success_per_phase_and_draws_rollouts(run, cache_dir):  # noqa: F811
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={run}", "--closed_loop",
         "--episodes=1"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
        text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for kind in ("navigation", "manipulation", "task"):
        assert kind in result.stdout
    out = run / "eval" / "step_2"
    saved = json.loads((out / "closed_loop.json").read_text())
    assert saved["episodes"] == 1 and len(saved["episodes_detail"]) == 1
    assert saved["n_exec"] == 2  # half the tiny preset's horizon of 4
    assert 0.0 <= saved["success/manipulation"] <= 1.0
    for kind in ("navigation", "manipulation"):  # every failed phase has its reason
        failed = sum(saved[f"failure/{kind}/{r}"] for r in world_lib.FAILURE_REASONS[kind])
        assert failed == pytest.approx(1 - saved[f"phase_success/{kind}"])
    assert "phases failed:" in result.stdout
    assert all(p["reason"] or p["success"] for p in saved["episodes_detail"][0]["phases"])
    assert saved["gripper_hysteresis"] is None
    assert (out / "rollouts.png").stat().st_size > 10_000


def test_real_time_chunking_weights_decay_over_the_overlap_to_zero():
    weights = inference.soft_mask(horizon=8, overlap=4)
    assert weights[4:].tolist() == [0.0] * 4
    assert np.all(np.diff(weights[:5]) < 0) and 0.5 < weights[0] < 1.0
    assert inference.soft_mask(8, 4, delay=2)[:2].tolist() == [1.0, 1.0]


def test_closed_loop_with_real_time_chunking_follows_the_tail(run, monkeypatch):
    asked = []
    infer = inference.RunPolicy.infer

    def recording_infer(self, observations, follow=None):
        asked.append(follow)
        return infer(self, observations, follow=follow)

    monkeypatch.setattr(inference.RunPolicy, "infer", recording_infer)
    _, summary = evaluate.closed_loop(run, episodes=1, follow_tail=True, progress=False)
    assert summary["follow_tail"] is True and summary["n_exec"] == 2
    assert asked[0] is None and all(f.shape == (1, 2, 23) for f in asked[1:])
    saved = json.loads((run / "eval" / "step_2" / "closed_loop_rtc.json").read_text())
    assert saved["follow_tail"] is True
    assert (run / "eval" / "step_2" / "rollouts_rtc.png").exists()


def test_server_latency_benchmark_prints_percentiles(run, cache_dir):  # noqa: F811
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.bench", "serve", f"--workdir={run}", "--requests=4",
         "--warmup=1"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
        text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "round trip per infer: p50" in result.stdout and "p95" in result.stdout
