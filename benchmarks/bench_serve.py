"""A policy server against models in process: forwards per second for N processes each with its own model, and for
N clients of one `PolicyServer`; the server's forwards by batch size; a request's overhead over an in-process
forward (one client, so no batching: msgpack, the websocket round trip and the batcher's hop to the model thread).

    python benchmarks/bench_serve.py [--model hybrid] [--clients 1 2 4] [--seconds 15]

The clients only ask (no simulator between requests), the load under which batching helps most. Prints, asserts
nothing. In-process workers run with one torch thread each, as rollout workers do; the server with --threads (1).
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import threading
import time

import numpy as np

INSTRUCTION = "pick up the black bowl between the plate and the ramekin and place it on the plate"


def observation(cameras, size: int) -> dict:
    rng = np.random.default_rng(0)
    return {"images": {c: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for c in cameras},
            "state": rng.normal(size=8).astype(np.float32), "instruction": INSTRUCTION}


def in_process(model: str, seconds: float, queue) -> None:
    import torch

    from vlactl.models.base import PolicyInput
    from vlactl.models.registry import load_policy

    torch.set_num_threads(1)
    vla = load_policy(model).eval()
    obs = observation(vla.cameras, vla.image_size or 128)
    batch = PolicyInput({k: v[None] for k, v in obs["images"].items()}, obs["state"][None], [obs["instruction"]])
    with torch.inference_mode():
        vla.predict_action_chunk(batch)  # warm-up
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            vla.predict_action_chunk(batch)
            n += 1
    queue.put((n, time.perf_counter() - start, 0.0, 0.0))


def client(url: str, seconds: float, queue) -> None:
    from vlactl.serve.client import Connection

    connection = Connection(url)
    meta = connection.metadata
    obs = observation(meta["cameras"], 128 if meta["needs_images"] else 0)
    connection.request({"obs": obs, "reset": True})  # warm-up
    n, start, infer, total = 0, time.perf_counter(), 0.0, 0.0
    while time.perf_counter() - start < seconds:
        timing = connection.request({"obs": obs, "reset": False})["server_timing"]
        infer, total, n = infer + timing["infer_ms"], total + timing["total_ms"], n + 1
    queue.put((n, time.perf_counter() - start, infer / n, total / n))
    connection.close()


def run_all(target, args_list) -> tuple[float, float, float, float]:
    """Start one process per argument tuple: forwards per second over all; mean seconds per forward of one; for
    clients, the server's mean forward and frame-in-to-reply-out milliseconds per request."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    processes = [ctx.Process(target=target, args=(*args, queue)) for args in args_list]
    for p in processes:
        p.start()
    results = [queue.get(timeout=3600) for _ in processes]  # start-up (torch, the model) is slow on a loaded CPU
    for p in processes:
        p.join(60)
    rate = sum(r[0] / r[1] for r in results)
    return rate, *(float(np.mean(column)) for column in zip(*[(s / n, i, t) for n, s, i, t in results]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="hybrid", help="registry name or checkpoint path (default: hybrid)")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--max-batch-size", type=int, default=8)
    parser.add_argument("--max-wait-s", type=float, default=0.005)
    parser.add_argument("--threads", type=int, default=1, help="the server's torch threads (0: torch's default)")
    args = parser.parse_args()
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)

    from vlactl.models.registry import load_policy
    from vlactl.serve.server import PolicyServer

    server = PolicyServer(load_policy(args.model), args.model, args.max_batch_size, args.max_wait_s)
    ready, loop = threading.Event(), asyncio.new_event_loop()
    holder = {}

    def listening(port: int) -> None:
        holder["url"] = f"ws://127.0.0.1:{port}"
        ready.set()

    async def serve() -> None:
        holder["stop"] = asyncio.Event()
        await server.serve("127.0.0.1", 0, listening, holder["stop"])

    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    thread.start()
    ready.wait(60)
    print(f"model {args.model}, {args.seconds:.0f} s per run, server max_batch_size {args.max_batch_size}, "
          f"max_wait_s {args.max_wait_s}, torch threads {args.threads or 'default'}")
    print(f"{'N':>3} {'in-process fwd/s':>17} {'served fwd/s':>13} {'ratio':>6}  server forwards by batch size")
    for n in args.clients:
        local, local_s, _, _ = run_all(in_process, [(args.model, args.seconds)] * n)
        before = server.batch_sizes.copy()
        served, served_s, infer_ms, total_ms = run_all(client, [(holder["url"], args.seconds)] * n)
        sizes = server.batch_sizes - before
        shown = ", ".join(f"{size}: {count}" for size, count in sorted(sizes.items()))
        print(f"{n:>3} {local:>17.1f} {served:>13.1f} {served / local:>6.2f}  {shown}")
        if n == 1:  # printed at once: a later N may take long
            print(f"one client: {1000 * served_s:.2f} ms a request against {1000 * local_s:.2f} ms a forward in "
                  f"process: overhead {1000 * (served_s - local_s):+.2f} ms (in the server {total_ms:.2f} ms, its "
                  f"forward {infer_ms:.2f} ms; the rest is msgpack and the socket both ways)")
    loop.call_soon_threadsafe(holder["stop"].set)
    thread.join(30)


if __name__ == "__main__":
    main()
