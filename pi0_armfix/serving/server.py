"""The policy server: a policy behind openpi's websocket protocol or B1K's harness (`PolicyServer`),
its msgpack encoding of numpy arrays (`pack` / `unpack`, openpi's), and the checks that turn a
request the policy cannot read into one text reply (the entry point: `pi0_armfix.serve`)."""

from __future__ import annotations

import asyncio
import functools
import http
import math
import socket
import threading
import time
import traceback
from typing import Any

import msgpack
import numpy as np
from websockets import exceptions as websockets_exceptions
from websockets.asyncio import server as ws_server

from pi0_armfix.policies import execution
from pi0_armfix.policies.sampling import Sampling
from pi0_armfix.serving import harness


def _pack_array(obj: Any) -> Any:
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind in ("V", "O", "c"):
        raise ValueError(f"unsupported dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str,
                b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


# What a request may carry: numbers and booleans (and byte/unicode strings). Never objects: an
# object array built from network bytes is a table of pointers (a crash, or worse).
ACCEPTED_KINDS = "biufSU"


class MalformedArray(ValueError):
    """An array of a request that is not what it claims to be (or not allowed)."""


def _request_dtype(text: Any) -> np.dtype:
    try:
        dtype = np.dtype(text.decode() if isinstance(text, bytes) else text)
    except (TypeError, ValueError) as e:
        raise MalformedArray(f"an array's dtype {text!r} is not a numpy dtype ({e})") from None
    if dtype.kind not in ACCEPTED_KINDS or dtype.fields is not None:
        raise MalformedArray(f"an array's dtype {dtype.str!r} is not accepted (numbers, booleans and "
                         "strings only)")
    return dtype


def _unpack_array(obj: dict) -> Any:
    if b"__ndarray__" in obj:
        dtype = _request_dtype(obj.get(b"dtype"))
        shape, data = obj.get(b"shape"), obj.get(b"data")
        if (not isinstance(shape, (list, tuple)) or not all(
                isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
                or not isinstance(data, bytes)):
            raise MalformedArray(f"an array's shape {shape!r} or data is malformed")
        if math.prod(shape) * dtype.itemsize != len(data):
            raise MalformedArray(f"an array of shape {tuple(shape)} and dtype {dtype.str} needs "
                             f"{math.prod(shape) * dtype.itemsize} bytes, the request holds "
                             f"{len(data)}")
        return np.frombuffer(data, dtype=dtype).reshape(shape)
    if b"__npgeneric__" in obj:
        dtype = _request_dtype(obj.get(b"dtype"))
        try:
            return dtype.type(obj.get(b"data"))
        except (TypeError, ValueError, OverflowError) as e:
            raise MalformedArray(f"a scalar of dtype {dtype.str} is malformed ({e})") from None
    return obj


MAX_MESSAGE_MB = 64  # three 720p RGBA images and a state are ~11 MiB
# openpi's request/reply; B1K's evaluation harness (serving/harness.py)
PROTOCOLS = ("openpi", "b1k")
pack = functools.partial(msgpack.packb, default=_pack_array)
unpack = functools.partial(msgpack.unpackb, object_hook=_unpack_array)


# ---------------------------------------------------------------------- the server

class PolicyServer:
    """Serves `policy` (a `RunPolicy`, or anything with `infer([obs]) -> [1, H, A]`,
    `metadata()`, `sampling`, `layout` and `horizon`) to websocket clients, one request at a
    time, with the policy's execution levers (`policies.execution`): an openpi client's chunks
    pass the per-chunk rules (`ChunkRules`, one stream per client), a B1K harness connection
    gets its own `Replanner` (`harness.HarnessSession`).

    Raises:
      ValueError naming the lever, for one the protocol cannot apply (rtc or temporal ensembling
      for an openpi client, which executes the chunks itself) or out of its range.
    """

    def __init__(self, policy: Any, host: str = "0.0.0.0", port: int = 8000, *,
                 sock: socket.socket | None = None,
                 max_message_bytes: int = MAX_MESSAGE_MB << 20, protocol: str = "openpi",
                 seed: int = 0, prompt: str = ""):
        if protocol not in PROTOCOLS:
            raise ValueError(f"--protocol={protocol!r}: choose one of {PROTOCOLS}")
        sampling = getattr(policy, "sampling", None) or Sampling()
        if protocol != "b1k" and (sampling.rtc or sampling.temporal_ensemble):
            raise ValueError("rtc and temporal_ensemble (the run's eval section or the flags) "
                             "need --protocol=b1k: an openpi client executes the chunks itself; "
                             "set them off (--nortc --temporal_ensemble=0)")
        self.policy, self.host, self.port = policy, host, port
        self.rules = execution.ChunkRules(policy, sampling)
        if protocol == "b1k":
            execution.Replanner(policy, sampling)  # its levers checked before any client
        self.sock, self.max_message_bytes = sock, max_message_bytes
        self.protocol, self.seed, self.prompt = protocol, seed, prompt
        self.sessions: dict[Any, harness.HarnessSession] = {}
        self._executed: dict[Any, np.ndarray] = {}  # per openpi client: its last executed action
        self.warm = threading.Event()  # /healthz answers 200 once set (the sampler compiled)
        self._metadata = pack(policy.metadata())

    def session(self, client: Any) -> harness.HarnessSession:
        """The harness session of `client` (`--protocol=b1k`), made on its first message."""
        if client not in self.sessions:
            self.sessions[client] = harness.HarnessSession(self.policy, self.seed, self.prompt)
        return self.sessions[client]

    def answer(self, message: bytes | str, client: Any = None) -> bytes | str | None:
        """One request of `client` -> the packed reply, the error text, or None where the
        protocol sends none (B1K's reset). Never raises."""
        try:
            if isinstance(message, str):
                raise ValueError("requests are binary msgpack messages, got a text message")
            try:
                observation = unpack(message)
            except MalformedArray as e:
                raise ValueError(f"the request is malformed: {e}") from None
            except Exception as e:  # msgpack raises several types for garbage
                raise ValueError(f"the request is not msgpack ({type(e).__name__}: {e})") from e
            if not isinstance(observation, dict):
                raise ValueError(f"the request must be an observation dict, got "
                                 f"{type(observation).__name__}")
            if self.protocol == "b1k":
                start = time.monotonic()
                reply = self.session(client).answer(observation)
                if reply is None:
                    return None
                return pack({**reply, "server_timing": {
                    "infer_ms": 1000 * (time.monotonic() - start)}})
            start = time.monotonic()
            kwargs, relative_to = self._previous(client, observation)
            actions = self.rules(client, self.policy.infer([observation], **kwargs)[0])
            reply = {"actions": actions,
                     "server_timing": {"infer_ms": 1000 * (time.monotonic() - start)}}
            if relative_to:
                self._executed[client] = actions[min(self.rules.executed or len(actions),
                                                     len(actions)) - 1]
                reply["relative_to"] = relative_to
            return pack(reply)
        except ValueError as e:
            return f"pi0_armfix.serve: {e}"
        except Exception:  # a bug of ours: report it, keep serving
            return f"pi0_armfix.serve: internal error\n{traceback.format_exc()}"

    def _previous(self, client: Any, observation: dict) -> tuple[dict[str, Any], str]:
        """For a policy relative to the previous command: `infer`'s `previous` and what the
        chunk is relative to, which the reply names (`relative_to`): the client's
        `previous_action`; else the action of this server's last reply to the client that the
        client executed last (`ChunkRules.executed`, the `--n_exec`-th: 'executed'); else, on a
        connection's first request, the episode's start, as training had it ('start':
        `stats.start_reference`). ({}, '') for any other policy."""
        if not getattr(self.policy, "needs_previous_action", False):
            return {}, ""
        if observation.get(self.policy.keys.previous_action) is not None:
            return {}, "previous_action"
        executed = self._executed.get(client)
        if executed is None:
            return {}, "start"
        return {"previous": executed[None]}, "executed"

    async def _handle(self, websocket) -> None:
        try:
            await websocket.send(self._metadata)
            # A request sent while the sampler compiles waits for it: the warm-up's draw and a
            # client's never interleave.
            await self._warmed.wait()
            async for message in websocket:
                reply = self.answer(message, client=websocket.id)
                if reply is not None:
                    await websocket.send(reply)
        except websockets_exceptions.ConnectionClosed:
            pass  # the client left (or sent more than --max_message_mb): nothing to answer
        finally:
            self.rules.forget(websocket.id)
            self.sessions.pop(websocket.id, None)
            self._executed.pop(websocket.id, None)

    def _health(self, connection, request):
        if request.path == "/healthz":
            if self.warm.is_set():
                return connection.respond(http.HTTPStatus.OK, "OK\n")
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, "compiling\n")
        return None

    async def serve(self, ready: asyncio.Event | None = None) -> None:
        """Serves until cancelled; sets `ready` once listening (and `self.port` to the bound
        port, for port 0)."""
        where = ({"sock": self.sock} if self.sock is not None
                 else {"host": self.host, "port": self.port})
        self._warmed = asyncio.Event()
        async with ws_server.serve(self._handle, compression=None,
                                   max_size=self.max_message_bytes,
                                   process_request=self._health, **where) as server:
            self.port = server.sockets[0].getsockname()[1]
            if ready is not None:
                ready.set()
            warm_up = getattr(self.policy, "warm_up", None)
            if warm_up is not None:  # compiled before /healthz says the server is ready
                sizes = harness.IMAGE_SIZES if self.protocol == "b1k" else ()
                await asyncio.to_thread(warm_up, *([sizes] if sizes else []))
            self.warm.set()
            self._warmed.set()
            await server.serve_forever()
