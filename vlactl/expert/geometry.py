"""Object geometry the expert needs, measured in the simulator: collision-geometry extents in the object's frame."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np

MESH, BOX, CYLINDER, SPHERE, CAPSULE = 7, 6, 5, 2, 3


@dataclass(frozen=True)
class ObjectShape:
    lo: np.ndarray  # (3,) min corner of the collision geometry, object body frame
    hi: np.ndarray  # (3,) max corner, object body frame

    @property
    def half_extent(self) -> np.ndarray:
        return (self.hi - self.lo) / 2

    @property
    def center(self) -> np.ndarray:
        return (self.hi + self.lo) / 2


def object_body(model, name: str) -> int:
    """LIBERO objects are `<name>_main` bodies; fixtures fall back to the plain name."""
    for candidate in (f"{name}_main", name):
        try:
            return model.body_name2id(candidate)
        except ValueError:
            continue
    raise KeyError(name)


def _in_tree(model, body: int, root: int) -> bool:
    while body != root and body > 0:
        body = model.body_parentid[body]
    return body == root


def _geom_points(model, data, g: int) -> np.ndarray:
    """Points bounding geom g, in world coordinates."""
    size = np.asarray(model.geom_size[g])
    kind = model.geom_type[g]
    if kind == MESH:
        adr, num = model.mesh_vertadr[model.geom_dataid[g]], model.mesh_vertnum[model.geom_dataid[g]]
        local = np.asarray(model.mesh_vert[adr : adr + num])
    else:
        half = {BOX: size, CYLINDER: [size[0], size[0], size[1]], SPHERE: [size[0]] * 3,
                CAPSULE: [size[0], size[0], size[1] + size[0]]}.get(kind, [0.0, 0.0, 0.0])
        local = np.array(list(product(*[(-h, h) for h in half])))
    xmat = np.asarray(data.geom_xmat[g]).reshape(3, 3)
    return np.asarray(data.geom_xpos[g]) + local @ xmat.T


def object_shape(model, data, name: str) -> ObjectShape:
    """Bounding box of the object's collision geometry in its own body frame."""
    root = object_body(model, name)
    points = [
        _geom_points(model, data, g)
        for g in range(model.ngeom)
        if _in_tree(model, model.geom_bodyid[g], root) and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]
    pts = np.concatenate(points)
    rot = np.asarray(data.xmat[root]).reshape(3, 3)
    local = (pts - np.asarray(data.xpos[root])) @ rot
    return ObjectShape(lo=local.min(axis=0), hi=local.max(axis=0))


def obstacle_boxes(model, data, exclude_roots: list[int]) -> np.ndarray:
    """World axis-aligned boxes [n, 2, 3] of every collision geom outside the robot, the table and `exclude_roots`."""
    boxes = []
    for g in range(model.ngeom):
        if not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        body = model.geom_bodyid[g]
        name = model.body_id2name(body) or ""
        if body == 0 or name.startswith(("robot", "gripper", "mount", "table", "floor")) or "table" in name:
            continue
        if any(_in_tree(model, body, root) for root in exclude_roots):
            continue
        pts = _geom_points(model, data, g)
        boxes.append((pts.min(axis=0), pts.max(axis=0)))
    return np.array(boxes).reshape(-1, 2, 3)


def clearance(points: np.ndarray, boxes: np.ndarray, saturate: float = 0.05) -> float:
    """Mean over points [m, 3] of the distance to the nearest box [n, 2, 3], capped at `saturate`.

    A soft score rather than the minimum, so that when every option touches something, the one touching least wins.
    """
    if len(boxes) == 0:
        return saturate
    gap = np.maximum(boxes[None, :, 0] - points[:, None], 0) + np.maximum(points[:, None] - boxes[None, :, 1], 0)
    return float(np.minimum(np.linalg.norm(gap, axis=-1).min(axis=1), saturate).mean())
