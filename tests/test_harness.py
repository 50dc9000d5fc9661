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

import numpy as np
import pytest
from websockets.sync.client import connect

import b1k2026_fixture
import b1k_fixture
import train_fixtures as tf
from pi0_armfix import harness, inference, serve, train

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
    server = serve.PolicyServer(inference.RunPolicy.from_workdir(workdir), "127.0.0.1", 0,
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
        self.metadata = serve.unpack(self.ws.recv())
        self.chunk = chunk

    def reset(self):
        self.ws.send(serve.pack({"reset": True}))  # and no reply is read

    def act(self, observation):
        request = dict(observation)
        if self.chunk > 1:
            request[harness.CHUNK_SIZE] = self.chunk
        self.ws.send(serve.pack(request))
        response = self.ws.recv()
        if isinstance(response, str):
            raise RuntimeError(f"Error in inference server:\n{response}")
        reply = serve.unpack(response)
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


def test_an_unknown_task_id_is_one_line_naming_it_and_prompt_overrides(run2025):
    workdir, data = run2025
    client = HarnessClient(_serve(workdir).port)
    with pytest.raises(RuntimeError, match=r"task_id 7 is not a task of the run's dataset .*"
                                           r"--prompt"):
        client.act(_observation(data[10]["state"][0], task_id=7))
    other = HarnessClient(_serve(workdir, prompt="turn on the radio").port)
    assert other.act(_observation(data[10]["state"][0], task_id=7))["action"].shape == (23,)


def test_2026_batched_envs_replay_chunks_from_a_queue_per_env(run2026):
    workdir, data = run2026
    server = _serve(workdir)
    client = HarnessClient(server.port, chunk=3)
    client.reset()
    proprio = np.stack([data[0]["state"][0], data[3]["state"][0]])  # 61-D, two envs
    reply = client.act(_observation(proprio, task_id=1, envs=2))
    assert reply["action"].shape == (2, 23) and reply["action_chunk"].shape == (2, 3, 23)
    assert not np.allclose(reply["action"][0], reply["action"][1])


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

    server = serve.PolicyServer(Compiling(), "127.0.0.1", 0)
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
