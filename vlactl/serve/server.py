"""`vlactl serve`: load a model once and answer many rollout workers over a websocket.

Requests that arrive together are batched into one forward: the batcher takes the first request waiting, then
gathers more for at most `max_wait_s`, up to `max_batch_size`, and stops early once every connected client has a
request in (none of them can send another before its reply). Each connection keeps its own noise stream
(`VLA.predict_rows`), so a batched row gets the actions it would get predicted alone. Steered connections run in a
`ConstrainedAgent` of their own, one request at a time (the steering hooks are on the shared model while it runs).
The forward runs in the event loop itself, as openpi's server runs it: a hand-off to a model thread cost ~10 ms a
request on a loaded CPU (benchmarks/bench_serve.py), and frames that come in meanwhile wait in the socket and join
the next batch. One bad message closes its own connection with a one-line error, never the server.
"""

from __future__ import annotations

import asyncio
import collections
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from vlactl.errors import UsageError
from vlactl.serve import protocol
from vlactl.serve.wire import packb, unpackb


@dataclass
class Session:
    """One client connection: its noise stream and, when it steers, its own agent."""

    noise: object = None  # the VLA's sampling state for this connection's episode
    agent: object = None  # ConstrainedAgent, for a steered connection


@dataclass
class Pending:
    session: Session
    obs: dict
    reset: bool
    seed: int | None  # the episode's, when `reset` starts one
    reply: asyncio.Future
    arrived: float  # perf_counter when its frame came in


class PolicyServer:
    def __init__(self, vla, model: str, max_batch_size: int = 8, max_wait_s: float = 0.005):
        if max_batch_size < 1 or max_wait_s < 0:
            raise UsageError(f"max_batch_size must be >= 1 and max_wait_s >= 0, got {max_batch_size}, {max_wait_s}")
        self.vla = vla.eval()
        self.metadata = protocol.metadata(vla, model)
        self.max_batch_size, self.max_wait_s = int(max_batch_size), float(max_wait_s)
        self.batch_sizes: collections.Counter = collections.Counter()  # forwards per batch size, for the benchmark
        self._queue: asyncio.Queue | None = None
        self._sessions = 0

    # --- connections --------------------------------------------------------------------------------------
    async def handle(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        self._sessions += 1
        session = Session()
        try:
            await self._converse(ws, session)
        except ConnectionClosed:  # the client went away (its rollout ended or was killed): nothing to answer
            pass
        finally:
            self._sessions -= 1

    async def _converse(self, ws, session: Session) -> None:
        """Metadata first, then one reply per request; a bad request ends the connection in one line."""
        await ws.send(packb(self.metadata))
        async for message in ws:
            received = time.perf_counter()
            try:
                request = unpackb(message) if isinstance(message, bytes) else None
                if not isinstance(request, dict):
                    raise protocol.BadRequest("a request must be a msgpack map in a binary frame")
                if "steer" in request:
                    self._steer(session, request["steer"])
                    await ws.send(packb({"steered": True}))
                    continue
                obs = protocol.observation(request, self.vla.cameras, self.vla.needs_images)
                seed = protocol.episode_seed(request)
                if session.agent is not None and obs["robot_state"] is None:
                    raise protocol.BadRequest("a steered request needs obs.robot_state (the SPEC.md §2 state)")
            except Exception as exc:  # noqa: BLE001 - whatever a client sends, it gets one line, the server lives on
                why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                await ws.send(f"{'refused' if isinstance(exc, UsageError) else 'bad request'}: {why}")
                await ws.close()
                return
            pending = Pending(session, obs, bool(request.get("reset", False)), seed,
                              asyncio.get_running_loop().create_future(), received)
            await self._queue.put(pending)
            reply = await pending.reply
            if isinstance(reply, str):
                await ws.send(reply)
                await ws.close()
                return
            reply["server_timing"]["total_ms"] = 1000 * (time.perf_counter() - received)  # frame in to reply out
            await ws.send(packb(reply))

    def _steer(self, session: Session, message) -> None:
        from vlactl.rollout.constrained import ConstrainedAgent

        constraint, steering, replan_every, snap = protocol.decode_steer(message if isinstance(message, dict) else {})
        for probe in steering.probes + steering.holds:  # probes of another model or layer width read nothing
            if probe.layer not in self.metadata["layer_widths"] and probe.layer not in self.vla.layer_names():
                raise UsageError(f"probe {probe.feature}@{probe.layer}: {self.vla.name} has no layer {probe.layer!r}")
            probe.check_fits(self.vla.name, self.metadata["layer_widths"].get(probe.layer))
        session.agent = ConstrainedAgent(self.vla, constraint, steering, replan_every, snap)

    # --- batching ------------------------------------------------------------------------------------------
    async def batcher(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            batch = [await self._queue.get()]
            deadline = loop.time() + self.max_wait_s
            while len(batch) < min(self.max_batch_size, self._sessions):
                try:
                    batch.append(await asyncio.wait_for(self._queue.get(), max(0.0, deadline - loop.time())))
                except asyncio.TimeoutError:
                    break
            steered = [p for p in batch if p.session.agent is not None]
            plain = [p for p in batch if p.session.agent is None]
            groups = collections.defaultdict(list)  # rows of one forward must have images of one size
            for p in plain:
                groups[tuple((k, v.shape) for k, v in p.obs["images"].items())].append(p)
            for group in groups.values():
                self._answer(group, self._forward)
            for p in steered:
                self._answer([p], self._step)

    def _answer(self, group: list[Pending], fn) -> None:
        try:
            replies = fn(group)
        except Exception as exc:  # noqa: BLE001 - a failing forward ends its own requests, not the server
            if len(group) > 1:  # one bad row must not fail the others: each alone
                for p in group:
                    self._answer([p], fn)
                return
            replies = [f"error: the model failed on this request ({type(exc).__name__}: {exc})".splitlines()[0]]
        for p, reply in zip(group, replies):
            if not p.reply.done():
                p.reply.set_result(reply)

    def _forward(self, group: list[Pending]) -> list[dict]:
        """One forward for the group's rows, each drawing from its own connection's noise stream."""
        import torch

        from vlactl.models.base import PolicyInput

        start = time.perf_counter()
        for p in group:
            if p.reset or p.session.noise is None:  # an episode starts: its noise restarts as in process
                self.vla.reset(p.seed)
                p.session.noise = self.vla.sampling_state()
        obs = [p.obs for p in group]
        batch = PolicyInput(images={k: np.stack([o["images"][k] for o in obs]) for k in obs[0]["images"]},
                            state=np.stack([o["state"] for o in obs]), instruction=[o["instruction"] for o in obs])
        with torch.inference_mode():
            chunk, states = self.vla.predict_rows(batch, [p.session.noise for p in group])
        chunk = chunk.float().cpu().numpy()
        infer_ms = 1000 * (time.perf_counter() - start)
        self.batch_sizes[len(group)] += 1
        replies = []
        for i, p in enumerate(group):
            p.session.noise = states[i]
            replies.append({"actions": chunk[i], "server_timing": {
                "infer_ms": infer_ms, "queue_ms": 1000 * (start - p.arrived), "batch_size": len(group)}})
        return replies

    def _step(self, group: list[Pending]) -> list[dict]:
        """A steered connection's step: its agent acts on its own noise stream, its reading of this step comes back."""
        p = group[0]
        agent, obs = p.session.agent, p.obs
        seen = SimpleNamespace(images=obs["images"], libero_state=obs["state"], state=obs["robot_state"])
        if p.reset or p.session.noise is None:
            agent.reset(SimpleNamespace(instruction=obs["instruction"]), seen, p.seed)  # the episode's boxes
            p.session.noise = self.vla.sampling_state()
        self.vla.set_sampling_state(p.session.noise)
        t = agent._t
        action = agent.act(seen)
        p.session.noise = self.vla.sampling_state()
        self.batch_sizes[1] += 1
        return [{"actions": np.asarray(action, dtype=np.float32)[None], "reading": agent.readings.get(t),
                 "server_timing": {"batch_size": 1}}]

    # --- running -------------------------------------------------------------------------------------------
    async def serve(self, host: str, port: int, ready=None, stop: asyncio.Event | None = None) -> None:
        """Serve until `stop` is set (forever without one); `ready(port)` is called once listening."""
        from websockets.asyncio.server import serve

        self._queue = asyncio.Queue()
        batcher = asyncio.create_task(self.batcher())
        # no compression and no frame limit: frames are images and arrays (openpi's server does the same)
        async with serve(self.handle, host, port, compression=None, max_size=None) as server:
            bound = server.sockets[0].getsockname()[1]
            if ready is not None:
                ready(bound)
            await (stop.wait() if stop is not None else asyncio.Future())
        batcher.cancel()


def run_serve(cfg) -> None:
    """`vlactl serve model=<name or checkpoint> [model options] host=... port=...`."""
    import torch

    from vlactl.models.registry import policy_loader

    if cfg.threads is not None:
        torch.set_num_threads(int(cfg.threads))
    vla = policy_loader(cfg)(str(cfg.model))
    server = PolicyServer(vla, str(cfg.model), int(cfg.max_batch_size), float(cfg.max_wait_s))
    meta = server.metadata

    def ready(port: int) -> None:
        print(f"serving {meta['model']} ({meta['name']}, chunk {meta['chunk_size']}) on ws://{cfg.host}:{port}; "
              f"rollout with policy=ws://{cfg.host}:{port}", flush=True)

    try:
        asyncio.run(server.serve(str(cfg.host), int(cfg.port), ready))
    except KeyboardInterrupt:
        sizes = ", ".join(f"{size}: {n}" for size, n in sorted(server.batch_sizes.items())) or "none"
        print(f"stopped; forwards by batch size: {sizes}")
    except OSError as exc:  # the port is taken, or the host is not this machine's
        raise UsageError(f"cannot listen on {cfg.host}:{cfg.port} ({exc.strerror or exc})") from None
