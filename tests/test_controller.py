"""Properties of the minimum-norm controller (SPEC.md §2, paper eq. 7): in the box after control, no push when
already inside, and no smaller push exists."""

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from vlactl.models.hooks import masked_mean
from vlactl.steering.controller import box_control, fixed_alpha, mean_difference, multi_box_control

SEEDS = st.integers(0, 2**31 - 1)


def _problem(seed, rows, d, k, width):
    rng = np.random.default_rng(seed)
    x = torch.as_tensor(rng.normal(0, 3, (rows, d)))
    w = torch.as_tensor(rng.normal(0, 1, (k, d)))
    b = torch.as_tensor(rng.normal(0, 1, k))
    centre = torch.as_tensor(rng.normal(0, 2, k))
    return x, w, b, centre - width, centre + width


def _inside(after, lo, hi, rel=1e-5):
    slack = rel * (1 + after.abs())
    return bool(((after >= lo - slack) & (after <= hi + slack)).all())


@settings(max_examples=100, deadline=None)
@given(SEEDS, st.integers(1, 20), st.integers(1, 64), st.floats(0.0, 3.0))
def test_single_box_lands_inside_with_the_least_push(seed, rows, d, width):
    x, w, b, lo, hi = _problem(seed, rows, d, 1, width)
    c = box_control(x.float(), w[0].float(), b[0], lo[0], hi[0])
    assert _inside(c.after[:, 0], lo[0], hi[0])
    inside = (c.before[:, 0] >= lo[0]) & (c.before[:, 0] <= hi[0])
    assert bool((c.u[inside] == 0).all()) and not bool(c.active[inside].any())
    # the least push moves the reading straight to the nearest bound: |change| / ||w|| is a lower bound for any u
    gap = (c.before[:, 0].clamp(lo[0], hi[0]) - c.before[:, 0]).abs()
    torch.testing.assert_close(c.norm, gap / w[0].norm(), rtol=1e-4, atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(SEEDS, st.integers(1, 16), st.floats(-5, 5), st.floats(0, 2))
def test_one_sided_boxes(seed, d, bound, above):
    x, w, b, _, _ = _problem(seed, 8, d, 1, 0.0)
    up = box_control(x, w[0], b[0], zmin=bound)
    down = box_control(x, w[0], b[0], zmax=bound + above)
    assert bool((up.after[:, 0] >= bound - 1e-9).all()) and bool((down.after[:, 0] <= bound + above + 1e-9).all())


def _kkt_multipliers(c, w):
    """u = W^T nu for the optimum; nu > 0 only at a lower bound, nu < 0 only at an upper one."""
    nu = torch.linalg.solve(w @ w.mT, w @ c.u.mT).mT
    assert torch.allclose(nu @ w, c.u, atol=1e-7 * (1 + c.u.abs().max()))  # u lies in the span of the probes
    return nu


@settings(max_examples=150, deadline=None)
@given(SEEDS, st.integers(1, 12), st.integers(1, 3), st.integers(0, 8), st.floats(0.0, 2.0))
def test_several_boxes_are_met_by_the_kkt_optimum(seed, rows, k, extra_dims, width):
    d = k + extra_dims
    x, w, b, lo, hi = _problem(seed, rows, d, k, width)
    assume(torch.linalg.cond(w @ w.mT) < 1e3)  # a well-posed QP; the parallel-probe case has its own test
    c = multi_box_control(x, w, b, lo, hi)
    assert bool(c.feasible.all())
    assert _inside(c.after, lo, hi)
    nu = _kkt_multipliers(c, w)
    tol = 1e-6 * (1 + c.after.abs())
    at_lo, at_hi = (c.after - lo).abs() <= tol, (c.after - hi).abs() <= tol
    big = nu.abs() > 1e-7 * (1 + nu.abs().max())
    assert bool((~big | (nu > 0) & at_lo | (nu < 0) & at_hi).all())
    already = ((c.before >= lo) & (c.before <= hi)).all(-1)
    assert bool((c.u[already] == 0).all())


def _dykstra(x, w, b, lo, hi, iters=3000):
    """Projection of 0 onto {u : lo <= W(x+u)+b <= hi} by Dykstra's alternating projections: a second, independent
    solver (slow, plain numpy) for small problems."""
    halfspaces = [(w[i], hi[i] - w[i] @ x - b[i]) for i in range(len(w))]
    halfspaces += [(-w[i], -(lo[i] - w[i] @ x - b[i])) for i in range(len(w))]
    u = np.zeros_like(x)
    corr = [np.zeros_like(x) for _ in halfspaces]
    for _ in range(iters):
        for j, (a, c) in enumerate(halfspaces):
            v = u + corr[j]
            excess = a @ v - c
            proj = v - max(excess, 0.0) / (a @ a) * a
            corr[j] = v - proj
            u = proj
    return u


@settings(max_examples=25, deadline=None)
@given(SEEDS, st.integers(1, 3), st.integers(0, 4), st.floats(0.1, 2.0))
def test_several_boxes_match_an_independent_solver(seed, k, extra_dims, width):
    x, w, b, lo, hi = _problem(seed, 1, k + extra_dims, k, width)
    assume(torch.linalg.cond(w @ w.mT) < 20)  # Dykstra converges slowly for near-parallel probes
    c = multi_box_control(x, w, b, lo, hi)
    ref = _dykstra(x[0].numpy(), w.numpy(), b.numpy(), lo.numpy(), hi.numpy())
    assert float(c.norm[0]) <= np.linalg.norm(ref) * (1 + 1e-6) + 1e-9
    np.testing.assert_allclose(c.u[0].numpy(), ref, atol=1e-4 * (1 + np.abs(ref).max()))


@settings(max_examples=50, deadline=None)
@given(SEEDS, st.integers(1, 3), st.integers(0, 6), st.floats(0.0, 2.0))
def test_no_random_feasible_point_is_shorter(seed, k, extra_dims, width):
    x, w, b, lo, hi = _problem(seed, 1, k + extra_dims, k, width)
    c = multi_box_control(x, w, b, lo, hi)
    rng = np.random.default_rng(seed)
    for scale in (1e-3, 1e-2, 1e-1, 1.0):
        cand = c.u + torch.as_tensor(rng.normal(0, scale, (2000, x.shape[1])))
        reading = (x + cand) @ w.mT + b
        feasible = ((reading >= lo) & (reading <= hi)).all(-1)
        assert bool((cand[feasible].norm(dim=-1) >= c.norm[0] * (1 - 1e-9)).all())


@settings(max_examples=100, deadline=None)
@given(SEEDS, st.integers(1, 8), st.integers(1, 3), st.integers(1, 8), st.floats(0.0, 0.5))
def test_held_readings_move_at_most_their_tolerance(seed, rows, holds, extra_dims, tol):
    x, w, b, lo, hi = _problem(seed, rows, holds + extra_dims, holds + 1, 1.0)
    lo[1:], hi[1:] = -tol, tol  # probe 0 gets its box, the others may move by at most tol
    relative = [False] + [True] * holds
    c = multi_box_control(x, w, b, lo, hi, relative=relative)
    assert _inside(c.after[:, 0], lo[0], hi[0])
    assert bool(((c.after[:, 1:] - c.before[:, 1:]).abs() <= tol + 1e-6 * (1 + c.before[:, 1:].abs())).all())
    free = multi_box_control(x, w[:1], b[:1], lo[:1], hi[:1])
    assert bool((c.norm >= free.norm - 1e-9).all())  # holding costs push, never saves it
    if tol == 0:  # exact holds: the push is orthogonal to every held probe
        assert bool(((c.u @ w[1:].mT).abs() <= 1e-7 * (1 + c.u.abs().amax())).all())


@settings(max_examples=50, deadline=None)
@given(SEEDS, st.integers(1, 5), st.integers(7, 10), st.integers(0, 6))
def test_one_valued_boxes_beyond_the_enumeration_are_the_min_norm_solve(seed, rows, k, extra_dims):
    # a stop's push pins up to eight read-outs a layer: each box one value, one candidate, any number of them
    x, w, b, _, _ = _problem(seed, rows, k + extra_dims, k, 0.0)
    assume(torch.linalg.cond(w @ w.mT) < 1e3)
    shift = torch.as_tensor(np.random.default_rng(seed).normal(0, 1, k))
    c = multi_box_control(x, w, b, shift, shift, relative=[True] * k)
    want = torch.linalg.pinv(w.double()) @ shift  # the least-norm u with W u = shift
    torch.testing.assert_close(c.u.double(), want.expand_as(c.u).to(torch.float64), atol=1e-6, rtol=1e-6)
    assert bool(c.feasible.all())


def test_more_wide_boxes_than_the_enumeration_takes_are_refused():
    w = torch.eye(8)
    with pytest.raises(ValueError, match="at most 6 probes with a box wider than one value"):
        multi_box_control(torch.zeros(1, 8), w, torch.zeros(8), -torch.ones(8), torch.ones(8))
    multi_box_control(torch.zeros(1, 8), w, torch.zeros(8), torch.tensor([-1.0] * 6 + [0.5] * 2),
                      torch.tensor([1.0] * 6 + [0.5] * 2))  # six wide, two one-valued: solved


def test_parallel_probes_with_compatible_boxes():
    w = torch.tensor([[1.0, 0.0], [2.0, 0.0]])
    x = torch.tensor([[5.0, 1.0]])
    c = multi_box_control(x, w, torch.zeros(2), torch.tensor([-1.0, -4.0]), torch.tensor([1.0, 1.0]))
    assert bool(c.feasible.all())
    torch.testing.assert_close(c.after, torch.tensor([[0.5, 1.0]], dtype=torch.float64))


def test_incompatible_boxes_are_flagged():
    w = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    c = multi_box_control(torch.zeros(1, 2), w, torch.zeros(2), torch.tensor([1.0, -3.0]), torch.tensor([2.0, -2.0]))
    assert not bool(c.feasible.any())


def test_empty_box_and_zero_probe_are_refused():
    with pytest.raises(ValueError, match="empty box"):
        box_control(torch.zeros(1, 2), torch.ones(2), 0.0, 1.0, -1.0)
    with pytest.raises(ValueError, match="zero weight"):
        multi_box_control(torch.zeros(1, 2), torch.zeros(1, 2), 0.0, -1.0, 1.0)


@settings(max_examples=100, deadline=None)
@given(SEEDS, st.integers(2, 40), st.integers(1, 32), st.floats(-3, 3), st.floats(0, 1))
def test_mean_pooling_identity(seed, tokens, d, zmin, width):
    """Adding u to every token of the read-out set shifts their mean by exactly u, so the probe reading of the
    pooled vector after the intervention is exactly on target (SPEC.md §2)."""
    rng = np.random.default_rng(seed)
    hidden = torch.as_tensor(rng.normal(0, 2, (1, tokens, d)))
    in_set = torch.as_tensor(rng.random((1, tokens)) < 0.6)
    assume(bool(in_set.any()))
    w, b = torch.as_tensor(rng.normal(0, 1, d)), float(rng.normal())
    pooled = masked_mean(hidden, in_set)  # the read-out the hooks use
    c = box_control(pooled, w, b, zmin, zmin + width)
    steered = hidden + in_set[..., None] * c.u[:, None, :]  # u added to every token of the set
    new_pooled = masked_mean(steered, in_set)
    torch.testing.assert_close(new_pooled, pooled + c.u)
    torch.testing.assert_close(new_pooled @ w + b, c.after[:, 0])
    assert zmin - 1e-9 <= float(new_pooled @ w + b) <= zmin + width + 1e-9
    torch.testing.assert_close(steered[~in_set], hidden[~in_set])  # tokens outside the set are untouched


def test_fixed_alpha_and_mean_difference():
    x = torch.randn(10, 4, dtype=torch.float64)
    w = torch.tensor([3.0, 4.0, 0.0, 0.0])
    c = fixed_alpha(x, w, 0.0, alpha=2.0)
    torch.testing.assert_close(c.norm, torch.full((10,), 2.0, dtype=torch.float64))
    torch.testing.assert_close(c.after[:, 0] - c.before[:, 0], torch.full((10,), 10.0, dtype=torch.float64))
    labels = torch.tensor([1, 0] * 5)
    shifted = x + labels[:, None] * torch.tensor([0.0, 0.0, 5.0, 0.0], dtype=torch.float64)
    direction = mean_difference(shifted, labels)
    assert abs(float(direction.norm()) - 1) < 1e-9 and float(direction[2]) > 0.9
