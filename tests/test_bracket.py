"""The searches of the box=action controller: one reading shift's bracketing search, and the pausing stop's read-out
shifts on a model whose commands move in whole tokens."""

import numpy as np
import pytest
import torch

from vlactl.models.registry import tiny_policy
from vlactl.rollout.bracket import MAX_SHIFT, Bracket
from vlactl.rollout.constrained import STOP_SETTLED, STOP_STEPS, ConstrainedAgent, Steering
from vlactl.rollout.constraints import parse_constraint
from vlactl.steering.probes import REGRESSION, Probe

TOKEN = 2 / 255  # one bin of a 256-bin action token over [-1, 1]


def search(response, target=0.0, passes=8):
    bracket, misses = Bracket(0.0, response(0.0) - target), []
    for _ in range(passes):
        misses.append(response(bracket.shift) - target)
        if abs(misses[-1]) <= TOKEN or not bracket.update(misses[-1]):
            break
    return bracket, misses


@pytest.mark.parametrize("response", [
    lambda s: -0.8 + 0.37 * s,  # a read-out's own dimension, pushed where it is written
    lambda s: -0.8 + TOKEN * np.round(0.37 * s / TOKEN),  # ... decoded to a token
    lambda s: float(np.tanh(-0.8 + 30 * s)),  # an expert layer: saturates after a small shift
])
def test_the_search_brings_the_quantity_to_its_target(response):
    _, misses = search(response)
    assert abs(misses[-1]) <= TOKEN


def test_a_target_out_of_reach_ends_at_the_largest_shift():
    bracket, misses = search(lambda s: -0.8 + 0.5 * np.tanh(s), passes=50)
    assert bracket.shift == MAX_SHIFT and len(misses) < 50 and misses[-1] < 0


def tokens(start, gains, bins=TOKEN * 4):
    """A chunk of 5 steps whose dimensions each move with their own read-out alone, in coarse token jumps."""
    def push(vector):
        commands = start + np.asarray(vector) * gains
        return (bins * np.round(commands / bins)).ravel()
    return push


def test_the_stop_searches_each_read_out_where_a_token_model_writes_it():
    start = np.tile([0.62, -0.41, -0.75, 0.3], (5, 1)) + np.linspace(0, 0.1, 5)[:, None]
    push, origin, wanted = tokens(start, np.array([0.37, 0.46, 0.23, 0.14])), np.zeros(4), np.zeros(20)
    calls = []

    def counted(vector):
        calls.append(vector)
        return push(vector)

    def nearest():  # the pass the stop keeps: nearest a standstill
        return min(np.abs(push(v).reshape(5, 4).mean(0)).max() for v in calls)

    passes = ConstrainedAgent._stop_by_dimension(counted, origin, push(origin), wanted, 4)
    assert passes == len(calls) <= 4 + STOP_STEPS
    assert nearest() <= TOKEN * 4  # within a coarse token of a standstill on every read-out
    # finite differences smaller than a token read no slope, and Newton steps on them move nothing
    calls.clear()
    ConstrainedAgent._stop_by_newton(counted, origin, push(origin), wanted, 4)
    assert nearest() > 10 * STOP_SETTLED


def stop_probes(vla, pooling):
    width = vla.layer_width("backbone.1")
    return tuple(Probe(feature=f, kind=REGRESSION, layer="backbone.1", model=vla.name, pooling=pooling,
                       weight=torch.ones(width, dtype=torch.float64), bias=0.0, mean=torch.zeros(width),
                       std=torch.ones(width)) for f in ("dz", "dx", "dy", "dyaw"))


@pytest.mark.parametrize("name, pooling, by_dimension", [
    ("autoregressive", "action", True), ("autoregressive", "prefix", False), ("hybrid", "action", False)])
def test_the_stop_searches_by_dimension_only_where_each_read_out_writes_its_own_token(name, pooling, by_dimension):
    vla = tiny_policy(name)
    steering = Steering("control", probes=stop_probes(vla, pooling), pause=True)
    agent = ConstrainedAgent(vla, parse_constraint("height=high"), steering)
    assert agent._one_dimension_a_token is by_dimension
