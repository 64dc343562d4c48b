"""Ridge regression for every layer x feature at once, the penalty chosen per layer x feature by cross-validation
with folds of whole episodes inside the training split.

Why grouped folds and not GCV / leave-one-out (both closed form): consecutive frames of an episode are near-duplicates,
so a held-out frame always has a twin in the fit and LOO/GCV pick far too little shrinkage.

The data are read once. Everything else comes from per-fold moments (n, sum z, sum z z^T, sum z y^T, sum y,
sum y^2): a fold's training moments are the total minus the fold's own, and the fold's validation error is a
quadratic form in its own moments. One eigendecomposition per layer and fold gives the solutions for the whole
penalty grid at once: w(lam) = V diag(1 / (e + lam)) V^T C.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Moments:
    """Sums over a set of rows of standardised inputs z [p] and targets y [F], per layer, in float64."""

    n: float
    sz: torch.Tensor  # [L, p]
    zz: torch.Tensor  # [L, p, p]
    zy: torch.Tensor  # [L, p, F]
    sy: torch.Tensor  # [F]
    yy: torch.Tensor  # [F]

    @staticmethod
    def of(z: torch.Tensor, y: torch.Tensor) -> "Moments":
        """z [L, n, p] float32 (the big one, multiplied in float32), y [n, F]."""
        y32 = y.to(z.dtype)
        return Moments(
            n=float(z.shape[1]),
            sz=z.sum(1).double(),  # summing in float64 directly is 20x slower on CPU
            zz=torch.bmm(z.mT, z).double(),
            zy=torch.matmul(z.mT, y32).double(),
            sy=y.double().sum(0),
            yy=y.double().square().sum(0),
        )

    def __add__(self, o: "Moments") -> "Moments":
        return Moments(self.n + o.n, self.sz + o.sz, self.zz + o.zz, self.zy + o.zy, self.sy + o.sy, self.yy + o.yy)

    def augmented_gram(self) -> torch.Tensor:
        """[Z 1]^T [Z 1] per layer, [L, p + 1, p + 1]."""
        top = torch.cat([self.zz, self.sz[:, :, None]], -1)
        bottom = torch.cat([self.sz[:, None, :], torch.full_like(self.sz[:, :1, None], self.n)], -1)
        return torch.cat([top, bottom], -2)

    def __sub__(self, o: "Moments") -> "Moments":
        return Moments(self.n - o.n, self.sz - o.sz, self.zz - o.zz, self.zy - o.zy, self.sy - o.sy, self.yy - o.yy)


class RidgePath:
    """Ridge solutions (with an unpenalised intercept) for any penalty, from one set of training moments."""

    def __init__(self, m: Moments):
        self.mean = m.sz / m.n  # [L, p]
        self.ybar = m.sy / m.n  # [F]
        gram = m.zz - m.n * self.mean[:, :, None] * self.mean[:, None, :]
        cross = m.zy - m.n * self.mean[:, :, None] * self.ybar
        self.e, self.v = torch.linalg.eigh(gram)  # [L, p], [L, p, p]
        self.proj = self.v.mT @ cross  # [L, p, F]

    def solve(self, lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """lam broadcastable to [..., L, F] -> weights [..., L, p, F], intercepts [..., L, F]."""
        shrink = 1.0 / (self.e[..., :, None] + lam.unsqueeze(-2))  # [..., L, p, F]
        w = layer_matmul(self.v, self.proj * shrink)
        b = self.ybar - torch.einsum("lp,...lpf->...lf", self.mean, w)
        return w, b


def layer_matmul(a: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """a [L, p, q] @ x [..., L, q, F] as one batched matmul with the leading dims folded into the columns
    (broadcasting would run many skinny products, which MKL does slowly)."""
    lead = x.shape[:-3]
    cols = x.movedim(-3, 0).movedim(-2, 1).reshape(x.shape[-3], x.shape[-2], -1)  # [L, q, (...) F]
    out = torch.bmm(a, cols).reshape(a.shape[0], a.shape[1], *lead, x.shape[-1])
    return out.movedim(1, -2).movedim(0, -3)


def sse(m: Moments, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Sum over m's rows of (z.w + b - y)^2, per layer and feature: w [..., L, p, F], b [..., L, F]."""
    quad = (w * layer_matmul(m.zz, w)).sum(-2)
    lin = torch.einsum("lp,...lpf->...lf", m.sz, w)
    cross = (m.zy * w).sum(-2)
    return quad + 2 * b * lin + m.n * b * b - 2 * cross - 2 * b * m.sy + m.yy


@dataclass
class RidgeFit:
    weight: torch.Tensor  # [L, p, F] on the standardised inputs
    bias: torch.Tensor  # [L, F]
    lam: torch.Tensor  # [L, F] the chosen penalty
    cv_r2: torch.Tensor  # [L, F] cross-validated R^2 at that penalty (1 - SSE / SSE of the fold-train mean)
    moments: Moments  # of all training rows


def fit_ridge(z: torch.Tensor, y: torch.Tensor, fold_sizes: list[int], grid: torch.Tensor) -> RidgeFit:
    """z [L, n, p] standardised training inputs with rows grouped by fold (so folds are views, not copies), y [n, F],
    fold_sizes [k] the number of rows of each fold in that order, grid [G] penalties."""
    per_fold = [Moments.of(zf, yf) for zf, yf in zip(z.split(fold_sizes, 1), y.split(fold_sizes, 0))]
    total = per_fold[0]
    for m in per_fold[1:]:
        total = total + m
    grid = grid.double()[:, None, None]  # [G, 1, 1]
    cv_sse = 0.0
    base_sse = 0.0
    for held_out in per_fold:
        path = RidgePath(total - held_out)
        cv_sse = cv_sse + sse(held_out, *path.solve(grid))
        base_sse = base_sse + sse(held_out, torch.zeros_like(path.proj), path.ybar.expand_as(path.proj[:, 0]))
    best = cv_sse.argmin(0)  # [L, F]
    lam = grid.flatten()[best]
    w, b = RidgePath(total).solve(lam)
    cv_r2 = 1 - cv_sse.gather(0, best[None])[0] / base_sse
    return RidgeFit(weight=w, bias=b, lam=lam, cv_r2=cv_r2, moments=total)
