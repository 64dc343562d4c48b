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
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict
from tqdm import tqdm

from vlactl.config import load_policy_stage_config, quote_values, resolve_path, save_config, stage_output
from vlactl.env.perturbations import parse_perturbation
from vlactl.errors import UsageError, check_choice, check_non_negative, check_positive
from vlactl.io import atomic_write_json, atomic_write_parquet, ensure_writable_dir, folder_name
from vlactl.rollout import parts, shards
from vlactl.rollout.agents import SCRIPTED, load_agent
from vlactl.rollout.constrained import STEERING, Steering, method_label
from vlactl.rollout.constraints import START_GRIPPER, constraint_name, parse_constraints, start_gripper
from vlactl.rollout.plan import controls_actions, steered_features, steering
from vlactl.rollout.summary import format_summary, summarise_file
from vlactl.rollout.workers import Batch, RunSpec, init_worker, run_batch

# Settings that change what an episode is: parts made under other values must not be mixed into this run.
SAME_RUN_KEYS = ("model", "model_inference", "suite", "seed", "max_steps", "replan_every", "snap_gripper", "env",
                 "constraint", "window", "method", "start_gripper", "hold", "hold_tolerance", "barrier_decay", "perturb",
                 "perturb_start", "perturb_steps", "perturb_size", "box", "passes", "height_margin", "pause",
                 "episode_noise", "speed_margin", "ensemble")
JUDGED_METHODS = ("none", "prompt")  # what judge_from can stand in for
# what runs saved before a key existed did
BEFORE_KEY = {"start_gripper": "open", "hold": [], "hold_tolerance": 0.0, "snap_gripper": False, "barrier_decay": 0.5,
              "perturb": "none", "perturb_start": 0, "perturb_steps": 15, "perturb_size": None,
              "box": "state", "passes": 3, "height_margin": 0.0, "pause": False, "episode_noise": False,
              "model_inference": None,  # None: not recorded, not compared (runs before 2026-12-02 evening)
              "speed_margin": 0.1, "ensemble": None}


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
    ensemble = _ensemble(cfg)
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
        agent = load_agent(str(cfg.model), cfg.replan_every, load_policy, bool(cfg.snap_gripper), ensemble)
    from vlactl.render_presets import warn_if_rendered_otherwise
    warn_if_rendered_otherwise(str(cfg.model), getattr(agent, "vla", None), env)
    for probe in plan.probes + plan.holds:  # here, not in a worker after its start-up; pushed where they were fitted
        probe.check_fits(agent.vla.name, agent.vla.layer_width(probe.layer))
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
        episode_noise=bool(cfg.episode_noise), ensemble=ensemble,
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


def _ensemble(cfg: DictConfig) -> float | None:
    """`ensemble=`: temporal ensembling averages the actions the policy predicted; a push or a policy server acts on
    one chunk a re-plan, the scripted expert has none. An unknown method is left to `steering`'s check."""
    if cfg.ensemble is None:
        return None
    if cfg.method in STEERING:  # a push acts on one chunk a re-plan
        raise UsageError(f"ensemble={cfg.ensemble} goes with method none, prompt or filter, not {cfg.method}")
    if cfg.policy or str(cfg.model) == SCRIPTED:
        what = f"policy={cfg.policy}" if cfg.policy else f"model={SCRIPTED}"
        raise UsageError(f"ensemble={cfg.ensemble} needs a model the workers load, not {what}")
    try:
        return float(cfg.ensemble)
    except ValueError:
        raise UsageError(f"ensemble must be a number (ACT's coefficient, e.g. 0.01) or null, "
                         f"got {cfg.ensemble!r}") from None


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
