"""The feature controller (paper eq. 7, LiSeCo Thm 4.1): the smallest u with every probe reading of x + u in its box.

Readings are zeta = W.x + b (for a logistic probe, the logit). For one probe the answer is closed form:
u = (zmax - zeta) W / ||W||^2 above the box, (zmin - zeta) W / ||W||^2 below it, 0 inside. For k probes on one layer
the problem min ||u||^2 s.t. zmin <= W (x + u) + b <= zmax is a small QP solved exactly by enumerating active sets:
its solution is the minimum-norm solution of W_S u = t_S for its active set S (each active probe at one of its
bounds), so among the 3^k candidates the feasible one of least norm is the optimum; a box of one value (a hold
without tolerance, a push to one reading) is always active, one candidate. Everything after the readings happens in
the k-dimensional space of the probes, so up to 6 wider boxes a layer cost nothing next to the forward pass. Plain
tensors in, plain tensors out: no model, no hooks.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch

MAX_PROBES = 6  # boxes wider than one value a layer: 3^6 = 729 candidate active sets


@dataclass
class Control:
    """Per row: the intervention u [B, d], readings before and after [B, k], ||u|| [B], and whether u != 0 [B]."""

    u: torch.Tensor
    before: torch.Tensor
    after: torch.Tensor
    norm: torch.Tensor
    active: torch.Tensor
    feasible: torch.Tensor  # [B] False only if the boxes cannot all hold at once (then u is the least-violating one)


def _float64(x, w, *scalars):
    """The controller's own arithmetic runs in float64 (k-dimensional, cheap), so a float32 model still lands inside
    its box to float32 rounding; u goes back in x's dtype."""
    w = torch.as_tensor(w).double()
    w = w[None] if w.dim() == 1 else w
    return (x.double(), w, *(torch.as_tensor(v, dtype=torch.float64).expand(w.shape[0]) for v in scalars))


def _result(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor, u: torch.Tensor, feasible=None) -> Control:
    """x and u in the caller's dtype, w and b in float64; the readings are those of x and of x + u as the model
    will hold it (the sum rounded to x's dtype)."""
    before = x.double() @ w.mT + b
    after = (x + u).double() @ w.mT + b
    norm = u.double().norm(dim=-1)
    ok = torch.ones_like(norm, dtype=torch.bool) if feasible is None else feasible
    return Control(u=u, before=before, after=after, norm=norm, active=norm > 0, feasible=ok)


def _check(w: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> None:
    if bool((lo > hi).any()):
        raise ValueError(f"empty box: zmin {lo.tolist()} > zmax {hi.tolist()}")
    if bool((w.norm(dim=-1) == 0).any()):
        raise ValueError("a probe with zero weight cannot steer its reading")


def box_control(x: torch.Tensor, w: torch.Tensor, b, zmin=-torch.inf, zmax=torch.inf) -> Control:
    """Eq. 7 for one probe: x [B, d], w [d], scalar bias and bounds (either bound may be infinite)."""
    xd, wd, bd, lo, hi = _float64(x, w, b, zmin, zmax)
    _check(wd, lo, hi)
    zeta = (xd @ wd.mT + bd)[:, 0]
    target = torch.minimum(torch.maximum(zeta, lo), hi)
    u = ((target - zeta) / wd.square().sum())[:, None] * wd
    return _result(x, wd, bd, u.to(x.dtype))


def multi_box_control(x: torch.Tensor, w: torch.Tensor, b, zmin, zmax, tol: float = 1e-9, relative=None) -> Control:
    """The exact minimum-norm u for k probes at once: x [B, d], w [k, d], b, zmin, zmax [k] (bounds may be inf).

    relative [k] bool: that probe's box is [zeta + zmin, zeta + zmax] around its own unsteered reading zeta, i.e. a
    bound on how far u may move it (zmin = zmax = 0: u leaves that reading alone, so it is orthogonal to its probe)."""
    xd, wd, bd, lo, hi = _float64(x, w, b, zmin, zmax)
    _check(wd, lo, hi)
    k = wd.shape[0]
    equal = (lo == hi).tolist()  # a box of one value (a hold, a relative push) is always active at it: one candidate
    if k - sum(equal) > MAX_PROBES:
        raise ValueError(f"at most {MAX_PROBES} probes with a box wider than one value can be controlled on one layer, "
                         f"got {k - sum(equal)}")
    zeta = xd @ wd.mT + bd  # [B, k]
    relative = torch.zeros(k, dtype=torch.bool) if relative is None else torch.as_tensor(relative, dtype=torch.bool)
    # the reading change r = W u must lie in [need_lo, need_hi]
    need_lo, need_hi = (torch.where(relative, bound, bound - zeta) for bound in (lo, hi))
    gram = wd @ wd.mT  # [k, k]
    scale = 1 + zeta.abs().amax(-1)
    # every active set at once (per probe: free, at its lower bound, at its upper bound), in one batch: the
    # pseudo-inverse of the Gram matrix with the free probes' rows and columns zeroed is the active block's own
    options = [(-1,) if one else (0, -1, 1) for one in equal]
    sides = torch.tensor(list(itertools.product(*options)), dtype=torch.int64)  # [C, k]
    mask = (sides != 0).to(torch.float64)
    block_inverse = torch.linalg.pinv(mask[:, :, None] * gram * mask[:, None, :])  # [C, k, k]
    target = torch.where(sides[:, None] < 0, need_lo, torch.where(sides[:, None] > 0, need_hi, 0.0))  # [C, B, k]
    usable = torch.isfinite(target).flatten(1).all(-1)  # an infinite bound is never active
    coef = torch.where(usable[:, None, None], target, 0.0) @ block_inverse.mT  # [C, B, k], u = coef @ W
    change = coef @ gram  # W u
    violation = ((need_lo - change).clamp(min=0) + (change - need_hi).clamp(min=0)).amax(-1) / scale  # [C, B]
    norm = (change * coef).sum(-1)  # ||u||^2
    violation = torch.where(usable[:, None], violation, torch.inf)
    feasible = violation <= tol
    solved = feasible.any(0)  # [B]
    # the least norm among the feasible sets; where none is feasible, the least violation (first on ties)
    pick = torch.where(solved, torch.where(feasible, norm, torch.inf).argmin(0), violation.argmin(0))
    u = (coef[pick, torch.arange(coef.shape[1])] @ wd).to(x.dtype)
    return _result(x, wd, bd, u, feasible=solved)


def fixed_alpha(x: torch.Tensor, w: torch.Tensor, b, alpha: float) -> Control:
    """Baseline: the same push for every row, u = alpha W / ||W|| (paper Fig. 3's 'alpha W')."""
    xd, wd, bd = _float64(x, w, b)
    u = (alpha * wd / wd.norm()).expand_as(xd)
    return _result(x, wd, bd, u.to(x.dtype))


def mean_difference(x: torch.Tensor, positive: torch.Tensor) -> torch.Tensor:
    """Unit direction from the mean of the negative rows to the mean of the positive ones (x [N, d], positive [N])."""
    positive = positive.bool()
    if positive.all() or not positive.any():
        raise ValueError("mean-difference direction needs rows of both classes")
    direction = x[positive].double().mean(0) - x[~positive].double().mean(0)
    return (direction / direction.norm()).to(x.dtype)
