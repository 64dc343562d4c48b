"""Hydra multirun (`vlactl rollout -m constraint=gripper=open,gripper=closed alpha=2,4`) through Hydra's own sweeper
and launcher, so `hydra/launcher=joblib|submitit_local|submitit_slurm|ray` and `hydra.launcher.*` work as in any Hydra
application (docs/scale-out.md, "Launchers").

Hydra's compose API, which composes every stage's config, cannot launch; hydra-zen's `launch` is Hydra's own multirun
(sweeper, launcher, callbacks) called as a function, so the Typer commands keep their options and one-line errors,
where a `@hydra.main` entry per stage would own the command line. Hydra sees only the swept overrides and the
`hydra...` ones: each job hands its combination, with the fixed overrides, to the stage's own config loader (whose
`model=<name>` is a plain value, not a choice of conf/model/). Hydra's default launcher runs the jobs one after
another, in order; each run is named after the swept keys its default name does not carry, so a re-run resumes.
"""

from __future__ import annotations

import functools
import multiprocessing
from typing import Callable

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException

from vlactl.errors import UsageError
from vlactl.io import folder_name


def _quote_pieces(item: str) -> str:
    """`constraint=gripper=open,gripper=closed` -> `constraint='gripper=open','gripper=closed'` (Hydra needs
    values holding '=' quoted). A bracketed list is one value, not a sweep: `constraint=[height=high,speed=low]`
    -> `constraint='[height=high,speed=low]'`, and `constraint=[height=high,speed=low],gripper=open` sweeps two."""
    key, _, value = item.partition("=")
    if "=" not in value or "'" in value or '"' in value:
        return item
    pieces, depth, start = [], 0, 0
    for i, char in enumerate(value):  # split at the commas outside brackets
        depth += {"[": 1, "]": -1}.get(char, 0)
        if char == "," and depth == 0:
            pieces.append(value[start:i])
            start = i + 1
    pieces.append(value[start:])
    return f"{key}=" + ",".join(f"'{piece}'" for piece in pieces)


def is_hydra(item: str) -> bool:
    """`hydra/launcher=joblib`, `hydra.launcher.n_jobs=2`: settings of Hydra's launch, not of the stage."""
    return item.lstrip("+~").startswith(("hydra/", "hydra."))


def _bare(key: str) -> str:
    return key.lstrip("+~")


def _job(cfg, run: Callable[[list[str], str], None], fixed: list[str], prefixes: dict[str, str],
         named_by: tuple[str, ...]) -> None:
    """One Hydra job: its swept values (`++key=value`, as Hydra's sweeper wrote them) back in the user's form."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    swept = [item.split("=", 1) for item in HydraConfig.get().overrides.task]
    items = [f"{prefixes[_bare(key)]}{_bare(key)}={value}" for key, value in swept]
    tag = "_".join(f"{_bare(key)}-{folder_name(value)}" for key, value in swept if _bare(key) not in named_by)
    # In joblib's (loky) workers the start method is 'loky', which the processes a stage spawns (rollout's
    # simulators) cannot find: they would die at start, and a pool would start them again without end.
    if multiprocessing.get_start_method(allow_none=True) == "loky":
        multiprocessing.set_start_method("spawn", force=True)
    # The stage composes its config with Hydra's compose API, which refuses to start inside the launch's Hydra.
    launching = GlobalHydra.instance().hydra
    GlobalHydra.instance().clear()
    try:
        run(fixed + items, tag)
    finally:
        GlobalHydra.instance().clear()
        if launching is not None:
            GlobalHydra.instance().initialize(launching)


def launch(stage: str, overrides: list[str], run: Callable[[list[str], str], None],
           load: Callable[[list[str]], object], named_by: tuple[str, ...] = ()) -> None:
    """Run `run(overrides, tag)` once per combination of the swept values, through Hydra's sweeper and launcher.

    `tag` names the swept keys outside `named_by` (e.g. `alpha-2`), '' if none. The fixed overrides, and every swept
    value with them, are first composed by `load`, so a bad one is a one-line error before anything is launched."""
    from hydra_zen import launch as hydra_launch

    from vlactl.config import REPO_ROOT

    hydra_args = [item for item in overrides if is_hydra(item)]
    items = [_quote_pieces(item) for item in overrides if not is_hydra(item)]
    try:
        parsed = OverridesParser.create().parse_overrides(items)
    except HydraException as exc:
        raise UsageError(f"bad multirun override in {overrides}: {str(exc).strip().splitlines()[0]}") from None
    fixed = [item for item, override in zip(items, parsed) if not override.is_sweep_override()]
    swept = [(item, override) for item, override in zip(items, parsed) if override.is_sweep_override()]
    load(fixed)  # the fixed values alone too: a bad one is one line here, not Hydra's job error
    for _, override in swept:
        if override.is_discrete_sweep():
            for value in override.sweep_string_iterator():
                load(fixed + [f"{override.get_key_element()}={value}"])
    config = {
        # Hydra's logging set-up, .hydra/ and job folders and change of directory are off: each stage logs, saves its
        # resolved config and writes its run folder as without -m. The sweep folder keeps Hydra's multirun.yaml and
        # the launchers' own files (submitit's logs, .submitit/<job id>/).
        "defaults": [{"override hydra/job_logging": "none"}, {"override hydra/hydra_logging": "none"}, "_self_"],
        "hydra": {"output_subdir": None, "job": {"chdir": False},
                  "sweep": {"dir": f"{REPO_ROOT}/outputs/multirun/{stage}/${{now:%Y-%m-%d_%H-%M-%S}}", "subdir": "."}},
    }
    # `++`: Hydra's config is empty; the stage's own loader checks the keys.
    sweeps = [f"++{_bare(item.split('=', 1)[0])}={item.split('=', 1)[1]}" for item, _ in swept]
    prefixes = {_bare(item.split("=", 1)[0]): item[:len(item) - len(item.lstrip("+~"))] for item, _ in swept}
    job = functools.partial(_job, run=run, fixed=fixed, prefixes=prefixes, named_by=named_by)
    try:
        hydra_launch(config, job, overrides=sweeps + hydra_args, multirun=True, version_base="1.3",
                     config_name=f"vlactl_{stage}", job_name=stage)
    except HydraException as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UsageError(f"bad multirun setting in {hydra_args or overrides}: {first_line}") from None
