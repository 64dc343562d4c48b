"""The bracketing search on a reading shift that the box=action controller runs at each pushed re-plan."""

import numpy as np
import pytest

from vlactl.rollout.bracket import MAX_SHIFT, Bracket

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
