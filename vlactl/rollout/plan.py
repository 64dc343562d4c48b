"""The intervention a rollout runs (`Steering`): the method, the probes it pushes at the layers chosen for each steered
feature, the read-outs it holds, and the demonstration constants its bounds need (speed threshold, metres per action
unit). Probes come from `probes=`, the previous stage's default output, or the ones shipped for the model
(`data/probes/<model>/{steer,observe,stop}`), and are refused for weights other than those they were fitted on."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import DictConfig

from vlactl.config import REPO_ROOT, SHIPPED_PROBES, resolve_path, stage_output
from vlactl.errors import UsageError, check_choice
from vlactl.rollout.agents import SCRIPTED
from vlactl.rollout.constrained import METHODS, STEERING, Steering
from vlactl.rollout.constraints import (BOXES, KINDS, STOP_READOUTS, Bounds, as_constraints, constraint_name,
                                       held_by_default, pausable)

if TYPE_CHECKING:
    import pandas as pd


def steering(cfg: DictConfig, constraint) -> Steering:
    """The run's intervention: method, and for control/alpha the probes of the constraint's feature at the chosen
    layers (by default the most controllable layer or group, else the best observable layer, of the probe run).
    `constraint`: a Constraint, or several (control with box=action, filter, prompt and none): each steered by the
    probes of its own action read-out at the layers chosen for that feature."""
    import pandas as pd

    from vlactl.steering.controllability import controllability_rows
    from vlactl.steering.train_probes import METRICS_NAME

    check_choice("method", cfg.method, METHODS)
    check_choice("box", cfg.box, BOXES)
    constraints = as_constraints(constraint)
    if cfg.method != "none" and not constraints:
        raise UsageError(f"method={cfg.method} needs a constraint, e.g. constraint=gripper=open")
    one_only = cfg.method in ("alpha", "meandiff") or (cfg.method == "control" and cfg.box == "state")
    if len(constraints) > 1 and one_only:
        what = "box=state" if cfg.method == "control" else f"method={cfg.method}"
        raise UsageError(f"{what} takes one constraint, not {len(constraints)} (constraint={constraint_name(constraints)}"
                         f"); several at once: method=control with box=action, filter, prompt or none")
    if cfg.method != "none" and cfg.model == SCRIPTED:
        raise UsageError(f"method={cfg.method} needs a VLA; the scripted expert takes no instruction or steering")
    if cfg.hold and cfg.method != "control":
        raise UsageError(f"hold={list(cfg.hold)} needs method=control, not {cfg.method!r}")
    bounds_actions = cfg.method == "filter" or controls_actions(cfg)
    if bounds_actions and int(cfg.passes) < 1:
        raise UsageError(f"passes must be >= 1, got {cfg.passes}")
    if bounds_actions and not 0 < float(cfg.barrier_decay) <= 1:
        raise UsageError(f"barrier_decay must be in (0, 1], got {cfg.barrier_decay}")
    if bounds_actions and not 0 <= float(cfg.height_margin) <= 0.1:
        raise UsageError(f"height_margin must be in [0, 0.1] m, got {cfg.height_margin}")
    if bounds_actions and not 0 <= float(cfg.speed_margin) < 1:
        raise UsageError(f"speed_margin must be in [0, 1) (a share of the speed threshold), got {cfg.speed_margin}")
    if cfg.pause:
        _check_pause(cfg, constraints)
    if cfg.stop_probes is not None and not (cfg.pause and controls_actions(cfg)):
        raise UsageError(f"stop_probes={cfg.stop_probes} needs pause=true with method=control (box=action)")
    run = probes_run(cfg) if cfg.method in STEERING else None
    stop_run = stop_probes_run(cfg, run) if cfg.pause and run is not None else run
    sources = tuple(dict.fromkeys((run, stop_run))) if run is not None else ()  # one run unless the stop has its own
    for source in sources:
        _check_probe_weights(source, str(cfg.model))
    threshold = scale = 0.0
    features = {c.feature for c in constraints}
    if "speed" in features:
        threshold = demo_constant(cfg, "speed_threshold", run)
    if bounds_actions and features - {"gripper"}:
        scale = demo_constant(cfg, "metres_per_unit", run)
        if scale <= 0:
            raise UsageError(f"metres_per_unit must be > 0, got {scale}")
    probes = holds = ()
    if run is not None:
        tables = {source: pd.read_parquet(source / METRICS_NAME) for source in sources}
        # each steered feature's probes at the layers chosen for it (height and speed share dz's); under pause the
        # stop's read-outs (height's dz among them) from the stop probes
        stop_features = set(tables[stop_run]["feature"])
        present = set(tables[run]["feature"]) | stop_features
        steered = (f for c in constraints for f in steered_features(c, cfg.box, cfg.method, cfg.pause, present))
        for feature in dict.fromkeys(steered):
            source = stop_run if feature in STOP_READOUTS and feature in stop_features else run
            control = controllability_rows(source, feature) if cfg.layers is None else None
            layers = _steered_layers(cfg.layers, tables[source][tables[source]["feature"] == feature], control)
            if cfg.layers is None and control is None:  # the most observable layer is seldom the most controllable
                print(f"note: {source} has no controllability rows for {feature}: steering it at its best observable "
                      f"layer {', '.join(layers)}; `vlactl controllability probes={source} features=[{feature}]` "
                      "measures where a push reaches the actions", file=sys.stderr)
            probes += _load_probes(source, layers, feature, str(source))
        holds = _hold_probes(cfg, constraints, run, probes)
        readouts = sorted({p.pooling for p in probes + holds})
        if len(readouts) > 1:
            raise UsageError(f"one push reads one read-out set, and the probes of {', '.join(map(str, sources))} "
                             f"read {' and '.join(readouts)}: fit them on activations of one pooling")
    meandiff = cfg.method == "meandiff"
    directions = mean_difference_directions(cfg, constraints[0], [p.layer for p in probes]) if meandiff else None
    bounds = Bounds(speed_threshold=threshold, metres_per_unit=scale, decay=float(cfg.barrier_decay),
                    height_margin=float(cfg.height_margin), speed_margin=float(cfg.speed_margin))
    return Steering(cfg.method, probes, directions, alpha=float(cfg.alpha), logit_margin=float(cfg.logit_margin),
                    bounds=bounds, holds=holds, hold_tolerance=float(cfg.hold_tolerance), box=str(cfg.box),
                    passes=int(cfg.passes), pause=bool(cfg.pause))


def _check_pause(cfg: DictConfig, constraints: tuple) -> None:
    """pause stops the arm where a constraint binds: on the executed action (method=filter) or by a push on the
    translation and rotation read-outs (method=control, box=action); it needs a constraint a still arm satisfies (height,
    speed=low), and none a still arm breaks (speed=high)."""
    name = constraint_name(constraints)
    if cfg.method not in ("filter", "control") or (cfg.method == "control" and cfg.box != "action"):
        what = f"method={cfg.method}" + (f" with box={cfg.box}" if cfg.method == "control" else "")
        raise UsageError(f"pause=true needs method=filter or method=control with box=action, not {what}")
    if not any(pausable(c) for c in constraints):
        raise UsageError(f"pause=true stops the arm, which no constraint in constraint={name} asks for; it takes "
                         f"height=low|high or speed=low")
    if any(c.name == "speed=high" for c in constraints):
        raise UsageError(f"pause=true cannot go with speed=high (constraint={name}): a stopped arm is not fast")


def steered_features(constraint, box: str, method: str, pause: bool = False, present=None) -> tuple[str, ...]:
    """The probe features a constraint's push moves: for control, read-outs of the action (box=action) or of the
    state (box=state), with `pause` for a pausable constraint also the read-outs that stop the arm (`STOP_READOUTS`:
    the translation, and yaw if it is among `present`, the probe runs' features, if given); the fixed pushes (alpha,
    meandiff) push along one probe: with box=action the read-out of the constrained quantity."""
    if box == "state":
        return (constraint.probe_feature,)
    if method != "control":
        return (constraint.quantity_feature,)
    translation = KINDS["speed"][3]
    stop = tuple(f for f in STOP_READOUTS if f in translation or present is None or f in present) \
        if pause and pausable(constraint) else ()
    return tuple(dict.fromkeys(constraint.action_features + stop))


def probes_run(cfg: DictConfig) -> Path:
    """`probes=`, or by default the previous stage's default output (`vlactl train-probes` after `vlactl collect`:
    outputs/probes/<model>_libero_spatial_prefix) if there is one, else the probes shipped for the model:
    `data/probes/<model>/steer` (strongly regularised, for control on the actions, alpha and meandiff) or
    `.../observe` (the observability probes, for box=state)."""
    from vlactl.steering.train_probes import METRICS_NAME

    if cfg.probes is not None:
        return stage_output(cfg.probes, METRICS_NAME, "probe run", "vlactl train-probes")
    name = Path(str(cfg.model)).name
    family = "observe" if cfg.method == "control" and cfg.box == "state" else "steer"
    for run in (REPO_ROOT / "outputs" / "probes" / f"{name}_libero_spatial_prefix", SHIPPED_PROBES / name / family):
        if (run / METRICS_NAME).is_file():
            print(f"probes: {run}", file=sys.stderr)
            return run
    raise UsageError(f"method={cfg.method} needs probes=<probe run folder from `vlactl train-probes`>; none ship "
                     f"for model {cfg.model!r} (shipped: {', '.join(shipped_probe_models()) or 'none'})")


def stop_probes_run(cfg: DictConfig, run: Path) -> Path:
    """pause with control: the probe run the stop's read-outs (`STOP_READOUTS`) come from: `stop_probes=`, else, when
    the steering probes are the shipped ones, the stop probes shipped beside them (`data/probes/<model>/stop`: fitted
    with the other action features regressed out, so that stopping the translation does not tilt the hand;
    docs/steering.md), else the steering probe run itself."""
    from vlactl.steering.train_probes import METRICS_NAME

    if cfg.stop_probes is not None:
        return stage_output(cfg.stop_probes, METRICS_NAME, "probe run", "vlactl train-probes family=partial")
    shipped = run.parent / "stop"
    if run.parent.parent == SHIPPED_PROBES and (shipped / METRICS_NAME).is_file():
        print(f"stop probes: {shipped}", file=sys.stderr)
        return shipped
    return run


def _check_probe_weights(run: Path, model: str) -> None:
    """Probes fitted on other weights of the same model name (a retrained checkpoint) read nothing: refused."""
    from vlactl.models.registry import weights_fingerprint

    provenance = probe_provenance(run)
    fitted = provenance.get("weights")
    current = weights_fingerprint(model) if fitted else None
    if fitted and current and fitted != current:
        raise UsageError(f"the probes in {str(run)!r} were fitted on {provenance.get('model', '?')!r} (weights "
                         f"{fitted}), not on model={model} (weights {current}); refit them (`make probes`, or collect + "
                         f"train-probes)")


def probe_provenance(run: Path | None) -> dict:
    """What `vlactl train-probes` recorded about a probe run (model, weights, demo constants); {} if nothing."""
    import json

    from vlactl.steering.train_probes import PROBE_PROVENANCE

    recorded = run / PROBE_PROVENANCE if run is not None else None
    return json.loads(recorded.read_text()) if recorded is not None and recorded.is_file() else {}


def shipped_probe_models() -> list[str]:
    return sorted(p.name for p in SHIPPED_PROBES.glob("*") if p.is_dir())


def demo_constant(cfg: DictConfig, key: str, run: Path | None) -> float:
    """speed_threshold / metres_per_unit: as given, else measured from `demos` when it is on disk, else the value the
    probe run (without one, as for none, prompt and filter: the probes shipped for the model) recorded from its own
    demonstrations (vlactl.data.motion)."""
    from vlactl.data import motion

    if cfg[key] is not None:
        return float(cfg[key])
    demos = resolve_path(cfg.demos)
    if (demos / "meta").is_dir():
        return motion.speed_median(demos) if key == "speed_threshold" else motion.metres_per_unit(demos)
    recorded = probe_provenance(run if run is not None else SHIPPED_PROBES / Path(str(cfg.model)).name / "steer")
    if key in recorded:
        return float(recorded[key])
    raise UsageError(f"{key} is measured from the demonstrations, and demos={cfg.demos!r} is no demonstration set; "
                     f"make it with `vlactl demos` (about 50 min on 2 cores) or give {key}=...")


def _load_probes(run: Path, layers: list[str], feature: str, source: str, hint: str = "") -> tuple:
    """The probes of one feature at these layers from a probe run folder; a missing one is a one-line UsageError."""
    from vlactl.steering.probe_file import load_probe
    from vlactl.steering.train_probes import probe_filename

    missing = [layer for layer in layers if not (run / "probes" / probe_filename(layer, feature)).is_file()]
    if missing or not layers:
        where = f" for layer {missing[0]}" if missing else ""
        hint = hint or ("; train it with `vlactl train-probes features=[...]` (box=action steers dx, dy, dz and "
                        "gripper_action)")
        raise UsageError(f"no probe of {feature!r}{where} in {source!r}{hint}")
    return tuple(load_probe(run / "probes" / probe_filename(layer, feature)) for layer in layers)


def _hold_probes(cfg: DictConfig, constraint, run: Path, steered: tuple) -> tuple:
    """`hold=[dx, dy, dz]`: on every steered layer (those of the `steered` probes), the probes of those features,
    whose readings the controller keeps within hold_tolerance of their unsteered values (the controller's multi-box QP
    with relative boxes)."""
    from collections import Counter

    from vlactl.steering.activations import FEATURES
    from vlactl.steering.controller import MAX_PROBES

    constraints = as_constraints(constraint)
    pushed = {p.feature for p in steered} | {c.quantity_feature for c in constraints}  # a hold would fight the push
    if float(cfg.hold_tolerance) < 0:
        raise UsageError(f"hold_tolerance must be >= 0, got {cfg.hold_tolerance}")
    # the controller enumerates the active sets of the boxes wider than one value (MAX_PROBES a layer): box=action
    # pushes each probe to one reading, a hold with no tolerance keeps one; those cost nothing
    beside = 0 if controls_actions(cfg) else max(Counter(p.layer for p in steered).values(), default=1)
    room = MAX_PROBES - beside if float(cfg.hold_tolerance) > 0 else None
    if cfg.hold is None:  # the defaults: those not pushed, as many as the controller has room for
        features = [f for f in default_holds(cfg, constraints, run) if f not in pushed][:room]
    else:
        features = list(dict.fromkeys(cfg.hold))
    if not features:
        return ()
    allowed = [f for f in FEATURES if f not in pushed]
    for feature in features:
        check_choice("hold feature", feature, allowed)
    if room is not None and len(features) > room:
        raise UsageError(f"hold={features} with hold_tolerance={cfg.hold_tolerance}: at most {room} features can be "
                         f"held (the controller solves at most {MAX_PROBES} boxes wider than one value a layer, "
                         f"{beside} of them the constraint's; hold_tolerance=0 holds any number)")
    hint = "; train it with `vlactl train-probes features=[...]` on the same activations"
    layers = list(dict.fromkeys(p.layer for p in steered))
    return tuple(p for feature in features for p in _load_probes(run, layers, feature, str(run), hint))


def controls_actions(cfg: DictConfig) -> bool:
    """Control on the actions (box=action): each re-plan's push sets every steered probe to one reading."""
    return cfg.method == "control" and cfg.box == "action"


def default_holds(cfg: DictConfig, constraint, run: Path) -> list[str]:
    """hold=null: under control on the actions, the action read-outs the constraints should leave alone (for one,
    `Constraint.holds`; for several, those every one of them holds, less the features they steer:
    `held_by_default`) that the probe run has, of the same family as the steered probes (a push that changes dz must
    leave the gripper, dx and dy where they were; FACTS, 2026-12-01); else none."""
    import pandas as pd

    from vlactl.steering.train_probes import METRICS_NAME

    if not controls_actions(cfg):
        return []
    present = set(pd.read_parquet(run / METRICS_NAME, columns=["feature"])["feature"])
    return [f for f in held_by_default(constraint) if f in present]


def _steered_layers(chosen, table: pd.DataFrame, control: pd.DataFrame | None = None) -> list[str]:
    """`layers=`: a list of layer names; a group (`backbone`, `expert`: its every steerable layer that has a probe);
    or null: the layer or group whose push moves the predicted action most (`control`, the feature's rows of the probe
    run's `vlactl controllability` table), else (no table, or nothing moved) the best observable steerable layer."""
    from vlactl.steering.controllability import group_layers, most_controllable
    from vlactl.steering.train_probes import best_layers

    if chosen is None:
        chosen = most_controllable(control) if control is not None else None
        if chosen is None:
            return list(best_layers(table, steerable=True)["layer"])
    if isinstance(chosen, str):
        return group_layers(table, chosen) or [chosen]
    return list(chosen)


SIGNED = ("gripper_action", "dz")  # commands whose sign is the side (close / rise), not their median


def mean_difference_directions(cfg: DictConfig, constraint, layers: list[str]) -> dict:
    """Per layer, the unit difference of the activation means of frames on the 'closed / high' side of the feature the
    push is along (`steered_features`: with box=action the commanded gripper, dz or speed; with box=state the state
    z or speed) and those on the other side: a command above 0 for the gripper and dz, else above its median in the
    activations. (Split on the state z, the frames where the hand is low are those after the grasp, where it rises:
    a push towards them under height=low raised the hand.)"""
    import torch

    from vlactl.steering.activations import ActivationStore
    from vlactl.steering.controller import mean_difference

    if cfg.activations is None:
        raise UsageError("method=meandiff needs activations=<activation folder from `vlactl collect`>")
    store = ActivationStore(resolve_path(cfg.activations))
    (feature,) = steered_features(constraint, cfg.box, cfg.method)
    values = store.labels[feature].to_numpy(dtype=float)
    upper = values > (0.0 if feature in SIGNED else np.median(values))
    return {layer: mean_difference(store.load([layer])[0], torch.as_tensor(upper)).float() for layer in layers}
