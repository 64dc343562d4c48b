"""What a client and the server say to each other, beyond the frames (`wire`): the metadata the server sends on
connect, the observation a request carries, and a run's steering as plain maps and arrays.

Requests (maps with string keys):
- `{"obs": {"images": {camera: uint8 [H, W, 3]}, "state": float32 [8], "instruction": str}, "reset": bool}` ->
  `{"actions": float32 [chunk_size, 7], "server_timing": {...}}`. `reset` starts an episode: its noise stream
  restarts as `VLA.reset(seed)` restarts it in process, from the episode's `seed` (an optional int beside `reset`),
  so the same seeds give the same actions.
- openpi's LIBERO keys are taken too: `observation/image`, `observation/wrist_image`, `observation/state`, `prompt`.
- `{"steer": {...}}` once after connect (`encode_steer`): every episode of this connection is then run in the server
  by a `ConstrainedAgent`, one request at a time, each request one step (`obs` also carries `robot_state`, the
  SPEC.md §2 state the boxes are set from) -> `{"actions": [1, 7], "reading": {...} or None}`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, fields

import numpy as np

from vlactl.errors import UsageError

OPENPI_KEYS = {"observation/image": "image", "observation/wrist_image": "wrist_image"}


def metadata(vla, model: str) -> dict:
    widths = {}
    for layer in vla.layer_names():
        try:
            widths[layer] = int(vla.layer_width(layer))
        except NotImplementedError:  # an adapter that cannot say: its probes are refused by name and layer only
            pass
    return {"model": model, "name": vla.name, "chunk_size": int(vla.chunk_size),
            "replan_every": int(vla.replan_every), "needs_images": bool(vla.needs_images),
            "gripper_levels": list(vla.gripper_levels) if vla.gripper_levels else None,
            "cameras": list(vla.cameras), "layer_widths": widths, "env_preset": getattr(vla, "env_preset", None)}


def observation(request: dict, cameras, needs_images: bool) -> dict:
    """The request's observation, checked: {"images", "state", "instruction", "robot_state"}; BadRequest if not."""
    if "observation/state" in request:  # an openpi-style client
        obs = {"images": {name: request[key] for key, name in OPENPI_KEYS.items() if key in request},
               "state": request["observation/state"], "instruction": request.get("prompt", "")}
    elif isinstance(request.get("obs"), dict):
        obs = request["obs"]
    else:
        raise BadRequest(f"a request needs 'obs' (or openpi's 'observation/state'); got keys {sorted(map(str, request))}")
    state = np.asarray(obs.get("state"))
    if state.shape != (8,) or state.dtype.kind != "f":
        raise BadRequest(f"obs.state must be 8 floats (the LIBERO state), got shape {state.shape} {state.dtype}")
    if not isinstance(obs.get("instruction"), str):
        raise BadRequest("obs.instruction must be a string")
    images = obs.get("images") or {}
    if needs_images:
        for camera in cameras:
            image = images.get(camera)
            if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
                raise BadRequest(f"obs.images[{camera!r}] must be uint8 [H, W, 3]")
    robot = obs.get("robot_state")
    return {"images": {c: np.array(images[c]) for c in cameras if c in images} if needs_images else {},  # writable
            "state": state.astype(np.float32), "instruction": obs["instruction"],
            "robot_state": None if robot is None else np.asarray(robot, dtype=np.float64)}


def episode_seed(request: dict) -> int | None:
    """The seed an episode-starting request gives its noise (`seed`, optional); BadRequest if it is not an int."""
    seed = request.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise BadRequest(f"seed must be an integer, got {seed!r}")
    return seed


class BadRequest(ValueError):
    """A request the server cannot read; it answers with one line and closes that connection."""


def _probe(probe) -> dict:
    return {"feature": probe.feature, "kind": probe.kind, "layer": probe.layer, "model": probe.model,
            "pooling": probe.pooling, "weight": probe.weight.double().numpy(), "bias": float(probe.bias),
            "mean": probe.mean.double().numpy(), "std": probe.std.double().numpy(), "positive": probe.positive,
            "metrics": json.dumps(probe.metrics)}


def _unprobe(d: dict):
    import torch

    from vlactl.steering.probes import Probe

    tensors = {k: torch.from_numpy(np.array(d[k], dtype=np.float64)) for k in ("weight", "mean", "std")}
    return Probe(feature=d["feature"], kind=d["kind"], layer=d["layer"], model=d["model"], pooling=d["pooling"],
                 bias=float(d["bias"]), positive=d["positive"], metrics=json.loads(d["metrics"]), **tensors)


def encode_steer(constraint: str, window, steering, replan_every, snap_gripper: bool) -> dict:
    """A run's constraint (one, or several: `height=high,speed=low`) and `Steering` as a map: every field, probes
    and directions as arrays."""
    plan = {}
    for f in fields(steering):
        value = getattr(steering, f.name)
        if f.name in ("probes", "holds"):
            value = [_probe(p) for p in value]
        elif f.name == "directions" and value is not None:
            value = {layer: d.double().numpy() for layer, d in value.items()}
        elif f.name == "bounds":
            value = asdict(value)
        plan[f.name] = value
    return {"constraint": constraint, "window": window, "steering": plan, "replan_every": replan_every,
            "snap_gripper": snap_gripper}


def decode_steer(message: dict):
    """(constraints, Steering, replan_every, snap_gripper) from `encode_steer`'s map (constraints: a tuple, one or
    several); UsageError if it is not one."""
    import torch

    from vlactl.rollout.constrained import Steering
    from vlactl.rollout.constraints import Bounds, parse_constraints

    try:
        plan = dict(message["steering"])
        plan["probes"] = tuple(_unprobe(p) for p in plan["probes"])
        plan["holds"] = tuple(_unprobe(p) for p in plan["holds"])
        plan["bounds"] = Bounds(**plan["bounds"])
        if plan.get("directions") is not None:
            plan["directions"] = {k: torch.from_numpy(np.array(v)).float() for k, v in plan["directions"].items()}
        steering = Steering(**plan)
        constraint = parse_constraints(message["constraint"], message["window"])
        return constraint, steering, message["replan_every"], bool(message["snap_gripper"])
    except (KeyError, TypeError, ValueError) as exc:  # another vlactl version's fields, or no steering map at all
        raise UsageError(f"unreadable steering settings ({type(exc).__name__}: {exc}); are the client's and the "
                         f"server's vlactl the same version?") from None
