"""`serve --protocol=b1k` against a client that sends what BEHAVIOR-1K's evaluation harness sends
(its `WebsocketClientPolicy`, reduced: resets without reading a reply, RGBA cameras under its
keys, the proprio as the simulator gives it, `task_id` and no prompt, batched envs, chunk
replay), for tiny `:b1k` and `:b1k2026` runs whose data folders were removed."""

from __future__ import annotations

import asyncio
import shutil
import threading
import time
import urllib.error
import urllib.request

import jax
import numpy as np
import pytest
from websockets.sync.client import connect

import b1k2026_fixture
import b1k_fixture
import train_fixtures as tf
from pi0_armfix import train
from pi0_armfix.serving import server as server_lib
from pi0_armfix.serving import harness
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.policies import inference
from pi0_armfix.policies.sampling import Sampling

CAMERAS = list(harness.CAMERAS)


def _train_without_data(tmp_path_factory, scale, write):
    root = tmp_path_factory.mktemp(scale) / "data"
    data = write(root)
    config = tf.tiny_b1k_config(scale, root, **{"eval.every": 0})
    workdir = root.parent / "run"
    train.train_and_evaluate(config, str(workdir))
    shutil.rmtree(root)  # the serving machine has the run folder only
    return workdir, data


@pytest.fixture(scope="module")
def run2025(tmp_path_factory):
    return _train_without_data(tmp_path_factory, "b1k", b1k_fixture.write_b1k_dataset)


@pytest.fixture(scope="module")
def run2026(tmp_path_factory):
    return _train_without_data(tmp_path_factory, "b1k2026", b1k2026_fixture.write_b1k2026_dataset)


def _serve(workdir, **kwargs):
    server = server_lib.PolicyServer(inference.RunPolicy.from_workdir(workdir), "127.0.0.1", 0,
                                protocol="b1k", **kwargs)
    loop, ready = asyncio.new_event_loop(), asyncio.Event()
    threading.Thread(target=lambda: loop.run_until_complete(server.serve(ready)),
                     daemon=True).start()
    deadline = time.monotonic() + 120
    while not server.warm.is_set() and time.monotonic() < deadline:
        time.sleep(0.05)
    return server


class HarnessClient:
    """What B1K's harness does over the wire (OmniGibson's `WebsocketClientPolicy`)."""

    def __init__(self, port, chunk=0):
        self.ws = connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None)
        self.metadata = server_lib.unpack(self.ws.recv())
        self.chunk = chunk

    def reset(self):
        self.ws.send(server_lib.pack({"reset": True}))  # and no reply is read

    def act(self, observation):
        request = dict(observation)
        if self.chunk > 1:
            request[harness.CHUNK_SIZE] = self.chunk
        self.ws.send(server_lib.pack(request))
        response = self.ws.recv()
        if isinstance(response, str):
            raise RuntimeError(f"Error in inference server:\n{response}")
        reply = server_lib.unpack(response)
        if "action" not in reply:
            raise RuntimeError(f"Server response missing 'action' key: {reply}")
        if self.chunk > 1:
            chunk = reply["action_chunk"]
            assert chunk.shape == (*reply["action"].shape[:-1], self.chunk, 23)
            np.testing.assert_array_equal(chunk[..., 0, :], reply["action"])
        return reply


def _observation(proprio, task_id, side=224, envs=0, seed=0):
    rng = np.random.default_rng(seed)
    lead = (envs,) if envs else ()
    obs = {key: rng.integers(0, 255, (*lead, side, side, 4), dtype=np.uint8) for key in CAMERAS}
    obs |= {harness.PROPRIO: np.asarray(proprio, np.float32),
            "robot_r1::cam_rel_poses": np.zeros((*lead, 21), np.float32),
            harness.TASK_ID: np.full((*lead, 1) if envs else (1,), task_id, np.int64)}
    return obs


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_2025_harness_steps_get_one_command_each_after_unread_resets(run2025):
    workdir, data = run2025
    server = _serve(workdir)
    client = HarnessClient(server.port)
    client.reset()
    client.reset()
    proprio = data[10]["state"][0]  # 256-D
    for side in (224, 720):  # the default and the full-resolution wrapper
        reply = client.act(_observation(proprio, task_id=0, side=side))
        assert reply["action"].shape == (23,) and np.isfinite(reply["action"]).all()


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_an_unknown_task_id_is_one_line_naming_it_and_prompt_overrides(run2025):
    workdir, data = run2025
    client = HarnessClient(_serve(workdir).port)
    with pytest.raises(RuntimeError, match=r"task_id 120 is not a task of the run's dataset .*"
                                           r"--prompt"):
        client.act(_observation(data[10]["state"][0], task_id=120))
    other = HarnessClient(_serve(workdir, prompt="turn on the radio").port)
    assert other.act(_observation(data[10]["state"][0], task_id=120))["action"].shape == (23,)


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_2026_batched_envs_replay_chunks_from_a_queue_per_env(run2026):
    workdir, data = run2026
    server = _serve(workdir)
    client = HarnessClient(server.port, chunk=3)
    client.reset()
    proprio = np.stack([data[0]["state"][0], data[3]["state"][0]])  # 61-D, two envs
    reply = client.act(_observation(proprio, task_id=1, envs=2))
    assert reply["action"].shape == (2, 23) and reply["action_chunk"].shape == (2, 3, 23)
    assert not np.allclose(reply["action"][0], reply["action"][1])


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_the_same_seed_and_resets_give_the_same_actions(run2026):
    workdir, data = run2026
    proprio = data[0]["state"][0]
    runs = []
    for _ in range(2):
        client = HarnessClient(_serve(workdir, seed=5).port)
        episode = []
        for _ in range(2):
            client.reset()
            episode.append([client.act(_observation(proprio, task_id=0))["action"]
                            for _ in range(3)])
        runs.append(np.asarray(episode))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0][0], runs[0][1])  # episode 2 draws other noise


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_a_request_without_proprio_is_one_line_and_the_server_keeps_serving(run2026):
    workdir, data = run2026
    client = HarnessClient(_serve(workdir).port)
    observation = _observation(data[0]["state"][0], task_id=0)
    with pytest.raises(RuntimeError, match="the request lacks 'robot_r1::proprio'"):
        client.act({k: v for k, v in observation.items() if k != harness.PROPRIO})
    assert client.act(observation)["action"].shape == (23,)


def test_healthz_says_ready_only_once_the_sampler_is_compiled():
    release = threading.Event()

    class Compiling:
        horizon = 4

        def metadata(self):
            return {}

        def warm_up(self):
            release.wait(30)

    server = server_lib.PolicyServer(Compiling(), "127.0.0.1", 0)
    loop, ready = asyncio.new_event_loop(), asyncio.Event()
    threading.Thread(target=lambda: loop.run_until_complete(server.serve(ready)),
                     daemon=True).start()
    while not ready.is_set():
        time.sleep(0.02)
    url = f"http://127.0.0.1:{server.port}/healthz"
    with pytest.raises(urllib.error.HTTPError, match="503"):
        urllib.request.urlopen(url, timeout=5)
    release.set()
    server.warm.wait(10)
    assert urllib.request.urlopen(url, timeout=5).status == 200


class Recorder:
    """A policy that records what the session asks of it; its chunk's values are the draw's key
    data, so two draws from the same stream position are equal."""

    horizon = 4
    layout = ActionLayout.preset("b1k_r1pro")
    stored_state_width = 256  # a B1K 2025 run
    keys = inference.B1K_KEYS
    task_prompts = {0: "trained task", 1: "listed, never trained"}
    trained_prompts = frozenset({"trained task"})

    def __init__(self):
        self.calls = []

    def infer(self, observations, follow=None, rng=None):
        self.calls.append({"follow": follow, "prompts": [o["prompt"] for o in observations]})
        value = float(np.asarray(jax.random.key_data(rng)).sum() % 1000)
        return np.stack([np.full((self.horizon, 23), value + i, np.float32)
                         for i in range(len(observations))])


def _step(session, task_id=0):
    return session.answer(_observation(np.zeros(256), task_id=task_id, side=8))["action"]


def test_a_batched_request_with_unequal_leading_sizes_is_one_line_naming_them():
    session = harness.HarnessSession(Recorder(), sampling=Sampling(n_exec=2))
    message = _observation(np.zeros((3, 256)), task_id=0, side=8, envs=2)
    with pytest.raises(ValueError, match=r"leading sizes \{'robot_r1::proprio': 3, .*: 2"):
        session.answer(message)


def test_the_other_releases_proprio_is_named_with_the_runs_release():
    session = harness.HarnessSession(Recorder(), sampling=Sampling(n_exec=2))
    with pytest.raises(ValueError, match=r"'robot_r1::proprio' has 61 dims; this is a B1K 2025 "
                                         r"\(256-D proprio\) run"):
        session.answer(_observation(np.zeros(61), task_id=0, side=8))


def test_rtc_follows_the_unexecuted_tail_from_the_second_chunk_of_an_episode():
    policy = Recorder()
    session = harness.HarnessSession(policy, sampling=Sampling(n_exec=2, rtc=True))
    for _ in range(4):
        _step(session)
    assert policy.calls[0]["follow"] is None
    assert policy.calls[1]["follow"].shape == (1, 2, 23)  # H - n_exec actions of the last chunk
    session.reset()
    _step(session)
    assert policy.calls[2]["follow"] is None  # a new episode starts free


def test_each_connection_draws_its_own_noise_stream():
    alone = harness.HarnessSession(Recorder(), seed=3, sampling=Sampling(n_exec=1))
    expected = [_step(alone) for _ in range(3)]
    shared = Recorder()
    first = harness.HarnessSession(shared, seed=3, sampling=Sampling(n_exec=1))
    second = harness.HarnessSession(shared, seed=3, sampling=Sampling(n_exec=1))
    got = []
    for _ in range(3):
        got.append(_step(first))
        _step(second)  # another connection in between changes nothing of the first's
    np.testing.assert_array_equal(np.stack(got), np.stack(expected))


def test_a_task_the_run_never_trained_on_is_served_with_one_warning(capsys):
    policy = Recorder()
    session = harness.HarnessSession(policy, sampling=Sampling(n_exec=1))
    for _ in range(3):
        _step(session, task_id=1)
    warnings = [line for line in capsys.readouterr().err.splitlines() if "task_id 1" in line]
    assert len(warnings) == 1 and "not a task this run trained on" in warnings[0]
    _step(session, task_id=7)  # not in the run's table: B1K 2025's task 7
    assert policy.calls[-1]["prompts"] == ["picking up toys"]


def test_the_harness_grippers_commit_through_the_latch():
    class Flicker(Recorder):
        def infer(self, observations, follow=None, rng=None):
            chunk = np.zeros((1, self.horizon, 23), np.float32)
            chunk[0, :, 14] = [1.0, 0.3, -0.3, -1.0]  # left gripper: open, in-band, closed
            return chunk

    session = harness.HarnessSession(Flicker(), sampling=Sampling(
        n_exec=4, gripper_hysteresis=(0.9, -0.98)))
    assert [float(_step(session)[14]) for _ in range(4)] == [1.0, 1.0, 1.0, -1.0]


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_the_harness_image_sizes_are_compiled_before_healthz_says_ready(run2025):
    workdir, _ = run2025
    server = _serve(workdir)
    assert server.warm.is_set()
    compiled = server.policy._to_model_images._cache_size()
    for size in harness.IMAGE_SIZES:  # what B1K's harness sends compiles nothing new
        server.policy._fit(np.zeros((1, *size, 3), np.uint8))
    assert server.policy._to_model_images._cache_size() == compiled


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_a_batched_task_id_of_another_length_than_the_envs_is_one_error(run2026):
    workdir, data = run2026
    client = HarnessClient(_serve(workdir).port)
    proprio = np.stack([data[0]["state"][0]] * 3)  # three envs
    observation = _observation(proprio, task_id=1, envs=3)
    observation[harness.TASK_ID] = np.array([[1], [2]], np.int64)  # two tasks
    with pytest.raises(RuntimeError, match=r"'task_id' has 2 entries for 3 envs: send one per env"):
        client.act(observation)
    observation[harness.TASK_ID] = np.array([1], np.int64)  # one for every env
    assert client.act(observation)["action"].shape == (3, 23)


@pytest.mark.slow  # a trained run of B1K's scale served to the harness
def test_batched_cameras_beside_an_unbatched_proprio_are_blamed_on_the_proprio(run2026):
    workdir, data = run2026
    client = HarnessClient(_serve(workdir).port)
    observation = _observation(np.stack([data[0]["state"][0]] * 2), task_id=1, envs=2)
    observation[harness.PROPRIO] = observation[harness.PROPRIO][0]  # [D]: no env dim
    with pytest.raises(RuntimeError, match=r"hold a leading env dim but 'robot_r1::proprio' is "
                                           r"\[61\]: .*\[N, D\]"):
        client.act(observation)


def test_a_chunk_longer_than_n_exec_is_one_plan_of_the_fresh_observation(capsys):
    policy = Recorder()
    session = harness.HarnessSession(policy, sampling=Sampling(n_exec=1))
    for step in range(3):  # the harness replays 3 actions of each reply before asking again
        message = {**_observation(np.zeros(256), task_id=0, side=8),
                   harness.CHUNK_SIZE: np.array([3])}
        reply = session.answer(message)
        assert reply["action_chunk"].shape == (3, 23)
        assert len(policy.calls) == step + 1  # one draw per request, none on a stale observation
        assert (reply["action_chunk"] == reply["action_chunk"][0]).all()  # all from that draw
    assert session._replanning._now[0] == 9  # what the harness executed, for ensembling


def test_a_chunk_longer_than_the_horizon_is_one_line_naming_it():
    session = harness.HarnessSession(Recorder(), sampling=Sampling(n_exec=1))
    message = {**_observation(np.zeros(256), task_id=0, side=8), harness.CHUNK_SIZE: np.array([5])}
    with pytest.raises(ValueError, match=r"__action_chunk_size__ = 5 exceeds the policy's "
                                         r"horizon H = 4"):
        session.answer(message)
