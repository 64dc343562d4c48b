"""Linear observers f_l(x) = w.x + b for every layer x feature at once (paper §IV-A, SPEC.md §2).

Inputs are standardised per layer with the training split's mean and std; the standardisation is then folded into
the weights, so a probe is a plain linear map on the layer's original (pooled) representation, which is what the
controller needs. Continuous features get ridge probes (vlactl.steering.ridge), binary ones logistic probes
(vlactl.steering.logistic); for those the reading is the logit. A steering family (`ProbeSettings.family`,
vlactl.steering.directions) instead takes a direction (class-mean difference, covariance with the label) and fits only
the scale along it.

When the layer is wider than the training set (d > n) the fit runs in the n-dimensional span of the training rows
(the kernel form): Z = U diag(sqrt(e)) V^T from the eigendecomposition of Z Z^T. Ridge and L2-logistic solutions lie
in that span, so the reduced problem is exact and costs n^2 d instead of n d^2.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from vlactl.errors import UsageError
from vlactl.steering.directions import scaled_directions
from vlactl.steering.logistic import fit_logistic
from vlactl.steering.ridge import fit_ridge

REGRESSION, LOGISTIC = "regression", "logistic"


@dataclass(frozen=True)
class ProbeSettings:
    ridge_grid: tuple[float, ...] = (1e-1, 1.0, 1e1, 1e2, 1e3, 1e4, 1e5)
    logistic_l2: float = 1.0  # scikit-learn's default, C = 1
    newton_steps: int = 20
    family: str = "fit"  # vlactl.steering.directions.FAMILIES: every weight fitted, or a direction and its scale


@dataclass
class Probe:
    """One observer f(x) = weight . x + bias on one layer's pooled representation, in its original (raw) space.

    For a logistic probe the reading is the logit, which the controller steers; `output` is the probability.
    """

    feature: str
    kind: str  # REGRESSION or LOGISTIC
    layer: str
    model: str
    pooling: str
    weight: torch.Tensor  # [d] float64
    bias: float
    mean: torch.Tensor  # [d] the standardisation folded into weight and bias, kept for the record
    std: torch.Tensor  # [d]
    positive: str = ""  # logistic probes: what label 1 means, e.g. "gripper < 0.5 (closed)"
    metrics: dict = field(default_factory=dict)

    @property
    def width(self) -> int:
        return self.weight.shape[0]

    def reading(self, x: torch.Tensor) -> torch.Tensor:
        """x [..., d] -> [...]."""
        return x.double() @ self.weight + self.bias

    def output(self, x: torch.Tensor) -> torch.Tensor:
        z = self.reading(x)
        return torch.sigmoid(z) if self.kind == LOGISTIC else z

    def check_fits(self, model: str | None = None, width: int | None = None, pooling: str | None = None) -> None:
        """A one-line UsageError unless this probe reads `model`'s layer of this `width` at this `pooling` (None:
        not checked)."""
        model, width, pooling = model or self.model, width or self.width, pooling or self.pooling
        if (model, width, pooling) != (self.model, self.width, self.pooling):
            raise UsageError(
                f"probe {self.feature}@{self.layer} was trained on model {self.model!r}, pooling {self.pooling!r}, "
                f"width {self.width}; this is {model!r}, pooling {pooling!r}, width {width}"
            )


@dataclass
class LinearProbes:
    """Probes of L layers x F features as raw-space linear maps: reading = x . weight[l, f] + bias[l, f]."""

    weight: torch.Tensor  # [L, F, d]
    bias: torch.Tensor  # [L, F]
    mean: torch.Tensor  # [L, d] training mean (already folded into weight and bias; kept for the record)
    std: torch.Tensor  # [L, d]
    kinds: list[str]  # per feature: "regression" or "logistic"
    lam: torch.Tensor  # [L, F] penalty used (chosen by CV for ridge, fixed for logistic)
    cv_r2: torch.Tensor  # [L, F] cross-validated R^2 for ridge probes, NaN for logistic

    def readings(self, x: torch.Tensor) -> torch.Tensor:
        """x [L, n, d] -> [L, n, F] (logits for logistic probes) as float64, multiplied in x's dtype: enough for
        metrics, and a float64 copy of a whole test set would cost more than the product."""
        return torch.bmm(x, self.weight.to(x.dtype).mT).double() + self.bias[:, None, :]

    TENSORS = ("weight", "bias", "mean", "std", "lam", "cv_r2")

    def to(self, device: torch.device | str) -> "LinearProbes":
        return replace(self, **{name: getattr(self, name).to(device) for name in self.TENSORS})

    @staticmethod
    def cat(parts: list["LinearProbes"]) -> "LinearProbes":
        """The probes of several groups of layers (same features), as one."""
        return replace(parts[0], **{name: torch.cat([getattr(p, name) for p in parts]) for name in parts[0].TENSORS})

    def probe(self, li: int, fi: int, /, **about) -> Probe:
        """The probe of layer li and feature fi; `about` names it (feature, layer, model, pooling, ...)."""
        return Probe(
            kind=self.kinds[fi], weight=self.weight[li, fi].clone(), bias=float(self.bias[li, fi]),
            mean=self.mean[li].clone(), std=self.std[li].clone(), **about,
        )


def standardise_(z: torch.Tensor, chunk: int = 512) -> tuple[torch.Tensor, torch.Tensor]:
    """Standardise z [L, n, d] in place per layer and dimension; returns the mean and std used (float64).

    Constant dimensions get std 1 (they carry nothing). Reductions run over row chunks that stay in cache: a
    reduction over the middle axis of the whole tensor is several times slower on CPU.
    """
    mean = z.sum(1) / z.shape[1]
    z.sub_(mean[:, None])
    var = sum(part.square().sum(1) for part in z.split(chunk, 1)) / z.shape[1]
    std = var.double().sqrt()
    std = torch.where(std > 1e-6 * (1 + mean.double().abs()), std, torch.ones_like(std))
    z.div_(std[:, None].float())
    return mean.double(), std


def _kernel_basis(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """z [L, n, d] with d > n -> coordinates [L, n, n] and basis [L, d, n] with z = coords @ basis^T."""
    e, u = torch.linalg.eigh(torch.bmm(z, z.mT).double())
    keep = e > e[:, -1:] * 1e-10  # drop the null space (rank < n, e.g. the centring direction)
    root = torch.where(keep, e, torch.ones_like(e)).sqrt()
    coords = u * torch.where(keep, root, torch.zeros_like(root))[:, None, :]
    basis = (z.mT.double() @ u) / root[:, None, :] * keep[:, None, :]
    return coords.to(z.dtype), basis


def fit_probes(
    x: torch.Tensor,
    y: np.ndarray,
    kinds: list[str],
    train: np.ndarray,
    folds: np.ndarray,
    settings: ProbeSettings = ProbeSettings(),
) -> LinearProbes:
    """x [L, N, d] activations (float32), y [N, F] labels (0/1 for logistic features), train [n] row indices,
    folds [n] episode-grouped fold id of each training row.

    On the CPU with several torch threads, the layers are split among that many threads, each running torch on one:
    layers are independent, and the small products and factorisations of a fit gain little from BLAS threads
    (24 layers on 2 cores: 1.95 s against 2.7 s, docs/probes.md)."""
    threads = torch.get_num_threads()
    workers = min(threads, x.shape[0]) if x.device.type == "cpu" else 1
    if workers == 1:
        return _fit_layers(x, y, kinds, train, folds, settings)
    torch.set_num_threads(1)  # process-wide: every worker thread sees it
    try:
        with ThreadPoolExecutor(workers) as pool:
            parts = list(pool.map(lambda part: _fit_layers(part, y, kinds, train, folds, settings),
                                  x.tensor_split(workers)))
    finally:
        torch.set_num_threads(threads)
    return LinearProbes.cat(parts)


def _fit_layers(
    x: torch.Tensor, y: np.ndarray, kinds: list[str], train: np.ndarray, folds: np.ndarray, settings: ProbeSettings
) -> LinearProbes:
    dev = x.device  # everything is computed where the activations are: a GPU's batched products win most
    order = np.argsort(folds, kind="stable")  # rows grouped by fold: each fold is a view of one copy
    rows, folds = np.asarray(train)[order], np.asarray(folds)[order]
    labels = torch.as_tensor(np.asarray(y)[rows], dtype=torch.float64, device=dev)
    z = x.index_select(1, torch.as_tensor(rows, device=dev)).float()
    mean, std = standardise_(z)
    basis = None
    if z.shape[2] > z.shape[1]:
        z, basis = _kernel_basis(z)
    n_layers, _, p = z.shape
    n_feat = len(kinds)
    w = torch.zeros(n_layers, p, n_feat, dtype=torch.float64, device=dev)
    b = torch.zeros(n_layers, n_feat, dtype=torch.float64, device=dev)
    lam = torch.full((n_layers, n_feat), float(settings.logistic_l2), dtype=torch.float64, device=dev)
    cv_r2 = torch.full((n_layers, n_feat), float("nan"), dtype=torch.float64, device=dev)
    if settings.family != "fit":
        w, b = scaled_directions(z, labels, [k == LOGISTIC for k in kinds], settings.family, settings.newton_steps)
        lam.fill_(float("nan"))
    reg = [i for i, k in enumerate(kinds) if k == REGRESSION] if settings.family == "fit" else []
    gram = None
    if reg:
        grid = torch.tensor(settings.ridge_grid, dtype=torch.float64, device=dev)
        fit = fit_ridge(z, labels[:, reg], np.bincount(folds).tolist(), grid)
        w[:, :, reg], b[:, reg], lam[:, reg], cv_r2[:, reg] = fit.weight, fit.bias, fit.lam, fit.cv_r2
        gram = fit.moments.augmented_gram()  # the logistic probes' first Hessian, up to a constant
    for i, kind in enumerate(kinds):
        if kind == LOGISTIC and settings.family == "fit":
            w[:, :, i], b[:, i] = fit_logistic(
                z, labels[:, i], settings.logistic_l2, settings.newton_steps, gram=gram
            )
    if basis is not None:
        w = basis @ w
    weight = (w / std[:, :, None]).mT.contiguous()  # fold the standardisation in: w.(x - mean)/std + b
    bias = b - torch.einsum("lfd,ld->lf", weight, mean)
    return LinearProbes(weight=weight, bias=bias, mean=mean, std=std, kinds=list(kinds), lam=lam, cv_r2=cv_r2)
