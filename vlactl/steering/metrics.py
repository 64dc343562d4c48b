"""Test metrics of a batch of probes, each against its trivial baseline, and the robustness of Remark 1."""

from __future__ import annotations

import torch

from vlactl.steering.probes import LOGISTIC, LinearProbes


def regression_metrics(pred: torch.Tensor, y: torch.Tensor, train_mean: torch.Tensor) -> dict[str, torch.Tensor]:
    """pred [L, n, F], y [n, F], train_mean [F] -> MAE and R^2 [L, F] against predicting the training mean.

    R^2 = 1 - SSE / SSE(train mean), so the baseline's R^2 is 0 by construction (NaN where the baseline is exact).
    """
    err = pred - y
    base = y - train_mean
    base_sse = base.square().sum(0)
    return {
        "mae": err.abs().mean(1),
        "r2": 1 - err.square().sum(1) / torch.where(base_sse > 0, base_sse, torch.nan),
        "baseline_mae": base.abs().mean(0).expand(pred.shape[0], -1),
        "baseline_r2": torch.zeros(pred.shape[0], pred.shape[2], dtype=pred.dtype),
    }


def _balanced_accuracy(hit: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean per-class recall over the classes present; hit [..., n, F] bool, y [n, F] in {0, 1}."""
    pos, neg = y > 0.5, y <= 0.5
    recalls = []
    for cls in (pos, neg):
        count = cls.sum(0)
        recall = (hit & cls).sum(-2) / count.clamp(min=1)
        recalls.append(torch.where(count > 0, recall.double(), torch.nan))
    return torch.stack(recalls).nanmean(0)


def classification_metrics(logit: torch.Tensor, y: torch.Tensor, train_majority: torch.Tensor) -> dict:
    """logit [L, n, F], y [n, F] in {0, 1}, train_majority [F] in {0, 1} -> accuracy, balanced accuracy [L, F]
    and those of always predicting the training split's majority class."""
    hit = (logit > 0) == (y > 0.5)
    base_hit = (train_majority > 0.5) == (y > 0.5)
    n_layers = logit.shape[0]
    return {
        "accuracy": hit.double().mean(1),
        "balanced_accuracy": _balanced_accuracy(hit, y),
        "baseline_accuracy": base_hit.double().mean(0).expand(n_layers, -1),
        "baseline_balanced_accuracy": _balanced_accuracy(base_hit, y).expand(n_layers, -1),
    }


def robustness(
    probes: LinearProbes, x: torch.Tensor, norms: list[float], directions: int, rows: int = 512, seed: int = 0,
    layer_ids: list[int] | None = None,
) -> dict[str, torch.Tensor]:
    """Remark 1: the change |f(x + eps) - f(x)| of each probe's output under random perturbations eps.

    x [L, n, d] raw representations; ||eps|| = rho ||x|| for each relative norm rho, in `directions` random
    directions per layer (uniform on the sphere), for up to `rows` random frames x every direction. The output f is
    the reading for regression probes and the probability sigmoid(logit) for logistic ones. Returns mean and max,
    [L, F] each, per rho. A layer's directions come from `seed` and its id (default: its position in x), so its
    numbers do not depend on which layers share its batch.
    """
    n_layers, n, d = x.shape
    x = x[:, torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:rows]]
    ids = range(n_layers) if layer_ids is None else layer_ids
    dirs = torch.stack([
        torch.randn(directions, d, generator=torch.Generator().manual_seed(seed * 1_000_003 + i), dtype=torch.float64)
        for i in ids
    ])
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    along = torch.einsum("lkd,lfd->lfk", dirs, probes.weight)  # w.e per layer, feature, direction
    size = x.double().norm(dim=-1)  # [L, n]
    logit = probes.readings(x).mT  # [L, F, n]
    is_logistic = torch.tensor([k == LOGISTIC for k in probes.kinds])[None, :, None, None]
    out = {}
    for rho in norms:
        shift = rho * size[:, None, :, None] * along[:, :, None, :]  # [L, F, n, k]
        prob_change = (torch.sigmoid(logit[..., None] + shift) - torch.sigmoid(logit[..., None])).abs()
        change = torch.where(is_logistic, prob_change, shift.abs())
        out[f"robust_mean_{rho:g}"] = change.mean((-1, -2))
        out[f"robust_max_{rho:g}"] = change.amax((-1, -2))
    return out
