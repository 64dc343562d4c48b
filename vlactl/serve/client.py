"""The client side: `RemoteAgent`, a `VLAAgent` whose model runs in a `vlactl serve` process, so the episode loop
and the worker do not change. Every failure to reach or understand the server is a one-line `ServerError` (a
UsageError): the episode in flight raises before anything of it is written, and re-running the same command
resumes with it.
"""

from __future__ import annotations

import time

import numpy as np

from vlactl.errors import UsageError
from vlactl.rollout.agents import VLAAgent
from vlactl.serve.wire import packb, unpackb

CONNECT_S = 30.0  # how long a client keeps retrying a server that is not (yet) listening, or busy in a forward
REPLY_S = 300.0  # a reply slower than this means the server is stuck (a first CUDA forward takes seconds)
RESUME = "the episodes in flight were not written; re-run the same command to resume"


class ServerError(UsageError):
    """The policy server is down, dropped the connection, refused the client, or sent something unreadable."""


def is_url(policy) -> bool:
    return isinstance(policy, str) and policy.startswith(("ws://", "wss://"))


class Connection:
    """A synchronous websocket to the server: metadata on connect, then one reply per request."""

    def __init__(self, url: str, connect_s: float = CONNECT_S, reply_s: float = REPLY_S):
        from websockets.sync.client import connect

        self.url, self.reply_s = url, reply_s
        deadline = time.monotonic() + connect_s
        while True:
            try:
                # entered as a context manager: websockets >= 17.1 warns when a connection is opened otherwise
                self._ws = connect(url, compression=None, max_size=None, open_timeout=connect_s).__enter__()
                break
            except (OSError, TimeoutError) as exc:
                if time.monotonic() >= deadline:
                    raise ServerError(f"no policy server at {url} ({exc}); start one with `vlactl serve model=...`")
                time.sleep(0.2)
            except Exception as exc:  # noqa: BLE001 - a handshake refused by whatever listens there
                raise ServerError(f"{url} is not a policy server ({type(exc).__name__}: {exc})") from None
        self.metadata = self._receive()

    def request(self, message: dict) -> dict:
        from websockets.exceptions import WebSocketException

        try:
            self._ws.send(packb(message))
        except (OSError, WebSocketException) as exc:
            raise ServerError(f"policy server {self.url} dropped the connection ({exc}); {RESUME}") from None
        return self._receive()

    def _receive(self) -> dict:
        from websockets.exceptions import ConnectionClosed, WebSocketException

        try:
            frame = self._ws.recv(timeout=self.reply_s)
        except TimeoutError:
            raise ServerError(f"policy server {self.url} sent no reply in {self.reply_s:.0f} s; {RESUME}") from None
        except ConnectionClosed as exc:
            raise ServerError(f"policy server {self.url} closed the connection ({exc}); {RESUME}") from None
        except (OSError, WebSocketException) as exc:
            raise ServerError(f"policy server {self.url} dropped the connection ({exc}); {RESUME}") from None
        if isinstance(frame, str):  # the server's one-line error
            raise ServerError(f"policy server {self.url}: {frame.splitlines()[0] if frame else 'error'}")
        try:
            reply = unpackb(frame)
        except Exception as exc:  # noqa: BLE001 - any decoding failure is one unreadable frame
            raise ServerError(f"policy server {self.url} sent an unreadable frame ({exc}); {RESUME}") from None
        if not isinstance(reply, dict):
            raise ServerError(f"policy server {self.url} sent {type(reply).__name__}, not a map; {RESUME}")
        return reply

    def close(self) -> None:
        self._ws.close()

    def __del__(self) -> None:  # a worker's agent lives until its process ends: say goodbye to the server
        if hasattr(self, "_ws"):
            self._ws.close()


class RemoteAgent(VLAAgent):
    """`VLAAgent` over a connection: the server predicts the chunk, this side keeps the queue and snaps the
    gripper. With `steer` (`protocol.encode_steer`), the server runs the episode's `ConstrainedAgent` step by step
    and sends each step's probe readings back (`readings`, as the in-process agent keeps them)."""

    def __init__(self, url: str, replan_every: int | None = None, snap_gripper: bool = True, steer: dict | None = None,
                 connection: Connection | None = None):
        self.connection = connection or Connection(url)
        meta = self.metadata = self.connection.metadata
        try:
            served = SimpleVLA(meta)
        except (KeyError, TypeError) as exc:
            raise ServerError(f"{url} sent no policy metadata ({exc}); is it a `vlactl serve`?") from None
        super().__init__(served, replan_every, snap_gripper)
        self.steered = steer is not None
        if self.steered:
            self.connection.request({"steer": steer})
        self.readings: dict[int, dict] = {}
        self._start, self._seed, self._t = False, None, 0

    def reset(self, env, obs, seed: int | None = None) -> None:
        self._queue, self._instruction, self._start, self._seed = [], env.instruction, True, seed
        self.readings, self._t = {}, 0

    def act(self, obs) -> np.ndarray:
        if not self.steered:
            return super().act(obs)
        t, self._t = self._t, self._t + 1
        reply = self._request(obs)
        if reply.get("reading") is not None:
            self.readings[t] = reply["reading"]
        return np.array(reply["actions"][0], dtype=np.float64)

    def predict(self, obs) -> np.ndarray:
        chunk = np.array(self._request(obs)["actions"], dtype=np.float32)  # writable: snap edits it
        return chunk[: self.replan_every]

    def _request(self, obs) -> dict:
        message = {"images": obs.images if self.needs_images else {}, "instruction": self._instruction,
                   "state": np.asarray(obs.libero_state, dtype=np.float32)}
        if self.steered:
            message["robot_state"] = np.asarray(obs.state, dtype=np.float64)
        request = {"obs": message, "reset": self._start}
        if self._start and self._seed is not None:
            request["seed"] = int(self._seed)
        reply = self.connection.request(request)
        self._start = False
        if not isinstance(reply.get("actions"), np.ndarray):
            raise ServerError(f"policy server {self.connection.url} replied without actions; {RESUME}")
        return reply


class SimpleVLA:
    """What `VLAAgent` reads of a model, from the server's metadata."""

    def __init__(self, meta: dict):
        self.name, self.chunk_size, self.replan_every = meta["name"], meta["chunk_size"], meta["replan_every"]
        self.needs_images, self.gripper_levels = meta["needs_images"], meta["gripper_levels"]
        self.widths, self.env_preset = meta["layer_widths"], meta.get("env_preset")  # the preset: render warnings

    def eval(self) -> "SimpleVLA":
        return self

    def layer_width(self, layer: str) -> int:
        if layer not in self.widths:
            raise UsageError(f"the served {self.name} has no layer {layer!r}")
        return self.widths[layer]


def served_agent(cfg) -> RemoteAgent:
    """The rollout's agent when `policy=ws://...`: the server must serve the run's `model` (the run folder, its
    resume checks and the default probes are named by it)."""
    from vlactl.rollout.agents import SCRIPTED

    if not is_url(cfg.policy):
        raise UsageError(f"policy must be a policy server's ws://HOST:PORT (from `vlactl serve`), got {cfg.policy!r}")
    if str(cfg.model) == SCRIPTED:
        raise UsageError("the scripted expert runs in the simulator's process; drop policy=... with model=scripted")
    agent = RemoteAgent(str(cfg.policy), cfg.replan_every, bool(cfg.snap_gripper))
    if agent.metadata["model"] != str(cfg.model):
        raise UsageError(f"the server at {cfg.policy} serves {agent.metadata['model']!r}, not model={cfg.model!r}; "
                         f"give model={agent.metadata['model']}")
    return agent
