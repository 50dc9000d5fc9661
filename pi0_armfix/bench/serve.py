"""Policy server latency: openpi's client against `python -m pi0_armfix.serve` over localhost.

    python -m pi0_armfix.bench serve [--workdir=RUN] [--requests=200] [--warmup=5] [--port=0] \
        [--protocol=openpi|b1k]

The server runs in its own process on RUN's latest checkpoint (no --workdir: a 2-step run of
`pi0_armfix/configs/uniform.py` on the demo preset is trained into a temporary folder first; latency
does not depend on the weights). The client is `openpi_client.WebsocketClientPolicy`, sending
observations of the demo world (`pi0_armfix.sim.env`, episode 0, one frame each); it prints the
round trip per `infer` (p50, p95, mean, max) and the server's own `infer_ms`, after `--warmup`
untimed requests (the first compiles the sampler).

`--protocol=b1k` measures what B1K's evaluation harness meets (`pi0_armfix/serving/harness.py`): the
seconds from the server's start until `/healthz` answers 200, the first step's latency right
after it (reset, then one RGBA 224² observation with the proprio and `task_id`, no warm-up
request: the server compiled before it said it was ready), and the per-step latency of the
following `--requests` steps (most pop the server-side queue; every `n_exec`-th replans).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench serve")
    parser.add_argument("--workdir", default="", help="run folder ('' = train a 2-step demo run)")
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--port", type=int, default=0, help="0 = a free port")
    parser.add_argument("--protocol", choices=("openpi", "b1k"), default="openpi")
    return parser.parse_args(argv[1:])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train_demo_run(folder: Path) -> Path:
    workdir = folder / "run"
    subprocess.run([sys.executable, "-m", "pi0_armfix.train", "--config=configs/uniform.py",
                    f"--workdir={workdir}", "--config.train.total_steps=2",
                    "--config.train.checkpoint_every=2", "--config.eval.every=0"],
                   cwd=REPO_ROOT, check=True, capture_output=True)
    return workdir


def start_server(workdir: Path, port: int, timeout: float = 300, protocol: str = "openpi",
                 env: dict[str, str] | None = None) -> subprocess.Popen:
    """`python -m pi0_armfix.serve` in its own process (`env`: its environment, default this
    one's), returned once /healthz answers."""
    server = subprocess.Popen(
        [sys.executable, "-m", "pi0_armfix.serve", f"--workdir={workdir}", "--host=127.0.0.1",
         f"--port={port}", f"--protocol={protocol}"], cwd=REPO_ROOT,
        env=dict(env or os.environ, PYTHONPATH=str(REPO_ROOT)),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"the server exited:\n{server.stdout.read()}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=1):
                return server
        except OSError:
            time.sleep(0.2)
    server.kill()
    raise RuntimeError(f"the server did not answer on port {port} within {timeout} s")


def harness_latency(workdir: Path, port: int, steps: int) -> None:
    """`--protocol=b1k`: start-up, first step after /healthz 200, per-step latency."""
    from websockets.sync.client import connect

    from pi0_armfix.serving import server as server_lib
    from pi0_armfix.serving import harness
    from pi0_armfix.data.pipeline import run_inputs

    inputs = run_inputs.load(workdir)
    width = inputs.state_width if inputs is not None else 23
    task = min(inputs.task_prompts) if inputs and inputs.task_prompts else 0
    rng = np.random.default_rng(0)
    observation = {key: rng.integers(0, 255, (224, 224, 4), dtype=np.uint8)
                   for key in harness.CAMERAS}
    observation |= {harness.PROPRIO: np.zeros(width, np.float32),
                    harness.TASK_ID: np.array([task], np.int64)}
    start = time.perf_counter()
    server = start_server(workdir, port, protocol="b1k")
    ready = time.perf_counter() - start
    try:
        with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
            meta = server_lib.unpack(ws.recv())
            ws.send(server_lib.pack({"reset": True}))  # the harness reads no reply
            latencies = []
            for _ in range(steps + 1):
                sent = time.perf_counter()
                ws.send(server_lib.pack(observation))
                reply = ws.recv()
                if isinstance(reply, str):
                    raise RuntimeError(reply)
                latencies.append(1000 * (time.perf_counter() - sent))
    finally:
        server.terminate()
        server.wait(30)
    rest = np.array(latencies[1:])
    print(f"B1K harness protocol, {meta['model']} preset (H = {meta['action_horizon']}), step "
          f"{meta['step']}, {workdir}:")
    print(f"  server start to /healthz 200: {ready:.1f} s (load, compile)")
    print(f"  first step after /healthz 200: {latencies[0]:.1f} ms")
    print(f"  next {steps} steps: p50 {np.percentile(rest, 50):.2f} ms, p95 "
          f"{np.percentile(rest, 95):.2f} ms, max {rest.max():.1f} ms (a replan every n_exec "
          "steps, the others from the queue)")


def main(argv: list[str]) -> None:
    args = _parse(argv)
    from openpi_client.websocket_client_policy import WebsocketClientPolicy

    from pi0_armfix.sim.env import DemoWorldEnv

    with tempfile.TemporaryDirectory() as folder:
        workdir = Path(args.workdir) if args.workdir else _train_demo_run(Path(folder))
        port = args.port or free_port()
        if args.protocol == "b1k":
            harness_latency(workdir, port, args.requests)
            return
        server = start_server(workdir, port)
        try:
            client = WebsocketClientPolicy(host="127.0.0.1", port=port)
            meta = client.get_server_metadata()
            env = DemoWorldEnv()
            observation, _ = env.reset(seed=0)
            for _ in range(args.warmup):
                client.infer(observation)
            round_trip, server_ms = [], []
            for _ in range(args.requests):
                start = time.perf_counter()
                result = client.infer(observation)
                round_trip.append(1000 * (time.perf_counter() - start))
                server_ms.append(result["server_timing"]["infer_ms"])
        finally:
            server.terminate()
            server.wait(30)
    rt, sv = np.array(round_trip), np.array(server_ms)
    print(f"policy server, {meta['model']} preset (H = {meta['action_horizon']}), step "
          f"{meta['step']}, {args.requests} requests over localhost (openpi-client):")
    print(f"  round trip per infer: p50 {np.percentile(rt, 50):.2f} ms, p95 "
          f"{np.percentile(rt, 95):.2f} ms, mean {rt.mean():.2f} ms, max {rt.max():.2f} ms")
    print(f"  server infer_ms:      p50 {np.percentile(sv, 50):.2f} ms, p95 "
          f"{np.percentile(sv, 95):.2f} ms")
