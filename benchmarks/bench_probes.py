"""Probe fitting for all layers x features at once on torch vs a scikit-learn loop over layers doing the same work.

Both sides: standardise with the training split's statistics; ridge for the continuous features with the penalty
chosen per layer x feature from the same grid by the same episode-grouped folds; L2 logistic regression (C = 1/l2)
for the binary ones; test metrics with the same formulas. Prints wall and CPU times, their ratio, and the largest
difference in any test metric. With --threads N both sides use N cores as each does best: torch splits the layers
among N threads (vlactl.steering.probes.fit_probes), scikit-learn's loop runs in N worker processes.

    .venv/bin/python benchmarks/bench_probes.py            # sized like a real run: 24 layers, 20000 frames, d=256
    .venv/bin/python benchmarks/bench_probes.py --quick    # a few seconds
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from joblib import Parallel, delayed
from sklearn.linear_model import LogisticRegression, Ridge
from sklearn.preprocessing import StandardScaler
from threadpoolctl import threadpool_limits

from vlactl.steering.metrics import classification_metrics, regression_metrics
from vlactl.steering.probes import LOGISTIC, REGRESSION, ProbeSettings, fit_probes
from vlactl.steering.split import episode_folds, split_by_episode
from vlactl.steering.synthetic import planted_activations


def metrics(pred: torch.Tensor, y: np.ndarray, y_train: np.ndarray, kinds: list[str]) -> dict[str, torch.Tensor]:
    """Test metrics [L, F_kind] of readings pred [L, n, F] (logits for logistic features)."""
    reg = [i for i, k in enumerate(kinds) if k == REGRESSION]
    log = [i for i, k in enumerate(kinds) if k == LOGISTIC]
    yt = torch.as_tensor(y, dtype=torch.float64)
    out = regression_metrics(pred[..., reg], yt[:, reg], torch.as_tensor(y_train[:, reg].mean(0)))
    majority = torch.as_tensor((y_train[:, log].mean(0) > 0.5).astype(float))
    return {**out, **classification_metrics(pred[..., log], yt[:, log], majority)}


def torch_side(x, y, kinds, train, test, folds, settings, device):
    probes = fit_probes(x.to(device), y, kinds, train, folds, settings).to("cpu")  # the copy waits for the GPU
    return metrics(probes.readings(x[:, torch.as_tensor(test)]), y[test], y[train], kinds)


def sklearn_layer(x, y, kinds, train, test, folds, settings):
    """One layer's probes, the same work, on one BLAS thread -> test readings [n_test, F] and the CPU seconds of the
    ridge and logistic parts."""
    reg = [i for i, k in enumerate(kinds) if k == REGRESSION]
    log = [i for i, k in enumerate(kinds) if k == LOGISTIC]
    grid = settings.ridge_grid
    preds = np.empty((len(test), len(kinds)))
    with threadpool_limits(1):
        start = time.process_time()
        scaler = StandardScaler().fit(x[train])
        z_tr, z_te = scaler.transform(x[train]), scaler.transform(x[test])
        y_tr = y[train][:, reg]
        cv_sse = np.zeros((len(grid), len(reg)))
        for g, alpha in enumerate(grid):
            for k in range(folds.max() + 1):
                held = folds == k
                model = Ridge(alpha=alpha).fit(z_tr[~held], y_tr[~held])
                cv_sse[g] += ((model.predict(z_tr[held]) - y_tr[held]) ** 2).sum(0)
        best = cv_sse.argmin(0)
        for g in np.unique(best):
            cols = np.flatnonzero(best == g)
            model = Ridge(alpha=grid[g]).fit(z_tr, y_tr[:, cols])
            preds[:, np.asarray(reg)[cols]] = model.predict(z_te).reshape(len(test), -1)
        middle = time.process_time()
        for i in log:
            model = LogisticRegression(C=1 / settings.logistic_l2, max_iter=1000).fit(z_tr, y[train, i])
            preds[:, i] = model.decision_function(z_te)
    return preds, middle - start, time.process_time() - middle


def sklearn_side(x, y, kinds, train, test, folds, settings, spent, workers):
    """A loop over layers, run by `workers` processes (joblib, as one would spread it over cores: scikit-learn's small
    products run slower with BLAS threads than without); `spent` collects the CPU seconds of its two parts."""
    layers = Parallel(n_jobs=workers)(
        delayed(sklearn_layer)(x[layer], y, kinds, train, test, folds, settings) for layer in range(x.shape[0])
    )
    spent["ridge"] += sum(r for _, r, _ in layers)
    spent["logistic"] += sum(lo for _, _, lo in layers)
    return metrics(torch.as_tensor(np.stack([p for p, _, _ in layers])), y[test], y[train], kinds)


def timed(fn, *args):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layers", type=int, default=24)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--frames", type=int, default=100, help="frames per episode")
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--features", type=int, default=16)
    ap.add_argument("--binary", type=int, default=2, help="how many of the features are binary (logistic probes)")
    ap.add_argument("--threads", type=int, default=1,
                    help="cores for both sides: torch's threads (it splits the layers among them); scikit-learn's "
                         "worker processes, each on its share of the layers with one BLAS thread")
    ap.add_argument("--device", default="cpu", help="where torch fits (cuda: a GPU against scikit-learn on the CPU)")
    ap.add_argument("--quick", action="store_true", help="6 layers, 40 episodes, d=64")
    args = ap.parse_args()
    if args.quick:
        args.layers, args.episodes, args.width = 6, 40, 64
    torch.set_num_threads(args.threads)

    data = planted_activations(args.layers, args.episodes, args.frames, args.width, args.features, seed=0)
    y = data.latent.copy()
    kinds = [REGRESSION] * (args.features - args.binary) + [LOGISTIC] * args.binary
    y[:, args.features - args.binary:] = y[:, args.features - args.binary:] < 0
    train, test = split_by_episode(data.episodes, 0.2, seed=0)
    folds = episode_folds(data.episodes[train], 3, seed=0)
    settings = ProbeSettings()
    n = len(data.episodes)
    print(f"{args.layers} layers x {args.features} features ({args.binary} binary), {n} frames "
          f"({len(train)} train), d={args.width}, {args.threads} thread(s), "
          f"penalty grid of {len(settings.ridge_grid)}, torch on {args.device}")

    with threadpool_limits(args.threads):
        xt = torch.from_numpy(data.x)
        if args.device != "cpu":  # the first call on a GPU pays for its context and kernels' start-up
            torch_side(xt, y, kinds, train, test, folds, settings, args.device)
        ours, t_wall, t_cpu = timed(torch_side, xt, y, kinds, train, test, folds, settings, args.device)
        reg = [i for i, k in enumerate(kinds) if k == REGRESSION]
        _, r_wall, r_cpu = timed(
            torch_side, xt, y[:, reg], [REGRESSION] * len(reg), train, test, folds, settings, args.device
        )
        spent = {"ridge": 0.0, "logistic": 0.0}
        # start the workers (and their imports) before the clock: one layer each
        sklearn_side(data.x[: args.threads], y, kinds, train, test, folds, settings, dict(spent), args.threads)
        theirs, s_wall, _ = timed(sklearn_side, data.x, y, kinds, train, test, folds, settings, spent, args.threads)
    s_cpu = spent["ridge"] + spent["logistic"]  # in the workers when there are several

    # the parts are compared in CPU time on the CPU (both sides single-threaded by default), in wall time on a GPU
    clock = "cpu" if args.device == "cpu" else "wall"
    t_all, t_ridge = (t_cpu, r_cpu) if clock == "cpu" else (t_wall, r_wall)
    print(f"torch    wall {t_wall:7.2f} s   cpu {t_cpu:7.2f} s   (ridge part alone: {clock} {t_ridge:.2f} s)")
    print(f"sklearn  wall {s_wall:7.2f} s   cpu {s_cpu:7.2f} s   (ridge {spent['ridge']:.2f} s, "
          f"logistic {spent['logistic']:.2f} s)")
    print(f"ratio    wall {s_wall / t_wall:7.1f} x   cpu {s_cpu / t_cpu:7.1f} x   (target >= 20x); "
          f"ridge part {spent['ridge'] / t_ridge:.1f} x, logistic part {spent['logistic'] / (t_all - t_ridge):.1f} x")
    for key in ("mae", "r2", "accuracy", "balanced_accuracy"):
        diff = (ours[key] - theirs[key]).abs()
        scale = theirs["baseline_mae"].abs() if key == "mae" else 1.0
        print(f"max |difference| {key:18s} {np.nanmax((diff / scale).numpy()):.2e}"
              + ("  (relative to the baseline MAE)" if key == "mae" else "  (absolute)"))


if __name__ == "__main__":
    main()
