"""`vlactl train-probes`: activation folder in, probe folder out (docs/formats.md). The math lives in the modules
beside this one; this file reads, checks, batches layers to bound memory, and writes."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from tqdm import tqdm

from vlactl.config import REPO_ROOT, resolve_path, save_config
from vlactl.errors import UsageError, check_choice, check_device, check_positive
from vlactl.io import atomic_write_json, atomic_write_parquet, ensure_writable_dir, keyed_parts
from vlactl.steering.activations import FEATURES, ActivationStore
from vlactl.steering.directions import FAMILIES
from vlactl.steering.metrics import classification_metrics, regression_metrics, robustness
from vlactl.steering.probe_file import save_probe
from vlactl.steering.probes import LOGISTIC, REGRESSION, ProbeSettings, fit_probes
from vlactl.steering.split import episode_folds, split_by_episode

# Binary features (SPEC.md §2) and what label 1 means; the controller steers their logit.
BINARY = {
    "gripper": ("gripper < 0.5 (closed)", lambda v: v < 0.5),
    "gripper_action": ("gripper_action > 0 (close)", lambda v: v > 0),
}
PROBE_PROVENANCE = "provenance.json"  # a probe run's model, weights, dataset and demo constants
METRICS_NAME = "metrics.parquet"
# The settings that change a probe or its metrics (not where or how fast it is fitted); with the activation folder
# they key the finished layers an interrupted run resumes from.
RESULT_KEYS = ("frames", "test_fraction", "cv_folds", "seed", "family", "ridge_grid", "logistic_l2", "newton_steps",
               "robustness_norms", "robustness_directions", "robustness_frames")


def _part(out: Path, layer: str) -> Path:
    """A finished layer's metrics rows, what an interrupted run resumes from (`vlactl.io.keyed_parts`)."""
    return out / "parts" / f"{layer}.parquet"


def probe_filename(layer: str, feature: str) -> str:
    return f"{layer}__{feature}.safetensors"


def _chosen(name: str, value, allowed: list[str]) -> list[str]:
    if value == "all":
        return list(allowed)
    chosen = [str(v) for v in value] if isinstance(value, (list, ListConfig)) else [str(value)]
    unknown = [v for v in chosen if v not in allowed]
    if unknown or not chosen:
        raise UsageError(f"unknown {name} {unknown[0] if unknown else chosen!r}; allowed: all, {', '.join(allowed)}")
    return chosen


def _targets(labels: pd.DataFrame, features: list[str]) -> tuple[np.ndarray, list[str]]:
    y = np.empty((len(labels), len(features)))
    kinds = []
    for i, name in enumerate(features):
        values = labels[name].to_numpy(dtype=np.float64)
        if not np.isfinite(values).all():
            raise UsageError(f"feature {name!r} has missing or non-finite labels in the activation folder")
        y[:, i] = BINARY[name][1](values) if name in BINARY else values
        kinds.append(LOGISTIC if name in BINARY else REGRESSION)
    return y, kinds


def _check(cfg: DictConfig) -> None:
    if cfg.activations is None:
        raise UsageError("which activations? pass activations=<folder written by `vlactl collect`>")
    if not 0 < cfg.test_fraction < 1:
        raise UsageError(f"test_fraction must be in (0, 1), got {cfg.test_fraction!r}")
    if cfg.cv_folds < 2:
        raise UsageError(f"cv_folds must be >= 2, got {cfg.cv_folds!r}")
    for key in ("layer_batch", "threads", "newton_steps", "robustness_directions", "robustness_frames"):
        check_positive(key, cfg[key])
    if not cfg.ridge_grid or min(cfg.ridge_grid) <= 0:
        raise UsageError(f"ridge_grid must be a non-empty list of penalties > 0, got {list(cfg.ridge_grid or [])}")
    check_positive("logistic_l2", cfg.logistic_l2)
    check_choice("family", cfg.family, FAMILIES)
    check_device("device", cfg.device)


def run_train_probes(cfg: DictConfig) -> Path:
    _check(cfg)
    store = ActivationStore(resolve_path(cfg.activations))
    layers = _chosen("layer", cfg.layers, store.layers)
    features = _chosen("feature", cfg.features, list(FEATURES))
    labels = store.labels
    episodes = labels["episode"].to_numpy()
    n_episodes = len(np.unique(episodes))
    if n_episodes < cfg.cv_folds + 1:
        raise UsageError(
            f"{n_episodes} episodes in {cfg.activations!r}: too few to hold out test episodes and make "
            f"{cfg.cv_folds} cross-validation folds; collect at least {cfg.cv_folds + 2}"
        )
    train, test = split_by_episode(episodes, cfg.test_fraction, cfg.seed)
    if cfg.frames:  # after the split, so that the episodes held out do not depend on the query
        chosen = _frames(labels, cfg.frames)
        train, test = train[chosen[train]], test[chosen[test]]
        if not len(test):
            raise UsageError(f"frames={cfg.frames!r} keeps no frame of the held-out episodes")
    if len(np.unique(episodes[train])) < cfg.cv_folds:
        raise UsageError(f"too few training episodes for cv_folds={cfg.cv_folds}; lower test_fraction or cv_folds")
    folds = episode_folds(episodes[train], cfg.cv_folds, cfg.seed)
    y, kinds = _targets(labels, features)
    keep = [i for i, kind in enumerate(kinds) if kind == REGRESSION or 0 < y[train, i].mean() < 1]
    for i in sorted(set(range(len(features))) - set(keep)):
        print(f"warning: skipping {features[i]}: one class only in the training episodes", file=sys.stderr)
    features, kinds, y = [features[i] for i in keep], [kinds[i] for i in keep], y[:, keep]
    if not features:
        raise UsageError("no feature left to probe: every chosen binary feature has one class only in training")

    run = cfg.run or resolve_path(cfg.activations).name
    out = resolve_path(cfg.output_dir) if cfg.output_dir else REPO_ROOT / "outputs" / "probes" / run
    ensure_writable_dir(out, requested=out)
    torch.set_num_threads(cfg.threads)
    settings = ProbeSettings(
        ridge_grid=tuple(float(v) for v in cfg.ridge_grid), logistic_l2=float(cfg.logistic_l2),
        newton_steps=int(cfg.newton_steps), family=str(cfg.family),
    )
    # a collect resumed since adds frames, and so changes the split; device, threads and layer batch change nothing
    resolved = OmegaConf.to_container(cfg, resolve=True)
    key = {"activations": str(store.folder.resolve()), "meta": store.meta, "features": features,
           **{k: resolved[k] for k in RESULT_KEYS}}
    keyed_parts(out, key, results=(METRICS_NAME, "probes"))
    todo = [name for name in layers if not _part(out, name).is_file()]
    if len(todo) < len(layers):
        print(f"resuming: {len(layers) - len(todo)} of {len(layers)} layers already fitted in {out}", file=sys.stderr)
    by_width: dict[int, list[str]] = {}
    for name in todo:
        by_width.setdefault(store.widths[name], []).append(name)
    with tqdm(total=len(layers), initial=len(layers) - len(todo), desc="train-probes", unit="layer") as bar:
        for group in by_width.values():
            for start in range(0, len(group), cfg.layer_batch):
                batch = group[start : start + cfg.layer_batch]
                bar.set_postfix_str(", ".join(batch))
                _fit_batch(cfg, store, batch, features, kinds, y, train, test, folds, settings, out)
                bar.update(len(batch))
    order = {name: i for i, name in enumerate(FEATURES)}
    table = pd.concat([pd.read_parquet(_part(out, name)) for name in layers])
    table = table.sort_values(["feature", "layer_index"], key=lambda c: c.map(order) if c.name == "feature" else c)
    table = table.reset_index(drop=True)
    atomic_write_parquet(out / METRICS_NAME, table)
    atomic_write_json(out / PROBE_PROVENANCE, provenance(store))
    save_config(cfg, out)
    _print_best(table)
    print(f"wrote {out / METRICS_NAME} and {len(table)} probes under {out / 'probes'}", file=sys.stderr)
    return out


def provenance(store: ActivationStore) -> dict:
    """What the probes were fitted on: the model and its weights' fingerprint (a rollout refuses them for other
    weights), the dataset, and, when the dataset is on disk, the constants constraints are stated in
    (vlactl.data.motion), so the probe run alone can steer."""
    from vlactl.data import motion

    info = store.meta.get("info", {})
    record = {"model": store.meta.get("model"), "weights": info.get("weights"), "dataset": info.get("dataset")}
    dataset = Path(info["dataset"]) if info.get("dataset") else None
    if dataset is not None and (dataset / "meta").is_dir():
        record.update(speed_threshold=motion.speed_median(dataset), metres_per_unit=motion.metres_per_unit(dataset))
    return record


def _frames(labels: pd.DataFrame, query: str) -> np.ndarray:
    """Boolean mask of the frames a pandas query on the label table keeps, e.g. "frame_index < 25"."""
    try:
        mask = labels.eval(str(query))
    except Exception as err:  # pandas raises many kinds for a bad expression
        raise UsageError(f"frames={query!r} is not a query on the label columns ({', '.join(labels.columns)}): "
                         f"{str(err).splitlines()[0] if str(err) else type(err).__name__}") from None
    if getattr(mask, "dtype", None) != bool or len(mask) != len(labels):
        raise UsageError(f"frames={query!r} must be a true/false condition per frame, e.g. \"frame_index < 25\"")
    return mask.to_numpy()


def _fit_batch(cfg, store, batch, features, kinds, y, train, test, folds, settings, out) -> None:
    """Fit a batch of layers; write each layer's probe files, then its metrics part (which marks it done)."""
    x = store.load(batch)
    probes = fit_probes(x.to(cfg.device), y, kinds, train, folds, settings).to("cpu")
    x_test = x[:, torch.as_tensor(test)]
    del x
    readings = probes.readings(x_test)
    y_test = torch.as_tensor(y[test])
    reg = [i for i, k in enumerate(kinds) if k == REGRESSION]
    log = [i for i, k in enumerate(kinds) if k == LOGISTIC]
    per_feature = {}
    if reg:
        m = regression_metrics(readings[..., reg], y_test[:, reg], torch.as_tensor(y[train][:, reg].mean(0)))
        per_feature.update({(key, f): value[:, j] for key, value in m.items() for j, f in enumerate(reg)})
    if log:
        majority = torch.as_tensor((y[train][:, log].mean(0) > 0.5).astype(np.float64))
        m = classification_metrics(readings[..., log], y_test[:, log], majority)
        per_feature.update({(key, f): value[:, j] for key, value in m.items() for j, f in enumerate(log)})
    robust = robustness(
        probes, x_test, list(cfg.robustness_norms), cfg.robustness_directions, cfg.robustness_frames, cfg.seed,
        layer_ids=[store.layers.index(layer) for layer in batch],
    )
    for li, layer in enumerate(batch):
        rows = []
        for fi, feature in enumerate(features):
            row = {
                "model": store.model, "pooling": store.pooling, "layer": layer,
                "layer_index": store.layers.index(layer), "steerable": layer in store.steerable,
                "feature": feature, "kind": kinds[fi], "family": settings.family, "n_train": len(train),
                "n_test": len(test),
                "penalty": float(probes.lam[li, fi]), "cv_r2": float(probes.cv_r2[li, fi]),
                "weight_norm": float(probes.weight[li, fi].norm()),
            }
            row.update({key: float(value[li]) for (key, f), value in per_feature.items() if f == fi})
            row.update({key: float(value[li, fi]) for key, value in robust.items()})
            row["probe"] = f"probes/{probe_filename(layer, feature)}"
            positive = BINARY[feature][0] if feature in BINARY else ""
            probe = probes.probe(li, fi, feature=feature, layer=layer, model=store.model, pooling=store.pooling,
                                 positive=positive, metrics={k: v for k, v in row.items() if isinstance(v, float)})
            save_probe(probe, out / row["probe"])
            rows.append(row)
        atomic_write_parquet(_part(out, layer), pd.DataFrame(rows))


def steerable_rows(table: pd.DataFrame) -> pd.DataFrame:
    """The rows of layers whose output can move the actions (all rows of a table without a `steerable` column)."""
    return table[table["steerable"]] if "steerable" in table else table


def best_layers(table: pd.DataFrame, steerable: bool = False) -> pd.DataFrame:
    """One row per feature: the layer whose probe scores best on the test episodes; with `steerable`, among the layers
    whose output can move the actions (where to steer it)."""
    if steerable:
        table = steerable_rows(table)
    def column(name):  # a run of only regression or only logistic probes lacks the other kind's metrics
        return table[name] if name in table else pd.Series(np.nan, index=table.index)

    score = column("r2").where(table["kind"] == REGRESSION, column("balanced_accuracy"))
    best = table.assign(_score=score.fillna(-np.inf)).sort_values("_score", kind="stable").groupby("feature").tail(1)
    order = {f: i for i, f in enumerate(dict.fromkeys(table["feature"]))}
    return best.sort_values("feature", key=lambda s: s.map(order)).drop(columns="_score")


def _print_best(table: pd.DataFrame) -> None:
    """Best layer per feature (by test R^2 / balanced accuracy, as the paper's Fig. 1) against its baseline."""
    for _, best in best_layers(table).iterrows():
        if best["kind"] == REGRESSION:
            print(f"{best['feature']:15s} best {best['layer']:14s} R2 {best['r2']:6.3f}  MAE {best['mae']:.4g} "
                  f"(train-mean baseline {best['baseline_mae']:.4g})")
        else:
            print(f"{best['feature']:15s} best {best['layer']:14s} acc {best['accuracy']:.3f} balanced "
                  f"{best['balanced_accuracy']:.3f} (majority baseline {best['baseline_accuracy']:.3f})")
