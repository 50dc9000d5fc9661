"""A trained run as a policy server that speaks openpi's websocket protocol.

    python -m pi0_armfix.serve --workdir=runs/arm_focused [--step=N] [--port=8000] \
        [--keys=observation/egocentric_camera=base_0_rgb,...,observation/state=state,prompt=prompt]

Any openpi client works against it (`openpi_client.websocket_client_policy.WebsocketClientPolicy`,
B1K's evaluation harness): on connect the server sends its metadata (`observation_keys` names
every key the policy reads); then every binary message is an observation dict, answered by
`{"actions": float32 [H, A], "server_timing": {"infer_ms"}}`, actions absolute and in the
dataset's units (`pi0_armfix.policies.inference.RunPolicy`). A run relative to the previous
command (`data.delta_reference=previous_action`) reads the request's `previous_action` (the
action the client last executed); a request without it is answered relative to the action of
this connection's last reply that the client executed last (the `--n_exec`-th, the chunk's last
for 0), or, on a connection's first request, to the episode's start as training had it
(`transforms.EpisodeStart`: the state and its mean offset, or the training split's mean action),
and the reply says which (`"relative_to"`: `previous_action`, `executed` or `start`). Messages
are msgpack with numpy arrays in openpi's encoding (`pack` / `unpack`). A request the policy cannot
read (not msgpack, not a dict, a missing key, a wrong state width, ...) is answered by a text
message naming the problem (openpi's client raises it as a RuntimeError); the connection and the
server stay up. `GET /healthz` answers 200 (openpi's health check). The run's execution
(`--execution`, default the world's adopted one; its `eval` levers and the flags in their place:
`policies.sampling.Sampling.for_run`) shapes every chunk; an openpi connection gets the per-chunk
levers (the draws averaged, the deadband, the grippers' hysteresis held across its requests as if
the client executed `--n_exec` actions of every chunk: it executes the chunks itself, so rtc and
temporal ensembling are its own), a B1K harness connection every lever (`policies.execution`).
"""


from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Sequence

from absl import app, flags

from pi0_armfix import cache, console
from pi0_armfix.policies import inference
from pi0_armfix.serving.server import MAX_MESSAGE_MB, PROTOCOLS, PolicyServer


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    cache.use_compilation_cache()
    logging.getLogger("websockets").setLevel(logging.WARNING)
    try:
        if FLAGS.max_message_mb < 1:
            raise ValueError(f"--max_message_mb = {FLAGS.max_message_mb} must be >= 1")
        # Bound before the (slow) policy load: a port in use is one line, at once.
        try:
            sock = socket.create_server((FLAGS.host, FLAGS.port))
        except OSError as e:
            raise ValueError(f"cannot listen on {FLAGS.host}:{FLAGS.port} ({e.strerror or e}); "
                             "pass another --port (or stop what holds it)") from None
        policy = inference.RunPolicy.from_workdir(
            FLAGS.workdir, FLAGS.step, FLAGS.params, levers=console.lever_flags(),
            client_executes=FLAGS.protocol != "b1k",
            keys=inference.ObservationKeys.parse(FLAGS.keys))
        server = PolicyServer(policy, FLAGS.host, FLAGS.port, sock=sock,
                              max_message_bytes=FLAGS.max_message_mb << 20,
                              protocol=FLAGS.protocol, seed=FLAGS.seed, prompt=FLAGS.prompt)
    except ValueError as e:
        raise SystemExit(f"pi0_armfix.serve: {e}") from None
    levers = policy.sampling.tag(closed_loop=True)  # every lever off its default, the run's own too
    meta = policy.metadata()
    print(f"serving step {meta['step']} of {FLAGS.workdir} ({meta['model']}, H = "
          f"{meta['action_horizon']}) on ws://{FLAGS.host}:{FLAGS.port}; observation keys "
          f"{meta['observation_keys']}"
          + (f"; levers {levers}" if levers else ""), flush=True)
    asyncio.run(server.serve())


def cli() -> None:
    """`python -m pi0_armfix.serve`."""
    flags.DEFINE_string("workdir", None, "run folder (holds checkpoints/)", required=True)
    flags.DEFINE_integer("step", None, "checkpoint step (default: the latest)")
    flags.DEFINE_enum("params", "ema", ["ema", "params"],
                      "the EMA params (when the run kept them) or the raw params")
    flags.DEFINE_string("host", "0.0.0.0", "interface to listen on")
    flags.DEFINE_integer("port", 8000, "port to listen on")
    console.define_lever_flags()
    flags.DEFINE_string("keys", "", "observation key mapping key=role,... (role: a batch camera "
                        "base_0_rgb / left_wrist_0_rgb / right_wrist_0_rgb, 'state', 'prompt' or "
                        "'previous_action'); '' = B1K's openpi keys")
    flags.DEFINE_enum("protocol", "openpi", PROTOCOLS, "openpi: a chunk per request "
                      "({'actions': [H, A]}); b1k: BEHAVIOR-1K's evaluation harness (one action "
                      "per request from a server-side queue, resets, its keys; "
                      "pi0_armfix/serving/harness.py)")
    flags.DEFINE_integer("seed", 0, "b1k: noise seed of the first episode (episode e: seed + e)")
    flags.DEFINE_string("prompt", "", "b1k: the prompt of every task ('' = the run's prompt of "
                        "the request's task_id)")
    flags.DEFINE_integer("max_message_mb", MAX_MESSAGE_MB, "largest request accepted, MiB (a "
                         "larger one closes that client's connection; the server keeps serving)")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.serve"))


if __name__ == "__main__":
    cli()
