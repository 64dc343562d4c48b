"""Probe families meant for steering (`vlactl train-probes family=...`): a direction chosen without fitting every
weight, and a scale fitted along it, so the reading stays in the feature's units (the logit for binary features).

- `meandiff`: the difference of the class means (binary features: label 1 against 0; continuous ones: above
  against below the training median);
- `covariance`: the covariance of the inputs with the label, X^T (y - mean y), the direction ridge tends to as its
  penalty grows (and the leading direction of the cross-covariance of one feature);
- `partial`: the covariance with the fit's other features regressed out: the feature's coefficient in the
  least-squares fit of the inputs on all the fit's labels at once, the change of the representation per unit of this
  feature with the others held. A feature that moves with the task's phase (the gripper closes as the hand stops
  descending) otherwise drags the others with it when pushed; `features=` says what is held.

All three work on the standardised inputs (or their kernel coordinates, `vlactl.steering.probes`: the directions are
linear in the rows, so they map back exactly). Along the direction v the reading is a (v.z) + c, with a and c the least
squares line (regression) or a one-dimensional logistic fit (binary).
"""

from __future__ import annotations

import torch

from vlactl.steering.logistic import fit_logistic

FAMILIES = ("fit", "meandiff", "covariance", "partial")  # fit: every weight fitted (ridge / logistic, the default)
SCALE_L2 = 1.0  # the one-dimensional logistic scale's penalty (scikit-learn's default): the direction is the steering
                # choice, its scale only calibrates the logit, so train-probes' logistic_l2 does not apply


def direction(z: torch.Tensor, y: torch.Tensor, binary: bool, family: str) -> torch.Tensor:
    """z [L, n, p] standardised rows, y [n] labels -> unit directions [L, p] (float64)."""
    if family == "covariance":
        v = torch.einsum("lnp,n->lp", z, (y - y.mean()).to(z.dtype)).double()
    else:
        upper = y > (0.5 if binary else y.median())
        if upper.all() or not upper.any():
            upper = y >= y.median()
        v = (z[:, upper].mean(1) - z[:, ~upper].mean(1)).double()
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def partial_directions(z: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """z [L, n, p] standardised rows, labels [n, F] -> unit directions [L, F, p] (float64): the rows of B in the
    least-squares fit z ~ (labels - mean) B, solved in the labels' F dimensions (a tiny ridge keeps collinear labels,
    speed beside dx, dy, dz, solvable)."""
    y = (labels - labels.mean(0)).double()
    gram = y.T @ y
    gram += 1e-6 * gram.diagonal().mean() * torch.eye(len(gram), dtype=gram.dtype, device=gram.device)
    cross = torch.einsum("nf,lnp->lfp", y.to(z.dtype), z).double()  # [L, F, p]
    v = torch.linalg.solve(gram, cross)
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def scaled_directions(
    z: torch.Tensor, labels: torch.Tensor, binary: list[bool], family: str, steps: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """z [L, n, p], labels [n, F] (0/1 for binary features) -> weights [L, p, F] and intercepts [L, F] (float64) of
    readings a (v.z) + c along each feature's `direction` v."""
    n_layers, _, p = z.shape
    w = torch.zeros(n_layers, p, len(binary), dtype=torch.float64, device=z.device)
    b = torch.zeros(n_layers, len(binary), dtype=torch.float64, device=z.device)
    partial = partial_directions(z, labels) if family == "partial" else None
    for i, is_binary in enumerate(binary):
        y = labels[:, i]
        v = partial[:, i] if partial is not None else direction(z, y, is_binary, family)
        proj = torch.einsum("lnp,lp->ln", z, v.to(z.dtype)).double()  # [L, n]
        if is_binary:
            scale = proj.std(1, keepdim=True).clamp_min(1e-12)
            a, c = fit_logistic((proj / scale)[..., None].float(), y, SCALE_L2, steps)
            a = a[:, 0] / scale[:, 0]
        else:
            centred = proj - proj.mean(1, keepdim=True)
            a = (centred * (y - y.mean())).sum(1) / centred.square().sum(1).clamp_min(1e-12)
            c = y.mean() - a * proj.mean(1)
        w[:, :, i], b[:, i] = a[:, None] * v, c
    return w, b
