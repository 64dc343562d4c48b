"""Steering probes chosen by what they do: of several probe runs on the same activations (families or penalties,
`vlactl train-probes family=...`), each feature's probes are taken from the run whose push moves the model's own
predicted feature most and most consistently (the largest |gain| x R² of any layer or group in its
`vlactl controllability` table, gains per standard deviation of the reading, so runs compare). The chosen probes,
their metrics rows and controllability rows go into one probe run folder that `vlactl rollout probes=` reads like
any other; `choice.parquet` there keeps every candidate's score."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pandas as pd

from vlactl.errors import UsageError
from vlactl.io import atomic_write_parquet, ensure_writable_dir
from vlactl.steering.controllability import (CONTROLLABILITY_NAME, controllability_rows, controllability_score,
                                             metrics_digest)
from vlactl.steering.train_probes import METRICS_NAME, PROBE_PROVENANCE

CHOICE_NAME = "choice.parquet"


def family_of(run: Path) -> str:
    table = pd.read_parquet(run / METRICS_NAME)
    return str(table["family"].iloc[0]) if "family" in table else "fit"  # runs from before families were fitted


def candidate_scores(runs: list[Path]) -> pd.DataFrame:
    """One row per candidate run and feature measured in all of them: its best unit and that unit's score."""
    features = None
    for run in runs:
        if not (run / CONTROLLABILITY_NAME).is_file():
            raise UsageError(f"{str(run)!r} has no controllability table; run `vlactl controllability probes={run}`")
        measured = set(pd.read_parquet(run / CONTROLLABILITY_NAME, columns=["feature"])["feature"])
        features = measured if features is None else features & measured
    rows, families = [], {run: family_of(run) for run in runs}
    for feature in sorted(features or ()):
        for run in runs:
            table = controllability_rows(run, feature)
            if table is None:  # retrained since it was measured (a warning was printed)
                raise UsageError(f"the controllability table of {str(run)!r} is out of date; re-run it")
            score = controllability_score(table)
            best = table.loc[score.idxmax()]
            rows.append({"feature": feature, "run": str(run), "family": families[run], "layer": best["layer"],
                         "gain": float(best["gain"]), "r2": float(best["r2"]), "score": float(score.max())})
    if not rows:
        raise UsageError(f"no feature is measured in every candidate run ({', '.join(map(str, runs))})")
    return pd.DataFrame(rows)


def choose_probes(runs: list[Path], out: Path) -> pd.DataFrame:
    """Assemble the best run's probes of each feature into `out` (replaced whole); returns the choice table."""
    scores = candidate_scores(runs)
    keys = [pd.read_parquet(run / METRICS_NAME, columns=["model", "pooling"]).iloc[0].tolist() for run in runs]
    if any(key != keys[0] for key in keys):
        raise UsageError(f"the candidate probe runs read different models or poolings: {keys}")
    winners = scores.loc[scores.groupby("feature")["score"].idxmax()]
    ensure_writable_dir(out.parent, str(out.parent))
    staging = out.with_name(out.name + ".new")
    shutil.rmtree(staging, ignore_errors=True)
    (staging / "probes").mkdir(parents=True)
    metrics, control = [], []
    for _, win in winners.iterrows():
        run = Path(win["run"])
        rows = pd.read_parquet(run / METRICS_NAME)
        rows = rows[rows["feature"] == win["feature"]]
        for probe in rows["probe"]:
            shutil.copy2(run / probe, staging / probe)
        metrics.append(rows)
        control.append(controllability_rows(run, win["feature"]))
    for name in (PROBE_PROVENANCE, "config.yaml"):
        if (Path(winners["run"].iloc[0]) / name).is_file():
            shutil.copy2(Path(winners["run"].iloc[0]) / name, staging / name)
    atomic_write_parquet(staging / METRICS_NAME, pd.concat(metrics, ignore_index=True))
    digest = metrics_digest(staging)  # the assembled table is what its controllability rows now describe
    atomic_write_parquet(staging / CONTROLLABILITY_NAME, pd.concat(control, ignore_index=True).assign(
        metrics_digest=digest))
    scores = scores.assign(chosen=scores.index.isin(winners.index))
    atomic_write_parquet(staging / CHOICE_NAME, scores)
    shutil.rmtree(out, ignore_errors=True)
    staging.rename(out)
    for _, win in winners.iterrows():
        print(f"{win['feature']:15s} {win['family']:10s} from {win['run']} (best {win['layer']}, gain "
              f"{win['gain']:.3g}, R² {win['r2']:.2f})", file=sys.stderr)
    return scores
