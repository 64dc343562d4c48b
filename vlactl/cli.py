"""`vlactl`: the pipeline as Typer subcommands; every config value can also be overridden Hydra-style (key=value).

demos -> train-policy -> collect -> train-probes -> sweep / controllability / rollout -> plot
"""

from __future__ import annotations

import functools
import sys
from typing import List, Optional

import typer

from vlactl.errors import UsageError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Observe and steer vision-language-action policies through their internal representations, in LIBERO.",
)

OVERRIDES = typer.Argument(None, help="Hydra-style config overrides, e.g. suite=libero_object episodes_per_task=5")


MULTIRUN = typer.Option(False, "-m", "--multirun", help="Hydra multirun: key=a,b runs once per value (cartesian "
                        "product over every swept key), each run in its own folder; hydra/launcher=joblib, "
                        "submitit_local, submitit_slurm or ray runs them in parallel (docs/scale-out.md).")


def _overrides(extra: list[str] | None, **options) -> list[str]:
    """Typer options become Hydra overrides; explicit key=value arguments win because they come last."""
    out = [f"{key}={value}" for key, value in options.items() if value is not None]
    return out + list(extra or [])


def _launch(stage: str, overrides: list[str], multirun: bool, run, load, named_by: tuple[str, ...]) -> None:
    """`run(overrides, tag)` once as given, or with -m once per combination of the swept values, through Hydra's
    launcher (vlactl/multirun.py). `run` is a module-level function, so that launchers can pickle it."""
    from vlactl.multirun import is_hydra, launch

    if multirun:
        launch(stage, overrides, run, load, named_by)
    elif hydra := [item for item in overrides if is_hydra(item)]:
        raise UsageError(f"{hydra[0]} needs -m: Hydra's launchers run multiruns")
    else:
        run(overrides, "")


@app.command()
def tasks(suite: Optional[str] = typer.Option(None, "--suite", help="Only this suite.")):
    """List LIBERO suites, their tasks and instructions."""
    from vlactl.env.suites import SUITES, n_tasks, task_info

    for name in [suite] if suite else SUITES:
        count = n_tasks(name)
        typer.echo(f"{name} ({count} tasks)")
        for tid in range(count):
            info = task_info(name, tid)
            typer.echo(f"  {tid:3d}  {info.instruction}  [{info.n_init_states} init states]")


@app.command()
def demos(
    overrides: Optional[List[str]] = OVERRIDES,
    suite: Optional[str] = typer.Option(None, "--suite", help="LIBERO suite, e.g. libero_spatial."),
    episodes_per_task: Optional[int] = typer.Option(None, "--episodes-per-task"),
    workers: Optional[int] = typer.Option(None, "--workers", help="Simulator worker processes."),
    output_dir: Optional[str] = typer.Option(None, "--output-dir"),
):
    """Generate scripted-expert demonstrations as a LeRobot v3 dataset (resumable)."""
    from vlactl.config import load_config
    from vlactl.data.demos import run_demos

    cfg = load_config(
        "demos",
        _overrides(overrides, suite=suite, episodes_per_task=episodes_per_task, workers=workers, output_dir=output_dir),
    )
    run_demos(cfg)


@app.command()
def rollout(
    overrides: Optional[List[str]] = OVERRIDES,
    model: Optional[str] = typer.Option(None, "--model", help="Registry name, checkpoint path, or 'scripted'."),
    suite: Optional[str] = typer.Option(None, "--suite", help="LIBERO suite, e.g. libero_spatial."),
    episodes_per_task: Optional[int] = typer.Option(None, "--episodes-per-task"),
    workers: Optional[int] = typer.Option(None, "--workers", help="Simulator worker processes."),
    video: Optional[bool] = typer.Option(None, "--video/--no-video", help="Save an mp4 per episode."),
    run_name: Optional[str] = typer.Option(None, "--run-name", help="Output folder under outputs/rollout/."),
    constraint: Optional[str] = typer.Option(
        None, "--constraint", help="none, gripper=open|closed, height=low|high, speed=low|high, or several at "
        "once, one per feature: [height=high,speed=low]."),
    method: Optional[str] = typer.Option(None, "--method", help="none, prompt, control (the default under a constraint), alpha, meandiff or filter."),
    probes: Optional[str] = typer.Option(None, "--probes", help="Probe run folder, for control and alpha."),
    multirun: bool = MULTIRUN,
):
    """Closed-loop evaluation on LIBERO: success per task, per-step states and actions, optional videos (resumable).

    `shard=i num_shards=n` runs one slice of the episodes; `vlactl rollout merge <same overrides>` joins them."""
    from vlactl.rollout.runner import rollout_config

    merge = bool(overrides) and overrides[0] == "merge"  # a word, not an override: Typer has one argument list here
    overrides = overrides[1:] if merge else overrides
    given = _overrides(
        overrides, model=model, suite=suite, episodes_per_task=episodes_per_task, workers=workers, video=video,
        run_name=run_name, constraint=constraint, method=method, probes=probes,
    )
    # `-m shard=0,1,2,3 num_shards=4`: the shards of one run (each writes its own shard folder), not four runs
    _launch("rollout", given, multirun, functools.partial(_rollout_run, merge=merge), rollout_config,
            named_by=("model", "suite", "constraint", "method", "shard"))


def _rollout_run(items: list[str], tag: str, merge: bool) -> None:
    from vlactl.rollout.runner import default_run_name, merge_run, rollout_config, run_rollout

    cfg = rollout_config(items)
    if tag and cfg.run_name is None:
        cfg.run_name = f"{default_run_name(cfg)}_{tag}"
    merge_run(cfg) if merge else run_rollout(cfg)


@app.command()
def serve(overrides: Optional[List[str]] = OVERRIDES):
    """Load a model once and answer rollout workers over a websocket (`vlactl rollout policy=ws://HOST:PORT`),
    batching requests that arrive together; steering runs in the server, per connection (docs/scale-out.md)."""
    from vlactl.config import load_policy_stage_config
    from vlactl.serve.server import run_serve

    run_serve(load_policy_stage_config("serve", overrides))


@app.command("train-policy")
def train_policy(
    overrides: Optional[List[str]] = OVERRIDES,
    model: Optional[str] = typer.Option(None, "--model", help="hybrid or autoregressive."),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="LeRobot v3 demonstrations (vlactl demos)."),
    steps: Optional[int] = typer.Option(None, "--steps"),
    output_dir: Optional[str] = typer.Option(None, "--output-dir"),
):
    """Train an embedded VLA on demonstrations; writes a checkpoint folder (resumable)."""
    from vlactl.config import load_config
    from vlactl.training.train_policy import run_train_policy

    cfg = load_config(
        "train_policy", _overrides(overrides, model=model, dataset=dataset, steps=steps, output_dir=output_dir)
    )
    typer.echo(f"checkpoint: {run_train_policy(cfg)}")


@app.command("average-policies")
def average_policies(overrides: Optional[List[str]] = OVERRIDES):
    """Average the weights of checkpoints fine-tuned from one start (a "model soup") into one checkpoint."""
    from vlactl.config import load_config
    from vlactl.training.average import run_average_policies

    typer.echo(f"checkpoint: {run_average_policies(load_config('average_policies', overrides))}")


@app.command()
def collect(
    overrides: Optional[List[str]] = OVERRIDES,
    model: Optional[str] = typer.Option(None, "--model", help="Registry name or checkpoint folder."),
    dataset: Optional[str] = typer.Option(None, "--dataset", help="LeRobot v3 dataset (vlactl demos, or your own)."),
    pooling: Optional[str] = typer.Option(None, "--pooling", help="prefix, last, image, text or action."),
    output_dir: Optional[str] = typer.Option(None, "--output-dir"),
    multirun: bool = MULTIRUN,
):
    """Per-layer pooled activations with robot labels for every dataset frame (resumable)."""
    given = _overrides(overrides, model=model, dataset=dataset, pooling=pooling, output_dir=output_dir)
    _launch("collect", given, multirun, _collect_run, functools.partial(_policy_stage, "collect"),
            named_by=("model", "dataset", "pooling"))


def _tagged_run(stage: str, module: str, items: list[str], tag: str) -> None:
    """One run of a collect or sweep multirun: in its default output folder with the swept keys' tag appended."""
    import importlib

    stage_module = importlib.import_module(module)
    cfg = _policy_stage(stage, items)
    if tag and cfg.output_dir is None:
        cfg.output_dir = f"{stage_module.default_output(cfg)}_{tag}"
    getattr(stage_module, f"run_{stage}")(cfg)


_collect_run = functools.partial(_tagged_run, "collect", "vlactl.steering.collect")


@app.command()
def sweep(
    overrides: Optional[List[str]] = OVERRIDES,
    model: Optional[str] = typer.Option(None, "--model", help="Registry name or checkpoint folder."),
    probes: Optional[str] = typer.Option(None, "--probes", help="Probe run folder (vlactl train-probes)."),
    feature: Optional[str] = typer.Option(None, "--feature", help="Whose probe direction to push along."),
    output_dir: Optional[str] = typer.Option(None, "--output-dir"),
    multirun: bool = MULTIRUN,
):
    """Perturbation sweep (Fig. 2): action change per layer and alpha, and each layer's norm."""
    given = _overrides(overrides, model=model, probes=probes, feature=feature, output_dir=output_dir)
    _launch("sweep", given, multirun, _sweep_run, functools.partial(_policy_stage, "sweep"),
            named_by=("model", "feature", "direction"))


def _policy_stage(stage: str, items: list[str]):
    from vlactl.config import load_policy_stage_config

    return load_policy_stage_config(stage, items)


_sweep_run = functools.partial(_tagged_run, "sweep", "vlactl.steering.sweep")


@app.command()
def controllability(
    overrides: Optional[List[str]] = OVERRIDES,
    model: Optional[str] = typer.Option(None, "--model", help="Registry name or checkpoint folder."),
    probes: Optional[str] = typer.Option(None, "--probes", help="Probe run folder (vlactl train-probes)."),
    output_dir: Optional[str] = typer.Option(None, "--output-dir"),
):
    """Controllability map: per layer (and group) x feature, how far the controller's push on the reading moves the
    predicted action feature (gain, R², crossing share); also written into the probe run for rollout (resumable)."""
    from vlactl.config import load_policy_stage_config
    from vlactl.steering.controllability import run_controllability

    run_controllability(load_policy_stage_config(
        "controllability", _overrides(overrides, model=model, probes=probes, output_dir=output_dir)))


@app.command("train-probes")
def train_probes(
    overrides: Optional[List[str]] = OVERRIDES,
    activations: Optional[str] = typer.Option(None, "--activations", help="Activation folder (vlactl collect)."),
    run: Optional[str] = typer.Option(None, "--run", help="Run name; output under outputs/probes/<run>."),
    output_dir: Optional[str] = typer.Option(None, "--output-dir"),
    multirun: bool = MULTIRUN,
):
    """Fit a linear probe per layer x feature; writes metrics.parquet and one safetensors file per probe."""
    from vlactl.config import load_config, quote_values

    # a frame query is one value however many commas it holds; a sweep of queries comes quoted, each on its own
    given = quote_values(_overrides(overrides, activations=activations, run=run, output_dir=output_dir), "frames")
    _launch("train_probes", given, multirun, _train_probes_run, functools.partial(load_config, "train_probes"),
            named_by=("activations", "run"))


def _train_probes_run(items: list[str], tag: str) -> None:
    from vlactl.config import load_config, resolve_path
    from vlactl.steering.train_probes import run_train_probes

    cfg = load_config("train_probes", items)
    if tag and cfg.run is None and cfg.output_dir is None and cfg.activations:
        cfg.run = f"{resolve_path(cfg.activations).name}_{tag}"
    run_train_probes(cfg)


plot_app = typer.Typer(no_args_is_help=True, help="The paper's figures, drawn from a stage's output files.")
app.add_typer(plot_app, name="plot")


@plot_app.command("probes")
def plot_probes(
    overrides: Optional[List[str]] = OVERRIDES,
    run_dir: Optional[str] = typer.Option(None, "--run-dir", help="Probe run folder (vlactl train-probes)."),
):
    """Fig. 1 (best layer per feature vs baseline) and per-layer curves of every probe metric, PNG and PDF."""
    from vlactl.config import load_config
    from vlactl.plots.probes import run_plot_probes

    run_plot_probes(load_config("plot_probes", _overrides(overrides, run_dir=run_dir)))


@plot_app.command("sweep")
def plot_sweep(
    overrides: Optional[List[str]] = OVERRIDES,
    run_dir: Optional[str] = typer.Option(None, "--run-dir", help="Sweep run folder (vlactl sweep)."),
):
    """Fig. 2: mean change of delta-yaw and gripper action vs layer per alpha, and the norm vs layer."""
    from vlactl.config import load_config
    from vlactl.plots.sweep import run_plot_sweep

    run_plot_sweep(load_config("plot_sweep", _overrides(overrides, run_dir=run_dir)))


@plot_app.command("controllability")
def plot_controllability(
    overrides: Optional[List[str]] = OVERRIDES,
    run_dir: Optional[str] = typer.Option(None, "--run-dir", help="Controllability run folder."),
    compare: Optional[str] = typer.Option(None, "--compare", help="A second controllability run, drawn beside it."),
):
    """Layer x feature heatmap of the controllability gain (annotated with R²); two runs side by side."""
    from vlactl.config import load_config
    from vlactl.plots.controllability import run_plot_controllability

    run_plot_controllability(load_config("plot_controllability", _overrides(overrides, run_dir=run_dir,
                                                                            compare=compare)))


@plot_app.command("rollouts")
def plot_rollouts(
    overrides: Optional[List[str]] = OVERRIDES,
    root: Optional[str] = typer.Option(None, "--root", help="Folder of rollout runs (default outputs/rollout)."),
):
    """Figs. 4-8: violins of the constrained feature per method and condition; success vs satisfaction."""
    from vlactl.config import load_config
    from vlactl.plots.rollouts import run_plot_rollouts

    run_plot_rollouts(load_config("plot_rollouts", _overrides(overrides, root=root)))


@plot_app.command("readings")
def plot_readings(
    overrides: Optional[List[str]] = OVERRIDES,
    model: Optional[str] = typer.Option(None, "--model", help="Registry name or checkpoint folder."),
    probes: Optional[str] = typer.Option(None, "--probes", help="Probe run folder (vlactl train-probes)."),
):
    """Fig. 3: a probe's readings under no intervention, a fixed alpha W push and the controller, with the box."""
    from vlactl.config import load_policy_stage_config
    from vlactl.plots.readings import run_plot_readings

    run_plot_readings(load_policy_stage_config("plot_readings", _overrides(overrides, model=model, probes=probes)))


def main() -> None:
    try:
        app(standalone_mode=True)
    except UsageError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except SystemExit as exc:
        if exc.code == 130:  # Typer turns Ctrl-C into a silent exit 130
            typer.echo("interrupted; re-run the same command to resume", err=True)
        raise


if __name__ == "__main__":
    main()
