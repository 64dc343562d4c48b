"""`vlactl rollout`: closed-loop evaluation of a policy on a LIBERO suite, in worker processes, resumable.

Protocol (SPEC.md §3): episode k of a task starts from the suite's fixed init state k mod 50 with seed `seed + k`,
settles with no-op steps (LiberoEnv), then runs at most the suite's step limit (220 on libero_spatial), re-planning
action chunks every `replan_every` actions; success is LIBERO's own check and ends the episode. Images are rendered
only when the policy needs them or videos are asked for.

Outputs in `<output_root>/<run_name>/`: episodes.parquet, steps.parquet, summary.json, config.yaml, videos/.
Finished episodes live in parts/ (see `parts`); re-running the same command skips them and rebuilds the tables.
"""

from __future__ import annotations

import multiprocessing as mp
import sys
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict
from tqdm import tqdm

from vlactl.config import REPO_ROOT, load_policy_stage_config, quote_values, resolve_path, save_config, stage_output
from vlactl.env.perturbations import parse_perturbation
from vlactl.errors import UsageError, check_choice, check_non_negative, check_positive
from vlactl.io import atomic_write_json, atomic_write_parquet, ensure_writable_dir, folder_name
from vlactl.rollout import parts, shards
from vlactl.rollout.agents import SCRIPTED, load_agent
from vlactl.rollout.constrained import METHODS, STEERING, Steering, method_label
from vlactl.rollout.constraints import (BOXES, KINDS, START_GRIPPER, STOP_READOUTS, Bounds, as_constraints,
                                       constraint_name, held_by_default, parse_constraints, pausable, start_gripper)
from vlactl.rollout.summary import format_summary, summarise_file
from vlactl.rollout.workers import Batch, RunSpec, init_worker, run_batch

# Settings that change what an episode is: parts made under other values must not be mixed into this run.
SAME_RUN_KEYS = ("model", "model_inference", "suite", "seed", "max_steps", "replan_every", "snap_gripper", "env",
                 "constraint", "window", "method", "start_gripper", "hold", "hold_tolerance", "barrier_decay", "perturb",
                 "perturb_start", "perturb_steps", "perturb_size", "box", "passes", "height_margin", "pause",
                 "episode_noise", "speed_margin")
JUDGED_METHODS = ("none", "prompt")  # what judge_from can stand in for
SHIPPED_PROBES = REPO_ROOT / "data" / "probes"  # data/probes/<model>/{steer,observe,stop}: `make probes` rebuilds them
# what runs saved before a key existed did
BEFORE_KEY = {"start_gripper": "open", "hold": [], "hold_tolerance": 0.0, "snap_gripper": False, "barrier_decay": 0.5,
              "perturb": "none", "perturb_start": 0, "perturb_steps": 15, "perturb_size": None,
              "box": "state", "passes": 3, "height_margin": 0.0, "pause": False, "episode_noise": False,
              "model_inference": None,  # None: not recorded, not compared (runs before 2026-12-02 evening)
              "speed_margin": 0.1}


def rollout_config(overrides: list[str] | None = None) -> DictConfig:
    """The rollout config; `model` is a registry name, a checkpoint path, or `scripted`. `constraint=gripper=open`
    and `constraint=[height=high,speed=low]` are taken as written (Hydra would need the value quoted); several
    constraints are saved in one canonical form, `height=high,speed=low` (KINDS order), and a bad list is a one-line
    error here, before any run starts."""
    cfg = load_policy_stage_config("rollout", quote_values(overrides, "constraint"))
    canonical_constraint(cfg)
    return cfg


def canonical_constraint(cfg: DictConfig) -> tuple:
    """The run's constraints (`parse_constraints`), with `cfg.constraint` rewritten in their canonical form."""
    constraints = parse_constraints(cfg.constraint, cfg.window)
    if constraints:
        cfg.constraint = constraint_name(constraints)
    return constraints


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
    import sys

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
    import sys

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


def run_rollout(cfg: DictConfig, load_policy=None) -> dict:
    """Run (or resume) the rollout `cfg` describes; returns the summary. `load_policy` replaces the model registry."""
    from vlactl.env.libero_env import check_env_config
    from vlactl.env.suites import MAX_STEPS, SUITES, resolve_tasks

    if OmegaConf.is_missing(cfg, "model"):
        raise UsageError("model is required: model=<registry name or checkpoint path>, e.g. model=scripted")
    shards.check(cfg.shard, cfg.num_shards)
    registry_loaded = load_policy is None
    if load_policy is None:
        from vlactl.models.registry import policy_loader

        load_policy = policy_loader(cfg)
    check_choice("suite", cfg.suite, SUITES)
    check_non_negative("episodes_per_task", cfg.episodes_per_task)
    check_non_negative("first_episode", cfg.first_episode)
    check_positive("workers", cfg.workers)
    cfg.max_steps = MAX_STEPS[cfg.suite] if cfg.max_steps is None else cfg.max_steps
    check_positive("max_steps", cfg.max_steps)
    env = OmegaConf.to_container(cfg.env, resolve=True)
    check_env_config(env)
    tasks = resolve_tasks(cfg.suite, cfg.tasks)
    constraint = canonical_constraint(cfg)  # the run's constraints, one or several
    check_choice("start_gripper", cfg.start_gripper, START_GRIPPER)
    resolve_defaults(cfg)
    plan = steering(cfg, constraint)
    perturbation = parse_perturbation(cfg.perturb, cfg.perturb_start, cfg.perturb_steps, cfg.perturb_size, cfg.max_steps)
    cfg.start_gripper = gripper = start_gripper(cfg.start_gripper, constraint, cfg.method)  # saved resolved
    if registry_loaded:
        record_model_inference(cfg)
    out = run_dir(cfg)
    where = shards.folder(out, cfg.shard, cfg.num_shards)  # a shard writes only into a folder of its own
    for folder in dict.fromkeys([out, where, *shards.folders(out)]):  # all hold episodes of this one run
        _check_same_run(cfg, folder)

    # Load once here, before any worker starts: a bad model name fails in one line, and we learn its settings.
    if cfg.policy:  # the model runs in a `vlactl serve` process; the workers are its clients
        from vlactl.serve.client import served_agent

        agent = served_agent(cfg)
    else:
        agent = load_agent(str(cfg.model), cfg.replan_every, load_policy, bool(cfg.snap_gripper))
    from vlactl.render_presets import warn_if_rendered_otherwise
    warn_if_rendered_otherwise(str(cfg.model), getattr(agent, "vla", None), env)
    for probe in plan.probes + plan.holds:  # here, not in a worker after its start-up; rollouts steer at "prefix"
        probe.check_fits(agent.vla.name, agent.vla.layer_width(probe.layer), "prefix")
    policy = {"needs_images": agent.needs_images, "chunk_size": agent.chunk_size, "replan_every": agent.replan_every,
              "gripper_levels": None if agent.gripper_levels is None else agent.gripper_levels.tolist()}
    if cfg.judge_from and perturbation is not None:
        raise UsageError(f"judge_from=... judges unperturbed episodes; drop it with perturb={cfg.perturb}")
    source = (judge_source(cfg, constraint, gripper, tasks, getattr(agent, "vla", None)) if cfg.judge_from
              else None)  # checked before anything is written
    del agent
    ensure_writable_dir(where)
    save_config(cfg, where)

    keys = episode_keys(cfg, tasks)
    if where == out:  # the whole run takes over the episodes its shards finished
        shards.adopt(out, shards.sources(out, keys, shards.folders(out)))
        mine = keys
    else:  # the shard's slice, less what the run folder already has (merged, or run in one process)
        mine = [key for key in shards.slice_of(keys, cfg.shard, cfg.num_shards) if not parts.is_done(out, *key)]
    todo = [key for key in mine if not parts.is_done(where, *key)]
    spec = RunSpec(
        out=str(where), suite=cfg.suite, model=str(cfg.model), seed=cfg.seed, max_steps=cfg.max_steps,
        replan_every=cfg.replan_every, snap_gripper=bool(cfg.snap_gripper), video=bool(cfg.video),
        env=env, load_policy=load_policy, constraint=str(cfg.constraint),
        window=cfg.window, steering=plan, start_gripper=gripper, perturbation=perturbation, policy=cfg.policy,
        episode_noise=bool(cfg.episode_noise),
    )
    if source is not None:
        judge_run(cfg, constraint, plan, todo, where, source)
    else:
        _run_workers(spec, batches(todo, cfg.workers), where, mine, cfg.workers)

    head = {"suite": cfg.suite, "model": str(cfg.model), "policy": policy, "constraint": str(cfg.constraint),
            "method": cfg.method, "start_gripper": gripper,
            "steered_layers": list(dict.fromkeys(p.layer for p in plan.probes)),
            "held": sorted({p.feature for p in plan.holds}), "pause": plan.pause,
            "episode_noise": bool(cfg.episode_noise), "perturbation": perturbation.name if perturbation else "none"}
    if len(constraint) > 1:  # each constraint with its window and layers; _write_tables adds its satisfaction
        head["constraints"] = {c.name: {"window": c.window, "steered_layers": [
            p.layer for p in plan.probes if p.feature in steered_features(c, cfg.box, cfg.method, cfg.pause)]}
            for c in constraint}
    summary = _write_tables(where, mine, head)
    if where != out:  # the last shard to finish merges; the others say what the run still lacks
        try:
            merge_run(cfg, head)
        except shards.Incomplete as exc:
            print(f"not merged yet: {exc}")
    return summary


def episode_keys(cfg: DictConfig, tasks: list[int]) -> list[tuple[int, int]]:
    """The run's (task, episode) pairs: episodes first_episode.. of each task, so a run can start where another's
    initial states end (DAgger stops on init states 10-24 leave the 10 x 10 evaluations' 0-9 alone)."""
    first = cfg.first_episode
    return [(t, k) for t in tasks for k in range(first, first + cfg.episodes_per_task)]


def merge_run(cfg: DictConfig, head: dict | None = None) -> dict:
    """`vlactl rollout merge <the run's overrides>`, and the last shard to finish: the run folder as the run in one
    process would have written it, from the parts its shards finished, running no episode. Unless every episode of
    the run is finished somewhere, it writes nothing and raises `shards.Incomplete` naming the missing ones. `head`:
    the summary's run fields; by default those a shard saved."""
    import json

    from vlactl.env.suites import MAX_STEPS, SUITES, resolve_tasks

    if OmegaConf.is_missing(cfg, "model"):
        raise UsageError("merge needs the run's overrides, model=... included, as its shards were given")
    check_choice("suite", cfg.suite, SUITES)
    cfg.max_steps = MAX_STEPS[cfg.suite] if cfg.max_steps is None else cfg.max_steps  # resolved as the shards saved
    resolve_defaults(cfg)
    cfg.start_gripper = start_gripper(cfg.start_gripper, canonical_constraint(cfg), cfg.method)
    record_model_inference(cfg)
    out = run_dir(cfg)
    folders = shards.folders(out)
    for folder in [out, *folders]:
        _check_same_run(cfg, folder)
    keys = episode_keys(cfg, resolve_tasks(cfg.suite, cfg.tasks))
    found = shards.sources(out, keys, folders)
    missing = [key for key, source in found.items() if source is None]
    if missing:
        raise shards.Incomplete(shards.missing_line(out, keys, missing))
    if head is None:
        saved = [f / "summary.json" for f in [out, *folders] if (f / "summary.json").is_file()]
        if not saved:
            raise UsageError(f"no shard of {out} has finished (no summary.json); re-run one with the same command")
        head = json.loads(saved[0].read_text())  # its episode statistics are replaced by the run's below
    shards.adopt(out, found)
    run = cfg.copy()
    run.shard, run.num_shards = 0, 1  # the run's config, whichever shard merges
    save_config(run, out)
    return _write_tables(out, keys, head)


def _write_tables(out: Path, keys: list[tuple[int, int]], head: dict) -> dict:
    """The episode and step tables of the parts in `out` among `keys`, and the summary: `head`, then the statistics."""
    episodes, steps = parts.merge(out, keys)
    atomic_write_parquet(out / "episodes.parquet", episodes)
    atomic_write_parquet(out / "steps.parquet", steps)
    summary = {**head, **summarise_file(out / "episodes.parquet")}
    for name, entry in summary.get("constraints", {}).items():  # several constraints: each its own satisfaction
        entry["satisfaction"] = summary.get(f"satisfaction_{name.partition('=')[0]}")
    atomic_write_json(out / "summary.json", summary)
    print(format_summary(summary))
    print(f"wrote {out}")
    return summary


def judge_source(cfg: DictConfig, constraint, gripper: str, tasks: list[int], vla) -> Path:
    """The run `judge_from` names, if its episodes are this run's: method=none judges an unconstrained run, method=prompt
    a prompting run whose prompted instructions the policy `vla` reads exactly as this run's (the embedded models read
    every word they never saw as one unknown token: "stay low" and "move fast" are the same input). Same model,
    suite, seeds and settings; not when the episodes start with the gripper closed (the runs judged start open)."""
    from vlactl.env.suites import task_info
    from vlactl.rollout.constraints import prompted

    if not constraint or cfg.method not in JUDGED_METHODS:
        raise UsageError(f"judge_from=... judges another run under a constraint with method="
                         f"{' or '.join(JUDGED_METHODS)}, not constraint={cfg.constraint} method={cfg.method}")
    if gripper != "open":
        raise UsageError(f"judge_from=... cannot stand in for episodes that start with the gripper {gripper} (the "
                         f"runs it judges start open); drop judge_from, or set start_gripper=open")
    source = stage_output(cfg.judge_from, "config.yaml", "rollout run", "vlactl rollout")
    ran = OmegaConf.load(source / "config.yaml").get("constraint", "none") if cfg.method == "prompt" else "none"
    as_source = {**OmegaConf.to_container(cfg, resolve=True), "constraint": ran}  # the method is the source's
    clash = _differing_key(source / "config.yaml", as_source, [k for k in SAME_RUN_KEYS if k != "window"])
    if clash:
        key, before, now = clash
        raise UsageError(f"judge_from={cfg.judge_from!r} ran with {key}={before!r}, not {now!r}")
    reads_alike = vla.reads_alike if vla is not None else str.__eq__  # a served policy: only the same words
    asked_there = parse_constraints(ran)
    for task in tasks if cfg.method == "prompt" else ():
        instruction = task_info(cfg.suite, task).instruction
        theirs, ours = prompted(instruction, asked_there), prompted(instruction, constraint)
        if not reads_alike(theirs, ours):
            raise UsageError(f"judge_from={cfg.judge_from!r} prompted {theirs!r}, which {cfg.model} reads otherwise "
                             f"than {ours!r}; run this prompt instead")
    return source


def judge_run(cfg: DictConfig, constraint, plan: Steering, todo: list[tuple[int, int]], out: Path,
              source: Path) -> None:
    """method=none or prompt without re-running: the policy acts as in the run `source` (`judge_source`), so judge its
    episodes against this constraint."""
    import json

    import pandas as pd

    from vlactl.rollout.constrained import reading_columns
    from vlactl.rollout.constraints import JUDGED
    from vlactl.rollout.workers import judge_part

    missing = [key for key in todo if not parts.is_done(source, *key)]
    if missing:
        raise UsageError(f"judge_from={cfg.judge_from!r} lacks {len(missing)} of these episodes (task "
                         f"{missing[0][0]}, episode {missing[0][1]} first); run it with the same tasks and episodes")
    for task, k in todo:
        base = parts.stem(source, task, k)
        row = json.loads(base.with_suffix(".json").read_text())
        judged_there = [*reading_columns(parse_constraints(row["constraint"])), *JUDGED]  # a prompting run's
        row.update(constraint=constraint_name(constraint), method=cfg.method, start_gripper="open")  # judge_source
        steps = pd.read_parquet(base.with_suffix(".parquet"))
        steps = steps.drop(columns=[c for c in steps if c.startswith(tuple(judged_there))])
        parts.write(out, row, judge_part(constraint, row, steps, plan.bounds.speed_threshold, {}))


def resolve_defaults(cfg: DictConfig) -> None:
    """The method and holds a run is saved with (a run and its merge resolve them alike): null method is control under a
    constraint, null holds are [] unless control on the actions holds by default (`default_holds`)."""
    cfg.method = resolved_method(cfg)
    if cfg.hold is None and not controls_actions(cfg):
        cfg.hold = []


def resolved_method(cfg: DictConfig) -> str:
    """method=null: a constraint alone is enforced by the controller; the baselines are asked for by name."""
    if cfg.method is not None:
        return cfg.method
    return "none" if cfg.constraint in (None, "", "none") else "control"


def default_run_name(cfg: DictConfig) -> str:
    """<model>_<suite>[_<constraint>_<method>[-pause]][_perturb-<kind>], e.g.
    `hybrid_libero_spatial_gripper-open_control`, `..._height-high_filter-pause`; several constraints are each named:
    `hybrid_libero_spatial_height-high_speed-low_control`."""
    default = f"{cfg.model}_{cfg.suite}"
    named = "_".join(folder_name(c.name) for c in parse_constraints(cfg.constraint))
    default += f"_{named}_{method_label(resolved_method(cfg), cfg.pause)}" if named else ""
    default += "" if cfg.perturb in (None, "none") else f"_perturb-{cfg.perturb}"
    return folder_name(default)


def run_dir(cfg: DictConfig) -> Path:
    """`<output_root>/<run_name>` (created later); the default run name is the model and the suite, e.g.
    `scripted_libero_spatial`. Fails early if the root is not writable."""
    name = cfg.run_name or default_run_name(cfg)
    root = resolve_path(cfg.output_root)
    return ensure_writable_dir(root, requested=root, key="output_root") / name


def record_model_inference(cfg: DictConfig) -> None:
    """`cfg.model_inference`: the inference options the run's workers load the model with (an embedded checkpoint's
    `samples`, `decode`, ...), saved and compared on resume like the other SAME_RUN_KEYS. Not for the scripted
    expert or a policy server's model, which the workers do not load."""
    if cfg.policy or str(cfg.model) == SCRIPTED:
        return
    from vlactl.models.registry import inference_options

    options = OmegaConf.to_container(cfg.model_args, resolve=True) if cfg.get("model_args") else {}
    with open_dict(cfg):
        cfg.model_inference = inference_options(str(cfg.model), **options)


def _differing_key(saved: Path, new: dict, keys) -> tuple | None:
    """(key, saved value, new value) of the first of `keys` on which a saved run config differs from `new`."""
    old = OmegaConf.to_container(OmegaConf.load(saved))
    old = {key: old.get(key, BEFORE_KEY.get(key)) for key in keys}
    unrecorded = {"model_inference"} if old.get("model_inference") is None else set()
    return next(((key, old[key], new.get(key)) for key in keys if key not in unrecorded and old[key] != new.get(key)),
                None)


def _check_same_run(cfg: DictConfig, out: Path) -> None:
    saved = out / "config.yaml"
    clash = saved.exists() and _differing_key(saved, OmegaConf.to_container(cfg, resolve=True), SAME_RUN_KEYS)
    if clash:
        key, before, now = clash
        raise UsageError(
            f"{out} holds a run with {key}={before!r}, not {now!r}; resume it with the same settings "
            f"or choose another run_name=..."
        )


def batches(todo: list[tuple[int, int]], workers: int) -> list[Batch]:
    """Group pending episodes by task so each worker builds an env once per batch (env creation takes seconds).

    With at least as many tasks as workers a batch is a whole task and the pool balances tasks; with fewer, each
    task is split into contiguous pieces so every worker has work.
    """
    by_task: dict[int, list[int]] = {}
    for task, k in todo:
        by_task.setdefault(task, []).append(k)
    pieces = -(-workers // len(by_task)) if by_task else 1
    out = []
    for task, episodes in by_task.items():
        n = min(pieces, len(episodes))
        out += [Batch(task, tuple(episodes[i * len(episodes) // n : (i + 1) * len(episodes) // n])) for i in range(n)]
    return out


def _run_workers(spec: RunSpec, work: list[Batch], out: Path, keys: list, workers: int) -> None:
    def finished() -> int:
        return sum(parts.is_done(out, *key) for key in keys)

    bar = tqdm(total=len(keys), initial=finished(), desc=f"rollout {spec.suite}", unit="ep")
    if work:
        ctx = mp.get_context("spawn")
        with ctx.Pool(min(workers, len(work)), initializer=init_worker, initargs=(spec,)) as pool:
            result = pool.map_async(run_batch, work, chunksize=1)
            while not result.ready():  # batches report at their end; the parts on disk show each episode
                result.wait(1.0)
                if finished() > bar.n:
                    bar.update(finished() - bar.n)
            result.get()  # re-raises a worker's error
        bar.update(finished() - bar.n)
    bar.close()
