"""L2-regularised logistic regression for every layer at once: Newton's method (IRLS), batched over layers.

Objective per layer: sum_i [softplus(s_i) - y_i s_i] + l2/2 ||w||^2 with s_i = z_i.w + b (intercept unpenalised),
the objective of scikit-learn's LogisticRegression with C = 1 / l2.

Each step uses the exact Hessian Z^T diag(p(1-p)) Z (one weighted Gram matrix per layer) and a line search that is
free: logits are linear in the parameters, so s + t Z.delta for every trial step length t costs
no pass over the data. Trial lengths above 1 let the first steps grow the weights fast on separable layers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

HESSIAN_MASS = 0.99  # share of the rows' total Hessian weight kept when building one
STEP_LENGTHS = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25, 0.125, 1 / 16, 1 / 64, 1 / 256)


def _objective(s: torch.Tensor, y: torch.Tensor, w: torch.Tensor, l2: float) -> torch.Tensor:
    """s [..., L, n] logits, y [n], w [..., L, p] -> [..., L] in float64."""
    return (F.softplus(s) - y * s).sum(-1, dtype=torch.float64) + 0.5 * l2 * w.double().square().sum(-1)


def fit_logistic(
    z: torch.Tensor, y: torch.Tensor, l2: float, steps: int = 20, tol: float = 1e-4, gram: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """z [L, n, p] float32 standardised inputs, y [n] in {0, 1} -> weights [L, p], intercepts [L] (float64).

    gram: [Z 1]^T [Z 1] per layer [L, p + 1, p + 1] if the caller has it (the ridge fit does). Newton starts from
    w = 0, where every row has the same weight p(1-p), so the first Hessian is that Gram matrix times p(1-p): free.

    A layer stops after the first step whose Newton decrement g^T H^-1 g is below tol * n: Newton converges
    quadratically there, so its objective is then within a negligible fraction of the optimum. Hessians dominate the
    cost, so a layer gets a new one only when the decrement measured with its last one is not yet below tol * n (that
    last step is then taken with the old Hessian), and finished layers drop out of the batch.
    """
    n_layers, n, p = z.shape
    dev = z.device
    y = y.to(z.dtype)
    prior = y.mean().clamp(1e-6, 1 - 1e-6)
    w = torch.zeros(n_layers, p, dtype=torch.float64, device=dev)
    b = torch.full((n_layers,), float(torch.log(prior / (1 - prior))), dtype=torch.float64, device=dev)
    s = torch.full((n_layers, n), float(b[0]), dtype=z.dtype, device=dev)
    penalty = torch.diag(torch.tensor([float(l2)] * p + [0.0], dtype=torch.float64, device=dev))
    hess = torch.zeros(n_layers, p + 1, p + 1, dtype=torch.float64, device=dev)  # per layer, its latest Hessian,
    state = [0] * n_layers  # which is 0: not built yet, 1: from an earlier point, 2: current
    if gram is not None:
        hess, state = gram * float(prior * (1 - prior)) + penalty, [2] * n_layers
    trial = torch.tensor(STEP_LENGTHS, dtype=torch.float64, device=dev)
    # reused: a fresh [n, p] tensor per Hessian costs as much as the product
    scratch = torch.empty(n, p, dtype=z.dtype, device=dev)
    moving = list(range(n_layers))
    for _ in range(steps):
        if not moving:
            break
        idx = torch.tensor(moving, device=dev)
        sm, wm = s[idx], w[idx]
        prob = torch.sigmoid(sm)
        resid = prob - y
        # per-layer products: z[moving] would copy the data, and MKL's batched one-column gemm is 3x slower than gemv
        grad_w = torch.stack([resid[i] @ z[layer] for i, layer in enumerate(moving)]).double() + l2 * wm
        grad = torch.cat([grad_w, resid.sum(-1, dtype=torch.float64)[:, None]], -1)
        delta = torch.zeros_like(grad)
        built = [i for i, layer in enumerate(moving) if state[layer] > 0]
        if built:
            delta[built] = -_spd_solve(hess[idx[built]], grad[built])
        decrement = -(grad * delta).sum(-1)
        # a new Hessian unless the layer has its current one, or its old one already gives the last step
        last = (decrement < tol * n).tolist()
        renew = [i for i, layer in enumerate(moving) if state[layer] == 0 or state[layer] == 1 and not last[i]]
        for i in renew:
            hess[moving[i]] = _weighted_gram(z[moving[i]], prob[i] * (1 - prob[i]), scratch) + penalty
        if renew:
            delta[renew] = -_spd_solve(hess[idx[renew]], grad[renew])
            decrement = -(grad * delta).sum(-1)
        dw, db = delta[:, :p], delta[:, p]
        ds = torch.stack([z[layer] @ dw[i].to(z.dtype) for i, layer in enumerate(moving)]) + db[:, None].to(z.dtype)
        cand = _objective(sm + trial[:, None, None].to(z.dtype) * ds, y, wm + trial[:, None, None] * dw, l2)
        t = trial[cand.argmin(0)]  # [M] the best trial length per layer
        w[idx], b[idx], s[idx] = wm + t[:, None] * dw, b[idx] + t * db, sm + t[:, None].to(z.dtype) * ds
        for layer in moving:
            state[layer] = 1  # every moving layer now holds a Hessian, from before this step
        moving = [layer for layer, dec in zip(moving, decrement.tolist()) if dec >= tol * n]
    return w, b


def _spd_solve(hess: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """hess [M, q, q] positive definite (penalised weights, intercept row sum(d) > 0), grad [M, q] -> hess^-1 grad.
    Cholesky, not torch.linalg.solve: its batched LU fails inside MKL with 2+ threads at this size (torch 2.14,
    "Pivots given to lu_solve must all be greater or equal to 1")."""
    return torch.cholesky_solve(grad[..., None], torch.linalg.cholesky(hess))[..., 0]


def _weighted_gram(z: torch.Tensor, d: torch.Tensor, scratch: torch.Tensor) -> torch.Tensor:
    """[Z 1]^T diag(d) [Z 1] of one layer, [p + 1, p + 1] in float64, from the rows that carry HESSIAN_MASS of the
    weight d. Once a probe is confident most rows weigh almost nothing, so later Hessians cost a fraction of a full
    pass; the gradient stays exact, so Newton still converges to the exact optimum (HESSIAN_MASS: docs/probes.md)."""
    order = torch.sort(d, descending=True)
    count = int(torch.searchsorted(order.values.cumsum(0), HESSIAN_MASS * order.values.sum())) + 1
    rows, root = order.indices[:count], order.values[:count].sqrt()
    a = torch.index_select(z, 0, rows, out=scratch[:count]).mul_(root[:, None])
    zz = (a.T @ a).double()
    zd = (root @ a).double()[:, None]  # Z^T d over the kept rows
    dd = d.sum(dtype=torch.float64).reshape(1, 1)  # every row: exact, and free
    return torch.cat([torch.cat([zz, zd], 1), torch.cat([zd.T, dd], 1)], 0)
