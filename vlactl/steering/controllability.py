"""`vlactl controllability`: where a push reaches the output. For every steerable layer (and every group of them:
`backbone`, `expert`) x feature of a probe run, the minimal controller sets the probe's reading to its unsteered value
plus each target delta (a relative box zmin = zmax = delta, `Steerer`), over N dataset frames, and the model's own
predicted action feature is compared with the unsteered prediction under the same noise. Targets are in standard
deviations of the probe's reading over those frames, so probes of different families (vlactl.steering.directions)
and penalties compare: a gain is the change of the predicted feature per standard deviation of the reading.

The predicted feature is the mean over the first `replan_every` actions of the chunk (what a rollout executes) of the
feature's action column: itself for an action feature, its delta for a state feature (z -> dz), and for speed the
norm of the predicted (dx, dy, dz). Per row: `gain`, the least-squares slope of its change on the reading's change
(per standard deviation of the reading), `r2` of that line, and for binary features `cross_share`, the
share of predictions not yet on the asked side (delta > 0: close) that the push moves across 0 to it; and
`leak_<column>`, the same slope for each other predicted action column (dx, dy, dz, droll, dpitch, dyaw,
gripper_action) the push was not meant to move: a gripper push that also lowers the hand shows as a negative `leak_dz`,
a translation push that also tilts the hand as a `leak_droll`.

Writes `controllability.parquet` (one row per layer or group and feature) and `points.parquet` (one per frame, target
and row) under the run folder, and the table into the probe run folder too (replacing only the rows of the features
measured), where `vlactl rollout` takes its default steered layers from (`most_controllable`).
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig, ListConfig, OmegaConf

from vlactl.config import REPO_ROOT, SHIPPED_PROBES, resolve_path, save_config, stage_output
from vlactl.env.features import ACTION_FEATURES, STATE_FEATURES, TRANSLATION
from vlactl.errors import UsageError, check_positive
from vlactl.io import atomic_write_parquet, ensure_writable_dir
from vlactl.steering.collect import frame_batch
from vlactl.steering.offline import policy_and_frames, predict_chunk, run_batches
from vlactl.steering.probe_file import load_probe
from vlactl.steering.steer import Constraint, Steerer
from vlactl.steering.train_probes import BINARY, METRICS_NAME, probe_filename, steerable_rows

CONTROLLABILITY_NAME, POINTS_NAME = "controllability.parquet", "points.parquet"
GROUPS = ("backbone", "expert")
# the predicted action column each probe feature is read against
OUTPUT = {**dict(zip(STATE_FEATURES, ACTION_FEATURES)), **{a: a for a in ACTION_FEATURES}, "speed": "speed"}
LEAK_COLUMNS = ACTION_FEATURES  # the predicted columns a push elsewhere should leave alone


def group_layers(table: pd.DataFrame, group: str) -> list[str]:
    """The steerable layers of a probe run's metrics rows whose name starts with `group` (`expert` -> expert.0, ...)."""
    return [layer for layer in dict.fromkeys(steerable_rows(table)["layer"]) if layer.split(".")[0] == group]


def metrics_digest(run: Path) -> str:
    """What a controllability table was measured on: a retrained probe run rewrites its metrics."""
    return hashlib.sha256((run / METRICS_NAME).read_bytes()).hexdigest()


def controllability_rows(run: Path, feature: str) -> pd.DataFrame | None:
    """A probe run's controllability rows of one feature; None if it has none, or (one stderr line) if its probes
    were retrained since."""
    path = run / CONTROLLABILITY_NAME
    if not path.is_file():
        return None
    table = pd.read_parquet(path)
    if (table["metrics_digest"] != metrics_digest(run)).any():
        print(f"warning: ignoring {path}: its probes were retrained since; re-run `vlactl controllability`",
              file=sys.stderr)
        return None
    rows = table[table["feature"] == feature]
    return rows if len(rows) else None


def controllability_score(rows: pd.DataFrame) -> pd.Series:
    """How far and how consistently each row's push moves the predicted feature: |gain| x R² (0 where nothing moved)."""
    return (rows["gain"].abs() * rows["r2"]).fillna(0.0)


def most_controllable(rows: pd.DataFrame) -> str | None:
    """The layer or group whose push moves the predicted feature most and most consistently (largest
    `controllability_score`); None when nothing moved it."""
    score = controllability_score(rows)
    return None if not (score > 0).any() else str(rows.loc[score.idxmax(), "layer"])


def _check(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "model"):
        raise UsageError("which model? pass model=<registry name or checkpoint folder>, e.g. model=hybrid")
    if cfg.probes is None:
        raise UsageError("which probes? pass probes=<probe run folder from `vlactl train-probes`>")
    for key in ("frames", "batch_size", "threads"):
        check_positive(key, cfg[key])
    targets = cfg.targets if isinstance(cfg.targets, (list, ListConfig)) else None
    numbers = targets and all(isinstance(t, (int, float)) and not isinstance(t, bool) and t != 0 for t in targets)
    if not numbers or len(set(targets)) < 2:  # a gain is a slope: it needs two pushes
        raise UsageError(f"targets must be a list of two or more different non-zero numbers (changes of the "
                         f"reading), e.g. targets=[-2,-1,1,2], got {cfg.targets!r}")


def _units(table: pd.DataFrame, features: list[str], groups: bool) -> list[tuple[str, bool, str]]:
    """(layer or group, is a group, feature) for every steerable layer with a probe and, with `groups`, every group
    of two or more of them (a group of one is that layer)."""
    units = []
    for feature in features:
        rows = table[table["feature"] == feature]
        units += [(layer, False, feature) for layer in dict.fromkeys(steerable_rows(rows)["layer"])]
        if groups:
            units += [(group, True, feature) for group in GROUPS if len(group_layers(rows, group)) > 1]
    return units


def default_output(cfg: DictConfig) -> Path:
    return REPO_ROOT / "outputs" / "controllability" / f"{Path(str(cfg.model)).name}_{resolve_path(cfg.probes).name}"


def run_controllability(cfg: DictConfig, load_policy=None) -> Path:
    """Measure (or resume measuring) and return the run folder; also writes the table into the probe run. With a list
    of probe runs, each is measured in turn, and with `choose_into` the best run's probes of every feature are
    assembled there (vlactl.steering.choose); returns that folder."""
    if isinstance(cfg.probes, (list, ListConfig)):
        return _measure_candidates(cfg, load_policy)
    if cfg.choose_into is not None:
        raise UsageError("choose_into= picks among several probe runs: give probes=[run_a,run_b,...]")
    _check(cfg)
    run = stage_output(cfg.probes, METRICS_NAME, "probe run", "vlactl train-probes")
    table = pd.read_parquet(run / METRICS_NAME)
    known = [f for f in dict.fromkeys(table["feature"]) if f in OUTPUT]
    features = known if cfg.features is None else [str(f) for f in (
        cfg.features if isinstance(cfg.features, (list, ListConfig)) else [cfg.features])]
    unknown = [f for f in features if f not in known]
    if unknown or not features:
        raise UsageError(f"no probes of feature {unknown[0] if unknown else features!r} in {cfg.probes!r}; "
                         f"allowed: {', '.join(known)}")
    units = _units(table, features, bool(cfg.groups))
    if not units:
        raise UsageError(f"{cfg.probes!r} has no probes at layers whose output can move the actions")
    out = resolve_path(cfg.output_dir) if cfg.output_dir else default_output(cfg)
    ensure_writable_dir(out, cfg.output_dir)
    shipped = run.resolve().is_relative_to(SHIPPED_PROBES.resolve())
    if not shipped:
        ensure_writable_dir(run, cfg.probes, key="probes")

    vla, frames, rows, key = policy_and_frames(cfg, load_policy)
    pooling = str(table["pooling"].iloc[0])
    probes = {(layer, feature): load_probe(run / "probes" / probe_filename(layer, feature), model=vla.name,
                                           width=vla.layer_width(layer), pooling=pooling)
              for layer, group, feature in units if not group}
    members = {(name, feature): group_layers(table[table["feature"] == feature], name) if group else [name]
               for name, group, feature in units}
    targets = [float(t) for t in cfg.targets]
    digest = metrics_digest(run)
    key |= {"metrics": digest, "units": units, "targets": targets, "replan_every": vla.replan_every}
    scale = _reading_std(vla, frames, rows, probes, pooling, int(cfg.batch_size))

    def work(index, bar):
        obs = frame_batch(frames, index)
        plain = predict_chunk(vla, obs)
        unpushed = {c: _predicted(plain, c, vla.replan_every) for c in LEAK_COLUMNS}
        points = []
        for name, group, feature in units:
            for target in targets:
                constraints = [Constraint(probes[layer, feature], target * scale[layer, feature],
                                          target * scale[layer, feature], relative=True)
                               for layer in members[name, feature]]
                with Steerer(vla, constraints, pooling=pooling) as steer:
                    chunk = predict_chunk(vla, obs, steer)
                log = pd.DataFrame(steer.log)
                points.append(pd.DataFrame({
                    "layer": name, "group": group, "feature": feature, "target": target, "frame": index,
                    "before": _predicted(plain, feature, vla.replan_every),
                    "after": _predicted(chunk, feature, vla.replan_every),
                    "u_norm": log.groupby("row")["u_norm"].mean().reindex(range(len(index))).to_numpy(),
                    **{f"shift_{c}": _predicted(chunk, c, vla.replan_every) - unpushed[c] for c in LEAK_COLUMNS},
                }))
                bar.update(len(index))
        return [pd.concat(points, ignore_index=True)]

    (points,) = run_batches(out, key, (POINTS_NAME,), rows, cfg.batch_size, work, f"controllability {vla.name}",
                            per_frame=len(units) * len(targets))
    result = _summary(points, vla.layer_names(), table)
    result["metrics_digest"] = digest
    atomic_write_parquet(out / POINTS_NAME, points)
    atomic_write_parquet(out / CONTROLLABILITY_NAME, result)
    save_config(cfg, out)
    if shipped:  # the shipped table picks every default rollout's layers: only `make probes` rebuilds it
        also = f"; the shipped probes' own table in {run} is left as `make probes` made it"
    else:
        atomic_write_parquet(run / CONTROLLABILITY_NAME, _merged(run / CONTROLLABILITY_NAME, result))
        also = f" and {run / CONTROLLABILITY_NAME}"
    print(f"wrote {out / CONTROLLABILITY_NAME} ({len(result)} rows){also}", file=sys.stderr)
    return out


def _measure_candidates(cfg: DictConfig, load_policy=None) -> Path:
    from vlactl.steering.choose import choose_probes

    runs = [str(run) for run in cfg.probes]
    if len(runs) < 2 or len(set(runs)) < len(runs):
        raise UsageError(f"probes= as a list needs two or more different probe runs, got {runs}")
    out = None
    for run in runs:
        one = OmegaConf.merge(cfg, {"probes": run, "choose_into": None,
                                    "output_dir": f"{cfg.output_dir}/{Path(run).name}" if cfg.output_dir else None})
        out = run_controllability(one, load_policy)
    if cfg.choose_into is None:
        return out
    chosen = resolve_path(cfg.choose_into)
    choose_probes([stage_output(run, METRICS_NAME, "probe run", "vlactl train-probes") for run in runs], chosen)
    return chosen


def _reading_std(vla, frames, rows: np.ndarray, probes: dict, pooling: str, batch_size: int) -> dict:
    """(layer, feature) -> the standard deviation of the probe's unsteered reading over the frames (every forward
    through its layer): the unit the targets are given in, so that probes of any family (a ridge probe shrunk by its
    penalty reads in a fraction of the feature's units) are pushed by the same share of their natural spread."""
    readings: dict[tuple[str, str], list[float]] = {}
    for feature in dict.fromkeys(f for _, f in probes):
        watch = [Constraint(probe) for (_, f), probe in probes.items() if f == feature]
        for start in range(0, len(rows), batch_size):
            with Steerer(vla, watch, pooling=pooling) as steer:
                predict_chunk(vla, frame_batch(frames, rows[start : start + batch_size]), steer)
            for entry in steer.log:
                readings.setdefault((entry["layer"], feature), []).append(entry["before"])
    return {unit: float(np.std(values)) or 1.0 for unit, values in readings.items()}


def _merged(path: Path, result: pd.DataFrame) -> pd.DataFrame:
    """The probe run's table with this run's features replaced: features measured apart (with targets of their own
    units) add up there, as long as the probes were not retrained in between."""
    if not path.is_file():
        return result
    earlier = pd.read_parquet(path)
    keep = (earlier["metrics_digest"] == result["metrics_digest"].iloc[0]) & ~earlier["feature"].isin(result["feature"])
    return pd.concat([earlier[keep], result], ignore_index=True)


def _predicted(chunk: np.ndarray, feature: str, replan_every: int) -> np.ndarray:
    """The feature's predicted action value per row of chunks [B, T, 7]: the mean over the executed actions."""
    executed = chunk[:, :replan_every]
    if OUTPUT[feature] == "speed":
        return np.linalg.norm(executed[..., :3], axis=-1).mean(1)
    return executed[..., ACTION_FEATURES.index(OUTPUT[feature])].mean(1)


def _summary(points: pd.DataFrame, layers: list[str], metrics: pd.DataFrame) -> pd.DataFrame:
    """One row per layer or group and feature: gain, R², cross share, mean ||u||, frames."""
    order = {name: i for i, name in enumerate([*layers, *GROUPS])}
    kinds = metrics.drop_duplicates("feature").set_index("feature")["kind"]
    rows = []
    for (name, feature), pts in points.groupby(["layer", "feature"], sort=False):
        x = pts["target"].to_numpy()
        gain, r2 = _line(x, (pts["after"] - pts["before"]).to_numpy())
        moved = set(LEAK_COLUMNS) & {OUTPUT[feature], *(TRANSLATION if OUTPUT[feature] == "speed" else ())}
        leaks = {f"leak_{c}": _line(x, pts[f"shift_{c}"].to_numpy())[0] if f"shift_{c}" in pts and c not in moved
                 else np.nan for c in LEAK_COLUMNS}
        cross = np.nan
        if feature in BINARY:
            wrong_side = pts["before"] * pts["target"] <= 0
            if wrong_side.any():
                cross = float((pts["after"] * pts["target"] > 0)[wrong_side].mean())
        rows.append({"layer": name, "group": bool(pts["group"].iloc[0]), "layer_index": order[name],
                     "feature": feature, "kind": kinds[feature], "output": OUTPUT[feature], "gain": gain, "r2": r2,
                     "cross_share": cross, **leaks, "u_norm": float(pts["u_norm"].mean()),
                     "n_frames": pts["frame"].nunique(), "n_targets": pts["target"].nunique()})
    return pd.DataFrame(rows)


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The least-squares slope of y on x and its R² (NaN where either does not vary)."""
    dx, dy = x - x.mean(), y - y.mean()
    sxx, syy = (dx * dx).sum(), (dy * dy).sum()
    slope = float((dx * dy).sum() / sxx) if sxx > 0 else np.nan
    return slope, float((dx * dy).sum() ** 2 / (sxx * syy)) if sxx > 0 and syy > 0 else np.nan
