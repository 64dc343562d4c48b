"""Steering inside the forward pass (the paper's Algorithm 2): at every forward through a constrained layer, read the
pooled representation, compute u, and add it at the read-out tokens (`vlactl.models.hooks.intervene`).

Methods: `control`, the minimum-norm controller (one box: closed form; several boxes on one layer: the exact QP);
`alpha`, a fixed push alpha W/||W|| along the first probe of each layer; `direction`, a fixed push alpha d along a
given unit direction per layer (e.g. a mean-difference direction). u is recomputed at every forward, so for a hybrid
it is applied at every re-plan and, on expert layers, at every denoising step. Knows nothing about any model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from vlactl.env.features import action_dimensions
from vlactl.errors import UsageError
from vlactl.models.hooks import intervene
from vlactl.steering.controller import box_control, multi_box_control
from vlactl.steering.probes import Probe

METHODS = ("control", "alpha", "direction")


@dataclass
class Constraint:
    """Keep `probe`'s reading (the logit, for a logistic probe) in [zmin, zmax] at the probe's layer; if `relative`,
    within [zmin, zmax] of its unsteered reading (a hold: the push may move it only that far)."""

    probe: Probe
    zmin: float = -math.inf
    zmax: float = math.inf
    relative: bool = False

    @property
    def layer(self) -> str:
        return self.probe.layer


class Steerer:
    """Context manager: hooks installed on enter, removed on exit. `log` holds one dict per forward, layer,
    constraint pushed there (`box`: its index among the layer's constraints) and batch row: reading before and after,
    ||u||, and whether u was non-zero."""

    def __init__(self, vla, constraints: list[Constraint], method: str = "control", alpha: float = 0.0,
                 directions: dict[str, torch.Tensor] | None = None, pooling: str | None = None):
        """`pooling`: the read-out set pushed; by default the one the probes were fitted at (all must share it)."""
        if method not in METHODS:
            raise UsageError(f"unknown steering method {method!r}; allowed: {', '.join(METHODS)}")
        if not constraints:
            raise UsageError("steering needs at least one constraint")
        pooling = pooling or constraints[0].probe.pooling
        for c in constraints:
            c.probe.check_fits(vla.name, vla.layer_width(c.layer), pooling)
        if method == "direction" and not {c.layer for c in constraints} <= set(directions or {}):
            raise UsageError("method=direction needs a direction for every constrained layer")
        self.vla, self.method, self.alpha, self.pooling = vla, method, float(alpha), pooling
        self.directions = directions or {}
        self.by_layer: dict[str, list[Constraint]] = {}
        for c in constraints:
            self.by_layer.setdefault(c.layer, []).append(c)
        self.log: list[dict] = []
        self._forwards = 0

    def reset_log(self) -> None:
        self.log, self._forwards = [], 0

    def _writing(self, constraints: list[Constraint]) -> list[int]:
        """The indices of `constraints` to push at this forward: at the `action` set of a model that writes one action
        dimension a token, those whose feature is a function of the dimension this forward writes (a push at another
        position of the chunk would change another dimension's token); otherwise all."""
        written = self.vla.written_dimension() if self.pooling == "action" else None
        return [k for k, c in enumerate(constraints)
                if written is None or written in (action_dimensions(c.probe.feature) or (written,))]

    def _u(self, layer: str, x: torch.Tensor) -> torch.Tensor | None:
        active = self._writing(self.by_layer[layer])
        if not active or (self.method != "control" and active[0] != 0):  # a fixed push is along the first probe
            return None
        constraints = [self.by_layer[layer][k] for k in active]
        w = torch.stack([c.probe.weight for c in constraints]).to(torch.float64)
        b = torch.tensor([c.probe.bias for c in constraints], dtype=torch.float64)
        lo = torch.tensor([c.zmin for c in constraints], dtype=torch.float64)
        hi = torch.tensor([c.zmax for c in constraints], dtype=torch.float64)
        if self.method == "control":
            relative = [c.relative for c in constraints]
            u = (box_control(x, w[0], b[0], lo[0], hi[0]) if relative == [False]
                 else multi_box_control(x, w, b, lo, hi, relative=relative)).u
        else:
            d = w[0] / w[0].norm() if self.method == "alpha" else self.directions[layer].double()
            u = (self.alpha * d).to(x.dtype).expand_as(x)
        before = x.double() @ w.mT + b
        after = (x + u).double() @ w.mT + b
        norm = u.double().norm(dim=-1)
        for row in range(x.shape[0]):
            for k, c in enumerate(constraints):
                origin = float(before[row, k]) if c.relative else 0.0  # the log holds every box in reading units
                self.log.append({
                    "forward": self._forwards, "layer": layer, "box": active[k], "feature": c.probe.feature, "row": row,
                    "before": float(before[row, k]), "after": float(after[row, k]),
                    "zmin": origin + c.zmin, "zmax": origin + c.zmax,
                    "u_norm": float(norm[row]), "active": bool(norm[row] > 0),
                })
        self._forwards += 1
        return u

    def __enter__(self) -> "Steerer":
        self._context = intervene(self.vla, list(self.by_layer), self._u, self.pooling)
        self._context.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._context.__exit__(*exc)
