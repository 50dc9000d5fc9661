"""A trained run as a policy: the inputs it builds, the policy server with openpi's real client,
malformed requests, the closed-loop evaluation and the latency benchmark."""

import asyncio
import json
import shutil
import socket
import subprocess
import sys
import threading
import time

import jax
import msgpack
import numpy as np
import pyarrow.parquet as pq
import pytest
from openpi_client import msgpack_numpy as openpi_msgpack
from openpi_client.websocket_client_policy import WebsocketClientPolicy
from websockets import exceptions as websockets_exceptions
from websockets.sync.client import connect

import train_fixtures as tf
from train_fixtures import arm_delta_run, cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix.data.formats import sources
from pi0_armfix.data.formats import video
from pi0_armfix.data.pipeline import batching, transforms
from pi0_armfix.evaluation import closed_loop as closed_loop_lib
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import outputs
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.model import flow_model
from pi0_armfix.model import inputs as model_inputs_lib
from pi0_armfix.policies import inference, restore
from pi0_armfix.policies.sampling import Sampling
from pi0_armfix.serving import server as server_lib
from pi0_armfix.sim import outcomes
from pi0_armfix.sim.env import DemoWorldEnv

# Delta arm actions and the baseline-order state reordered into the action order: the policy
# must select, normalize and undo the delta as training did.
CONFIG = "configs/arm_delta.py"


@pytest.fixture(scope="module")
def run(arm_delta_run):  # noqa: F811
    return arm_delta_run


def _serve_in_thread(policy, **kwargs):
    """A server of `policy` on a free port, in a thread of this process, once it listens."""
    policy_server = server_lib.PolicyServer(policy, "127.0.0.1", 0, **kwargs)
    loop, ready = asyncio.new_event_loop(), asyncio.Event()
    threading.Thread(target=lambda: loop.run_until_complete(policy_server.serve(ready)),
                     daemon=True).start()
    deadline = time.monotonic() + 60
    while not ready.is_set() and time.monotonic() < deadline:
        time.sleep(0.02)
    return policy_server


@pytest.fixture(scope="module")
def server(run):
    """A server of the run's policy on a free port, in a thread of this process."""
    return _serve_in_thread(inference.RunPolicy.from_workdir(run))


def test_a_request_sent_while_the_sampler_compiles_waits_for_it(run):
    policy = inference.RunPolicy.from_workdir(run)
    release, compiled = threading.Event(), []
    warm_up = policy.warm_up

    def slow_warm_up(*args):
        release.wait(30)
        warm_up(*args)
        compiled.append(policy._draws)

    policy.warm_up = slow_warm_up
    server = server_lib.PolicyServer(policy, "127.0.0.1", 0)
    loop, ready = asyncio.new_event_loop(), asyncio.Event()
    threading.Thread(target=lambda: loop.run_until_complete(server.serve(ready)),
                     daemon=True).start()
    while not ready.is_set():
        time.sleep(0.02)
    client = WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    threading.Timer(0.5, release.set).start()
    result = client.infer(_observation())  # sent before the warm-up ends
    assert compiled == [0] and result["actions"].shape[-1] == 23
    twin = inference.RunPolicy.from_workdir(run)
    np.testing.assert_allclose(result["actions"], twin.infer([_observation()])[0], atol=1e-6)


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
        delta_mask=policy.delta_mask, tokenize=policy.tokenize,
        image_size=policy.run.model_config.image_resolution)  # as training builds them
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
    for camera in inputs["image"]:  # the model's own conversion of training's images
        np.testing.assert_allclose(inputs["image"][camera], model_inputs_lib.model_image(
            expected["image"][camera], policy.run.model_config.image_resolution), atol=1e-6)
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


def _raw_request(port, message):
    with connect(f"ws://127.0.0.1:{port}", max_size=None) as raw:
        raw.recv()  # the metadata
        raw.send(message)
        return raw.recv()


def test_an_object_array_is_refused_and_the_server_keeps_serving(server):
    observation = _observation()
    state = {b"__ndarray__": True, b"data": bytes(range(16)), b"dtype": "|O", b"shape": [2]}
    request = msgpack.packb({**{k: v for k, v in observation.items()
                                if k != "observation/state"}, "observation/state": state},
                            default=server_lib._pack_array)
    assert "dtype '|O' is not accepted" in _raw_request(server.port, request)
    client = WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    assert client.infer(observation)["actions"].shape[1] == 23


@pytest.mark.parametrize("array, message", [
    ({b"__ndarray__": True, b"data": b"\0" * 3, b"dtype": "<f4", b"shape": [2]},
     "needs 8 bytes, the request holds 3"),
    ({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "<f4", b"shape": [-2]},
     "shape .* malformed"),
    ({b"__ndarray__": True, b"data": b"", b"dtype": "not a dtype", b"shape": [0]},
     "is not a numpy dtype"),
    ({b"__npgeneric__": True, b"data": 1, b"dtype": "|O"}, "is not accepted")])
def test_malformed_arrays_are_refused_before_use(array, message):
    with pytest.raises(ValueError, match=message):
        server_lib.unpack(msgpack.packb({"x": array}))


def test_an_empty_image_and_a_text_state_are_refused_by_key(server):
    client = WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    observation = _observation()
    with pytest.raises(RuntimeError, match="wrist_image_left.*h, w > 0"):
        client.infer({**observation, "observation/wrist_image_left": np.zeros((0, 8, 3), np.uint8)})
    with pytest.raises(RuntimeError, match="'observation/state'.* got str"):
        client.infer({**observation, "observation/state": "twenty-three numbers"})
    with pytest.raises(RuntimeError, match=r"'observation/state'\] is not finite in dim\(s\) "
                                           r"\[0, 1, 2"):
        client.infer({**observation, "observation/state": np.full(23, np.nan, np.float32)})


def test_a_request_over_the_size_cap_closes_only_that_connection(run):
    small = server_lib.PolicyServer(inference.RunPolicy.from_workdir(run), "127.0.0.1", 0,
                               max_message_bytes=4096)
    loop, ready = asyncio.new_event_loop(), asyncio.Event()
    threading.Thread(target=lambda: loop.run_until_complete(small.serve(ready)),
                     daemon=True).start()
    deadline = time.monotonic() + 60
    while not ready.is_set() and time.monotonic() < deadline:
        time.sleep(0.02)
    with connect(f"ws://127.0.0.1:{small.port}", max_size=None) as raw:
        raw.recv()
        raw.send(b"\0" * 10_000)
        with pytest.raises(Exception):  # the server closes this connection (1009)
            raw.recv()
    with connect(f"ws://127.0.0.1:{small.port}", max_size=None) as raw:
        assert isinstance(raw.recv(), bytes)  # a new client still gets the metadata


def test_a_client_that_leaves_mid_answer_is_no_error_of_the_server():
    class Leaving:
        id = "gone"

        async def send(self, message):
            raise websockets_exceptions.ConnectionClosed(None, None)

    class Stub:
        def metadata(self):
            return {}

    asyncio.run(server_lib.PolicyServer(Stub())._handle(Leaving()))


def test_images_of_any_size_compile_the_sampler_once(run):
    policy = inference.RunPolicy.from_workdir(run)
    observation = _observation()
    policy.infer([observation])
    compiled = flow_model.sample_actions._cache_size()
    for size in ((48, 40), (20, 64)):
        bigger = {**observation, **{key: np.zeros((*size, 3), np.uint8)
                                    for key in inference.B1K_KEYS.cameras}}
        assert policy.infer([bigger]).shape[1:] == (policy.horizon, 23)
    assert flow_model.sample_actions._cache_size() == compiled


def test_a_served_image_gets_the_resize_every_trained_frame_got(run):
    policy = inference.RunPolicy.from_workdir(run)
    size = policy.run.model_config.image_resolution
    picture = np.random.default_rng(0).integers(0, 256, (1, 3 * size[0], 3 * size[1], 3),
                                                 np.uint8)
    trained = video.fit_frames(picture, size)  # what a decoder or a batch of stored images gives
    assert trained.shape[1:3] == tuple(size)
    np.testing.assert_array_equal(policy._fit(picture), policy._fit(trained))
    np.testing.assert_allclose(policy._fit(trained), trained / 127.5 - 1, atol=1e-6)


def test_a_port_in_use_is_one_line_before_the_policy_loads(run, cache_dir):  # noqa: F811
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "pi0_armfix.serve", f"--workdir={run}", "--host=127.0.0.1",
             f"--port={port}"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
            text=True, timeout=300)
    assert result.returncode != 0
    assert result.stderr.strip().splitlines()[-1].startswith(
        f"pi0_armfix.serve: cannot listen on 127.0.0.1:{port}")
    assert "Traceback" not in result.stderr and "serving" not in result.stdout


def test_arrays_round_trip_between_the_server_and_openpis_encoding():
    payload = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.int64(3), "c": "x"}
    for packed, unpack in ((server_lib.pack(payload), openpi_msgpack.unpackb),
                           (openpi_msgpack.packb(payload), server_lib.unpack)):
        restored = unpack(packed)
        np.testing.assert_array_equal(restored["a"], payload["a"])
        assert restored["b"] == 3 and restored["c"] == "x"


@pytest.mark.slow  # a closed-loop evaluation of a trained run: the slow lane
def test_closed_loop_evaluation_reports_success_per_phase_and_draws_rollouts(run, cache_dir):  # noqa: F811
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={run}", "--closed_loop",
         "--episodes=1"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
        text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for kind in ("navigation", "manipulation", "task"):
        assert kind in result.stdout
    out = run / "eval" / "step_2"
    saved = json.loads((out / "closed_loop_1ep.json").read_text())
    assert saved["episodes"] == 1 and len(saved["episodes_detail"]) == 1
    assert saved["n_exec"] == 2  # half the tiny preset's horizon of 4
    assert 0.0 <= saved["success/manipulation"] <= 1.0
    for kind in ("navigation", "manipulation"):  # every failed phase has its reason
        failed = sum(saved[f"failure/{kind}/{r}"] for r in outcomes.FAILURE_REASONS[kind])
        assert failed == pytest.approx(1 - saved[f"phase_success/{kind}"])
    assert "phases failed:" in result.stdout
    assert all(p["reason"] or p["success"] for p in saved["episodes_detail"][0]["phases"])
    assert saved["gripper_hysteresis"] is None
    assert (out / "rollouts_1ep.png").stat().st_size > 10_000
    if not saved["success/task"]:  # strict JSON: no time to success is null, not NaN
        assert saved["seconds_to_success"] is None


def test_closed_loop_outputs_are_named_by_their_settings_and_never_replaced(tmp_path):
    settings = ({}, {"n_exec": 4}, {"rtc": True}, {"temporal_ensemble": 0.1},
                {"deadband": "base=0.2"}, {"group_draws": "base=4"}, {"average_draws": 4})
    names = [closed_loop_lib.closed_loop_paths(
        tmp_path, 5, episodes=50, levers=Sampling(**levers).tag(closed_loop=True))[0].name
        for levers in settings]
    assert names == ["closed_loop_50ep.json", "closed_loop_50ep_exec4.json",
                     "closed_loop_50ep_rtc.json", "closed_loop_50ep_ens0.1.json",
                     "closed_loop_50ep_deadband-base0.2.json",
                     "closed_loop_50ep_draws-base4.json",
                     "closed_loop_50ep_avg4.json"]
    assert closed_loop_lib.closed_loop_paths(tmp_path, 5, episodes=10)[0].name == \
        "closed_loop_10ep.json"


def test_closed_loop_outputs_name_the_inference_levers():
    tag = Sampling(average_draws=4, temperature=0.5).tag()
    path, _ = closed_loop_lib.closed_loop_paths("run", 5, episodes=20, levers=tag)
    assert path.name == "closed_loop_20ep_avg4_temp0.5.json"
    assert Sampling().tag() == ""


def test_a_policy_with_levers_averages_its_draws_and_says_so(run):
    rng = np.random.default_rng(0)
    plain = inference.RunPolicy.from_workdir(run, seed=1)
    averaged = inference.RunPolicy.from_workdir(run, seed=1, levers={"average_draws": 4})
    observation = {**{key: rng.integers(0, 255, (32, 32, 3), np.uint8)
                      for key in plain.keys.cameras},
                   plain.keys.state: rng.normal(size=plain.stored_state_width),
                   plain.keys.prompt: ""}
    assert averaged.metadata()["average_draws"] == 4 and plain.metadata()["temperature"] == 1.0
    a, b = averaged.infer([observation]), averaged.infer([observation])
    assert not np.array_equal(a, b)  # each request its own draws
    # The mean of 4 draws varies less between requests than one draw does.
    singles = np.stack([plain.infer([observation]) for _ in range(6)])
    means = np.stack([averaged.infer([observation]) for _ in range(6)])
    assert means.std(axis=0).mean() < singles.std(axis=0).mean()


def test_the_evaluator_and_the_served_policy_sample_a_chunk_alike(run):
    restored = restore.restore_run(run, levers={"average_draws": 2, "temperature": 0.5,
                                                  "group_draws": "base=3"})
    policy = inference.RunPolicy(restored)
    evaluator, mesh = evaluator_lib.run_evaluator(restored)
    assert evaluator.predict.sampling == policy.sampling
    with jax.set_mesh(mesh):
        evaluated = evaluator.sample(restored.params)  # [draws, N, H, A]: the base of 3, else 2
    batch, rows = evaluator.chunks.batches[0], evaluator.chunks.batch_rows[0]
    observation = {k: v for k, v in batch.items() if k not in ("actions", "action_is_pad")}
    noise = np.zeros((3, len(batch["actions"]), *evaluator.predict.noise.shape[2:]), np.float32)
    noise[:, :rows] = evaluator.predict.noise[:3, :rows]  # the first draw's three noises
    served = policy.sample(restored.params, None, observation, noise=noise.reshape(
        -1, *noise.shape[2:]))
    np.testing.assert_allclose(np.asarray(served)[:rows], evaluated[0, :rows], atol=1e-5)
    # drawn from a key, the policy's noise is the levers' (`Sampling.noise`): scaled alike
    key = jax.random.key(4)
    np.testing.assert_allclose(
        policy.sample(restored.params, key, observation),
        policy.sample(restored.params, None, observation, noise=policy.sampling.noise(
            key, (3 * len(batch["actions"]), *evaluator.predict.noise.shape[2:]))), atol=1e-6)


def test_a_wide_deadband_holds_the_previous_action_but_leaves_an_episodes_first_chunk_alone(run):
    draws = {}
    for band in ("torso=1e9", None):
        restored = restore.restore_run(run, levers={"deadband": band})
        evaluator, mesh = evaluator_lib.run_evaluator(restored)
        with jax.set_mesh(mesh):
            draws[band] = evaluator.absolute_draws(restored.params)[0]  # [N, H, A]
    chunks, torso = evaluator.chunks, list(range(3, 7))
    first = chunks.chunk_names[:, 1] == 0  # nothing executed yet, as in the closed loop
    assert first.sum() == 2 and (~first).sum() > 0
    held = (chunks.previous / chunks.scale)[~first][:, None, torso]
    np.testing.assert_allclose(draws["torso=1e9"][~first][..., torso],
                               np.broadcast_to(held, draws[None][~first][..., torso].shape))
    # ... whose first command passes, the band then holding it, as the closed loop does
    np.testing.assert_array_equal(draws["torso=1e9"][first][:, 0], draws[None][first][:, 0])
    np.testing.assert_array_equal(draws["torso=1e9"][first][..., torso],
                                  np.broadcast_to(draws[None][first][:, :1, torso],
                                                  draws[None][first][..., torso].shape))
    np.testing.assert_array_equal(np.delete(draws["torso=1e9"], torso, -1),
                                  np.delete(draws[None], torso, -1))  # the others as sampled


@pytest.mark.parametrize("levers, message", [
    ({"temperature": 0.0}, r"temperature = 0.0 \(eval.temperature or --temperature\) must be "
                           r"in \(0, 1\]"),
    ({"average_draws": 0}, r"average_draws = 0 \(eval.average_draws or --average_draws\) must "
                           "be a whole number >= 1"),
    ({"draws": 2}, r"unknown inference lever\(s\) \['draws'\]")])
def test_bad_levers_are_refused_before_the_checkpoint_is_read(levers, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        restore.restore_run(tmp_path / "no run here", levers=levers)


@pytest.mark.parametrize("kwargs, message", [({"episodes": 0}, "--episodes = 0 must be >= 1"),
                                             ({"sim_seed": -1}, "--sim_seed = -1 must be >= 0")])
def test_closed_loop_settings_are_refused_before_the_policy_loads(kwargs, message, tmp_path):
    with pytest.raises(ValueError, match=message):
        closed_loop_lib.closed_loop(tmp_path / "no run here", **kwargs)


def test_a_read_only_run_folder_is_refused_before_the_rollouts(run, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(closed_loop_lib.rollout_lib, "rollout", lambda *a, **k: calls.append(1))
    monkeypatch.setattr(closed_loop_lib, "writable_folder", lambda folder: (_ for _ in ()).throw(
        ValueError(f"cannot write the results into {folder}")))
    with pytest.raises(ValueError, match="cannot write the results into .*eval/step_2"):
        closed_loop_lib.closed_loop(run, episodes=1, progress=False)
    assert not calls


def test_real_time_chunking_weights_decay_over_the_overlap_to_zero():
    weights = inference.soft_mask(horizon=8, overlap=4)
    assert weights[4:].tolist() == [0.0] * 4
    assert np.all(np.diff(weights[:5]) < 0) and 0.5 < weights[0] < 1.0
    assert inference.soft_mask(8, 4, delay=2)[:2].tolist() == [1.0, 1.0]


@pytest.mark.slow  # a closed-loop evaluation of a trained run: the slow lane
def test_closed_loop_with_real_time_chunking_follows_the_tail(run, monkeypatch):
    asked = []
    infer = inference.RunPolicy.infer

    def recording_infer(self, observations, follow=None):
        asked.append(follow)
        return infer(self, observations, follow=follow)

    monkeypatch.setattr(inference.RunPolicy, "infer", recording_infer)
    _, summary = closed_loop_lib.closed_loop(run, episodes=1, levers={"rtc": True},
                                             progress=False)
    assert summary["rtc"] is True and summary["n_exec"] == 2
    assert asked[0] is None and all(f.shape == (1, 2, 23) for f in asked[1:])
    saved = json.loads((run / "eval" / "step_2" / "closed_loop_1ep_rtc.json").read_text())
    assert saved["rtc"] is True
    assert (run / "eval" / "step_2" / "rollouts_1ep_rtc.png").exists()


@pytest.mark.slow  # a whole benchmark
def test_server_latency_benchmark_prints_percentiles(run, cache_dir):  # noqa: F811
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.bench", "serve", f"--workdir={run}", "--requests=4",
         "--warmup=1"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
        text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "round trip per infer: p50" in result.stdout and "p95" in result.stdout


def test_an_unwritable_results_folder_is_named(tmp_path):
    blocker = tmp_path / "eval"
    blocker.write_text("a file where the folder should be")
    with pytest.raises(ValueError, match=r"cannot write the results into .*eval/step_2"):
        outputs.writable_folder(blocker / "step_2")


@pytest.mark.slow  # a server process on a copied run folder
def test_a_run_folder_serves_without_its_data(tmp_path, cache_dir, demo_root):  # noqa: F811
    data = shutil.copytree(demo_root, tmp_path / "data")
    workdir = tmp_path / "run"
    trained = tf.run_train(CONFIG, workdir, tf.tiny_overrides(data), cache_dir)
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert (workdir / "policy_inputs.json").is_file() and (workdir / "tokenizer.model").is_file()
    twin = inference.RunPolicy.from_workdir(workdir)
    observation = _observation()
    expected = twin.infer([observation])
    shutil.rmtree(data)  # the robot-side machine has the run folder only
    policy = inference.RunPolicy.from_workdir(workdir)
    np.testing.assert_allclose(policy.infer([observation]), expected, atol=1e-6)


def _as_main_job_world(run, folder):
    """A copy of `run` whose config names the embedded demo (`data.root=''`), as the main job's
    does: the world whose adopted execution the commands default to (the run folder keeps its
    inputs, so nothing reads the data)."""
    copy = shutil.copytree(run, folder)
    for path in copy.glob("checkpoints/*/config/metadata"):
        config = json.loads(path.read_text())
        config["data"]["root"] = ""
        path.write_text(json.dumps(config))
    return copy


def test_the_readme_serve_command_on_a_main_job_run_answers_the_openpi_client(
        run, tmp_path, cache_dir):  # noqa: F811
    workdir = _as_main_job_world(run, tmp_path / "run")
    with socket.create_server(("127.0.0.1", 0)) as probe:
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, "-m", "pi0_armfix.serve", f"--workdir={workdir}", "--host=127.0.0.1",
         f"--port={port}"], env=tf.env(cache_dir), cwd=tf.REPO_ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        assert "serving step 2" in server.stdout.readline(), server.stderr.read()[-3000:]
        client = WebsocketClientPolicy(host="127.0.0.1", port=port)
        metadata = client.get_server_metadata()
        # the adopted execution's per-chunk levers; the chunk's execution is the client's
        assert (metadata["group_draws"], metadata["deadband"], metadata["temporal_ensemble"],
                metadata["rtc"]) == ("base=4+torso=8", "torso=2", 0.0, False)
        assert client.infer(_observation())["actions"].shape == (4, 23)
    finally:
        server.terminate()
        server.wait(30)


def test_the_b1k_harness_executes_a_main_job_run_with_the_adopted_execution(run, tmp_path):
    policy = inference.RunPolicy.from_workdir(_as_main_job_world(run, tmp_path / "run"))
    sampling = policy.sampling
    assert (sampling.n_exec, sampling.temporal_ensemble, sampling.group_draws,
            sampling.deadband) == (1, 0.01, "base=4+torso=8", "torso=2")  # H = 4: every quarter
    server = server_lib.PolicyServer(policy, "127.0.0.1", 0, protocol="b1k")
    assert server.session("client")._replanning.sampling == sampling


def test_a_previous_action_run_never_answers_a_mid_episode_request_relative_to_the_state(run):
    policy, twin = inference.RunPolicy.from_workdir(run), inference.RunPolicy.from_workdir(run)
    for p in (policy, twin):  # its actions relative to the previous command
        p.delta_reference = "previous_action"
        p.start = transforms.EpisodeStart.of(p.run.norm_stats, p.layout, None)
    server = _serve_in_thread(policy)
    client = WebsocketClientPolicy(host="127.0.0.1", port=server.port)
    assert client.get_server_metadata()["observation_keys"]["previous_action"] == (
        "previous_action")
    observation = _observation()
    first = client.infer(observation)
    assert first["relative_to"] == "start"  # a connection's first request: nothing executed yet
    second = client.infer(observation)  # the client sends no previous_action
    assert second["relative_to"] == "executed"
    executed = first["actions"][-1]  # n_exec 0: an openpi client executes the whole chunk
    twin._draws = 1
    np.testing.assert_allclose(second["actions"],
                               twin.infer([observation], previous=executed[None])[0], atol=1e-5)
    held = np.full(23, 0.3, np.float32)
    third = client.infer({**observation, "previous_action": held})
    assert third["relative_to"] == "previous_action"
    twin._draws = 2
    np.testing.assert_allclose(third["actions"], twin.infer(
        [{**observation, "previous_action": held}])[0], atol=1e-5)
