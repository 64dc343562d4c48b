"""`vlactl serve` and `rollout policy=ws://...`, on 127.0.0.1 only: a served model acts as the same model in process
(per connection noise streams, batched or not), a rollout through the server writes the in-process run's episodes,
and a server that is down, a bad message or probes of another model end in one line, never a traceback.

With the registry's tiny random hybrid; the servers run in a thread and stop themselves."""

import asyncio
import threading
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from test_constrained_rollout import probes  # noqa: F401 - the fixture: probes of the random model

from vlactl.models.registry import tiny_policy
from vlactl.rollout.agents import VLAAgent
from vlactl.serve.client import Connection, RemoteAgent, ServerError
from vlactl.serve.server import PolicyServer
from vlactl.serve.wire import packb, unpackb


class Served:
    """A PolicyServer on a free loopback port in a background thread, for the `with` block."""

    def __init__(self, vla, model="random", **options):
        self.server = PolicyServer(vla, model, **options)

    def __enter__(self):
        ready, self.loop = threading.Event(), asyncio.new_event_loop()

        def listening(port):
            self.url = f"ws://127.0.0.1:{port}"
            ready.set()

        async def main():
            self.stop = asyncio.Event()
            await self.server.serve("127.0.0.1", 0, listening, self.stop)

        self.thread = threading.Thread(target=self.loop.run_until_complete, args=(main(),), daemon=True)
        self.thread.start()
        assert ready.wait(30), "the server did not start"
        return self

    def __exit__(self, *exc):
        self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(30)


def _episode(seed: int, steps: int = 5):
    """A fake episode: its env (the instruction) and observations, as the env worker would see them."""
    rng = np.random.default_rng(seed)
    env = SimpleNamespace(instruction="pick up the black bowl on the stove and place it on the plate")
    obs = [SimpleNamespace(images={c: rng.integers(0, 255, (128, 128, 3), dtype=np.uint8) for c in ("image", "wrist_image")},
                           libero_state=rng.normal(size=8).astype(np.float32), state=rng.normal(size=7))
           for _ in range(steps)]
    return env, obs


def _actions(agent, env, obs, seed=None):
    agent.reset(env, obs[0], seed)
    return np.stack([agent.act(o) for o in obs])


@pytest.fixture(scope="module")
def served():
    with Served(tiny_policy("hybrid"), max_batch_size=4, max_wait_s=0.05) as s:
        yield s


def test_served_actions_equal_in_process(served):
    """Two episodes in a row on one connection, and again: each starts its noise stream afresh, as in process."""
    local = VLAAgent(tiny_policy("hybrid"))
    remote = RemoteAgent(served.url)
    assert (remote.chunk_size, remote.replan_every, remote.needs_images) == (local.chunk_size, local.replan_every, True)
    for seed in (0, 1, 0):
        env, obs = _episode(seed)
        np.testing.assert_array_equal(_actions(remote, env, obs), _actions(local, env, obs))
    env, obs = _episode(0)
    for seed in (7, 8):  # an episode's own noise seed travels with its first request
        np.testing.assert_array_equal(_actions(remote, env, obs, seed), _actions(local, env, obs, seed))
    assert not np.array_equal(_actions(remote, env, obs, 7), _actions(remote, env, obs, 8))


def test_batched_rows_equal_alone(served):
    """Three clients at once share forwards (batch sizes > 1), and each still gets its in-process actions: its own
    noise, to float rounding (a batched matrix product may round otherwise than one of a single row)."""
    episodes = [_episode(seed, steps=6) for seed in (3, 4, 5)]
    expected = [_actions(VLAAgent(tiny_policy("hybrid")), *e) for e in episodes]
    agents = [RemoteAgent(served.url) for _ in episodes]
    got, before = [None] * 3, sum(n for size, n in served.server.batch_sizes.items() if size > 1)
    threads = [threading.Thread(target=lambda i=i: got.__setitem__(i, _actions(agents[i], *episodes[i])))
               for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    for g, e in zip(got, expected):
        np.testing.assert_allclose(g, e, rtol=0, atol=1e-5)
    assert sum(n for size, n in served.server.batch_sizes.items() if size > 1) > before


def test_bad_message_is_one_line_and_the_server_lives_on(served):
    from websockets.sync.client import connect

    with connect(served.url) as ws:
        assert unpackb(ws.recv(timeout=10))["name"] == "hybrid"  # the metadata, first
        ws.send(packb({"obs": {"state": np.zeros(3, np.float32), "instruction": "x"}}))
        reply = ws.recv(timeout=10)
    assert isinstance(reply, str) and reply.startswith("bad request: obs.state must be 8 floats") and "\n" not in reply
    connection = Connection(served.url)
    with pytest.raises(ServerError, match="bad request: a request needs 'obs'"):
        connection.request({"hello": 1})
    with pytest.raises(ServerError, match="bad request: seed must be an integer, got 'one'"):
        images = _episode(0)[1][0].images
        Connection(served.url).request({"obs": {"images": images, "state": np.zeros(8, np.float32),
                                                "instruction": "x"}, "reset": True, "seed": "one"})
    with connect(served.url) as ws:
        ws.recv(timeout=10)
        ws.send(b"\xc1 not msgpack")
        assert ws.recv(timeout=10).startswith("bad request: ")
    env, obs = _episode(0, steps=2)
    assert _actions(RemoteAgent(served.url), env, obs).shape == (2, 7)  # other clients are served as before


def test_an_openpi_style_request_is_answered(served):
    """openpi's LIBERO observation keys; its client sends no episode start, so the connection's stream goes on."""
    from websockets.sync.client import connect

    rng = np.random.default_rng(0)
    request = {"observation/image": rng.integers(0, 255, (128, 128, 3), dtype=np.uint8),
               "observation/wrist_image": rng.integers(0, 255, (128, 128, 3), dtype=np.uint8),
               "observation/state": np.zeros(8), "prompt": "pick up the black bowl"}
    with connect(served.url, compression=None, max_size=None) as ws:
        metadata = unpackb(ws.recv(timeout=10))
        ws.send(packb(request))
        reply = unpackb(ws.recv(timeout=30))
    assert reply["actions"].shape == (metadata["chunk_size"], 7) and reply["actions"].dtype == np.float32


def test_server_down_is_one_line():
    with pytest.raises(ServerError, match=r"^no policy server at ws://127.0.0.1:9 .*vlactl serve") as err:
        Connection("ws://127.0.0.1:9", connect_s=0.5)
    assert "\n" not in str(err.value)


def test_dropped_connection_is_one_line():
    with Served(tiny_policy("hybrid")) as s:
        agent = RemoteAgent(s.url)
    env, obs = _episode(0, steps=1)
    agent.reset(env, obs[0])
    with pytest.raises(ServerError, match="re-run the same command to resume"):
        agent.act(obs[0])


def test_rollout_through_the_server_equals_in_process(tmp_path):
    """`rollout policy=ws://...`: the same episodes, row for row and step for step, as the run with the model in
    the worker; a server serving another model than `model=` is refused in one line."""
    from vlactl.errors import UsageError
    from vlactl.rollout.runner import rollout_config, run_rollout

    base = ["model=random", "tasks=[0]", "episodes_per_task=2", "max_steps=4", "workers=1", f"output_root={tmp_path}"]
    run_rollout(rollout_config([*base, "run_name=local"]))
    with Served(tiny_policy("hybrid")) as s:
        run_rollout(rollout_config([*base, "run_name=served", f"policy={s.url}"]))
        with pytest.raises(UsageError, match="serves 'random', not model='hybrid'; give model=random"):
            run_rollout(rollout_config([*base[1:], "model=hybrid", "run_name=other", f"policy={s.url}"]))
    for table in ("episodes", "steps"):
        local, served = (pd.read_parquet(tmp_path / run / f"{table}.parquet") for run in ("local", "served"))
        pd.testing.assert_frame_equal(local.drop(columns="wall_s", errors="ignore"),
                                      served.drop(columns="wall_s", errors="ignore"))


@pytest.mark.parametrize("box, constraint", [("state", "gripper=open"), ("action", "gripper=open"),
                                             ("action", "[height=high,speed=low]")])
def test_steered_rollout_through_the_server_equals_in_process(probes, tmp_path, box, constraint):
    """Steering runs in the server, per connection: the same steps and the same probe readings come back (several
    constraints too)."""
    from vlactl.rollout.runner import rollout_config, run_rollout

    base = ["model=random", "tasks=[0]", "episodes_per_task=1", "max_steps=6", "workers=1", f"output_root={tmp_path}",
            f"constraint={constraint}", "window=4", "method=control", f"probes={probes}", f"box={box}",
            "metres_per_unit=0.012", "speed_threshold=0.02"]
    run_rollout(rollout_config([*base, "run_name=local"]))
    with Served(tiny_policy("hybrid")) as s:
        run_rollout(rollout_config([*base, "run_name=served", f"policy={s.url}"]))
    local, served = (pd.read_parquet(tmp_path / run / "steps.parquet") for run in ("local", "served"))
    assert local.filter(like="reading_after").notna().any().any()
    pd.testing.assert_frame_equal(local, served)


def test_probes_of_another_model_are_refused_by_the_server(probes):
    from vlactl.rollout.constrained import Steering
    from vlactl.serve.protocol import encode_steer
    from vlactl.steering.probe_file import load_probe

    probe = next(p for p in map(load_probe, sorted((probes / "probes").glob("*.safetensors")))
                 if p.layer == "backbone.0")
    steer = encode_steer("gripper=open", 4, Steering("control", (probe,)), None, True)
    with Served(tiny_policy("autoregressive")) as s:
        with pytest.raises(ServerError, match=r"refused: probe .* trained on model 'hybrid'.*this is 'autoregressive'"):
            RemoteAgent(s.url, steer=steer)


def test_serve_command_answers_and_a_rollout_without_it_fails_in_one_line(tmp_path):
    import subprocess
    import sys

    from test_cli import run

    server = subprocess.Popen([sys.executable, "-m", "vlactl.cli", "serve", "model=random", "port=0"],
                              stdout=subprocess.PIPE, text=True)
    try:
        line = server.stdout.readline()  # "serving random (hybrid, chunk 4) on ws://127.0.0.1:PORT; ..."
        assert line.startswith("serving random (hybrid, chunk 4) on ws://127.0.0.1:"), line
        url = line.split(" on ")[1].split(";")[0]
        env, obs = _episode(0, steps=3)
        np.testing.assert_array_equal(_actions(RemoteAgent(url), env, obs),
                                      _actions(VLAAgent(tiny_policy("hybrid")), env, obs))
    finally:
        server.terminate()
        server.wait(30)
    result = run("rollout", "model=random", "tasks=[0]", "episodes_per_task=1", f"output_root={tmp_path}",
                 f"policy={url}")
    assert result.returncode == 2
    assert result.stderr.strip().startswith(f"error: no policy server at {url}") and "\n" not in result.stderr.strip()
    assert not any(tmp_path.iterdir())  # nothing written
