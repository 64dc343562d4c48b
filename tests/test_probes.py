"""Probe fitting on synthetic activations with features planted in known layers: recovered where planted, absent
elsewhere; the batched solvers agree with direct ones; the split never shares an episode."""

import dataclasses

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from vlactl.steering.directions import direction, partial_directions
from vlactl.steering.logistic import fit_logistic
from vlactl.steering.metrics import classification_metrics, regression_metrics, robustness
from vlactl.steering.probes import LOGISTIC, REGRESSION, ProbeSettings, fit_probes
from vlactl.steering.split import episode_folds, split_by_episode
from vlactl.steering.synthetic import planted_activations


@pytest.fixture(scope="module")
def planted():
    data = planted_activations(n_layers=6, n_episodes=40, frames=40, d=24, n_features=4, planted_every=2, seed=3)
    y = data.latent.copy()
    y[:, 3] = y[:, 3] < 0  # the last feature is binary
    kinds = [REGRESSION] * 3 + [LOGISTIC]
    train, test = split_by_episode(data.episodes, 0.25, seed=0)
    folds = episode_folds(data.episodes[train], 3, seed=0)
    probes = fit_probes(torch.from_numpy(data.x), y, kinds, train, folds)
    readings = probes.readings(torch.from_numpy(data.x)[:, torch.as_tensor(test)])
    return data, y, train, test, folds, probes, readings


def test_planted_features_are_recovered_and_absent_ones_are_not(planted):
    data, y, train, test, _, _, readings = planted
    m = regression_metrics(readings[..., :3], torch.as_tensor(y[test, :3]), torch.as_tensor(y[train, :3].mean(0)))
    here = data.planted[:, :3]
    assert bool((m["r2"][torch.as_tensor(here)] > 0.8).all()), m["r2"]
    assert bool((m["r2"][torch.as_tensor(~here)].abs() < 0.15).all()), m["r2"]
    assert bool((m["mae"][torch.as_tensor(here)] < 0.5 * m["baseline_mae"][torch.as_tensor(here)]).all())


def test_logistic_probes_beat_the_majority_class_where_planted(planted):
    data, y, train, test, _, _, readings = planted
    majority = torch.tensor([float(y[train, 3].mean() > 0.5)])
    c = classification_metrics(readings[..., 3:], torch.as_tensor(y[test, 3:]), majority)
    here = torch.as_tensor(data.planted[:, 3])
    assert bool((c["accuracy"][here, 0] > c["baseline_accuracy"][here, 0] + 0.2).all()), c["accuracy"]
    assert bool((c["balanced_accuracy"][here, 0] > 0.8).all())


@settings(max_examples=50, deadline=None)
@given(st.integers(2, 60), st.integers(1, 30), st.floats(0.05, 0.9), st.integers(0, 1000))
def test_split_and_folds_keep_episodes_whole(n_episodes, frames, fraction, seed):
    episodes = np.repeat(np.random.default_rng(seed).permutation(n_episodes * 3)[:n_episodes], frames)
    train, test = split_by_episode(episodes, fraction, seed)
    assert len(train) and len(test) and len(train) + len(test) == len(episodes)
    assert not set(episodes[train]) & set(episodes[test])
    again = split_by_episode(episodes, fraction, seed)
    assert np.array_equal(train, again[0]) and np.array_equal(test, again[1])
    k = min(3, len(set(episodes[train])))
    folds = episode_folds(episodes[train], k, seed)
    for e in set(episodes[train]):
        assert len(set(folds[episodes[train] == e])) == 1
    assert set(folds) == set(range(k))


def _direct_ridge(x, y, lam):
    """Ridge on standardised x with an unpenalised intercept, by one dense solve; returns raw-space (w, b)."""
    mean, std = x.mean(0), x.std(0)
    z = (x - mean) / std
    zc, yc = z - z.mean(0), y - y.mean()
    w = np.linalg.solve(zc.T @ zc + lam * np.eye(x.shape[1]), zc.T @ yc)
    return w / std, y.mean() - (w / std) @ mean


@pytest.mark.parametrize("d, episodes", [(12, 30), (80, 6)], ids=["primal d<n", "kernel d>n"])
def test_ridge_equals_a_direct_solve_at_the_chosen_penalty(d, episodes):
    data = planted_activations(n_layers=3, n_episodes=episodes, frames=10, d=d, n_features=2, seed=1)
    train = np.arange(len(data.episodes))
    folds = episode_folds(data.episodes, 3, seed=0)
    x = torch.from_numpy(data.x).double()
    probes = fit_probes(x.float(), data.latent, [REGRESSION] * 2, train, folds)
    for layer in range(3):
        for f in range(2):
            w, b = _direct_ridge(x[layer].numpy(), data.latent[:, f], float(probes.lam[layer, f]))
            np.testing.assert_allclose(probes.weight[layer, f].numpy(), w, rtol=1e-3, atol=1e-5 * np.abs(w).max())
            np.testing.assert_allclose(float(probes.bias[layer, f]), b, rtol=1e-3, atol=1e-4)


def test_logistic_reaches_the_same_optimum_as_scikit_learn():
    from sklearn.linear_model import LogisticRegression

    data = planted_activations(n_layers=3, n_episodes=30, frames=20, d=10, n_features=1, planted_every=1, seed=2)
    z = torch.from_numpy(data.x)
    z = (z - z.mean(1, keepdim=True)) / z.std(1, keepdim=True)
    y = torch.as_tensor(data.latent[:, 0] < 0.3).double()
    w, b = fit_logistic(z, y, l2=1.0, steps=50, tol=1e-12)
    for layer in range(3):
        ref = LogisticRegression(C=1.0, tol=1e-10, max_iter=10000).fit(z[layer].double().numpy(), y.numpy())
        np.testing.assert_allclose(w[layer].numpy(), ref.coef_[0], rtol=1e-3, atol=1e-4)
        np.testing.assert_allclose(float(b[layer]), ref.intercept_[0], rtol=1e-3, atol=1e-4)


def test_logistic_fits_many_wide_layers_with_two_threads():
    # batched LU solves of this size failed inside MKL with 2 threads; vlactl train-probes threads=2 hit it
    data = planted_activations(n_layers=3, n_episodes=20, frames=30, d=256, n_features=1, planted_every=1, seed=4)
    z = torch.from_numpy(data.x)
    z = (z - z.mean(1, keepdim=True)) / z.std(1, keepdim=True)
    y = torch.as_tensor(data.latent[:, 0] < 0).double()
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        w, b = fit_logistic(z, y, l2=1.0)
    finally:
        torch.set_num_threads(threads)
    accuracy = ((torch.einsum("lnp,lp->ln", z.double(), w) + b[:, None] > 0) == y.bool()).double().mean(1)
    assert (accuracy > 0.9).all()


def test_probe_reading_is_linear_in_the_raw_representation(planted):
    data, _, _, _, _, probes, _ = planted
    probe = probes.probe(1, 0, feature="x", layer="backbone.1", model="m", pooling="prefix")
    x = torch.from_numpy(data.x[1, :5]).double()
    z = (x - probes.mean[1]) / probes.std[1]
    w_std = probe.weight * probes.std[1]  # the standardised-space weights, unfolded
    torch.testing.assert_close(probe.reading(x), z @ w_std + probe.bias + probe.weight @ probes.mean[1])
    batched = probes.readings(torch.from_numpy(data.x[:, :5]))[1, :, 0]  # multiplied in float32
    torch.testing.assert_close(probe.reading(x), batched, rtol=1e-5, atol=1e-5)


def test_robustness_grows_linearly_with_the_perturbation_for_regression(planted):
    data, _, _, test, _, probes, _ = planted
    r = robustness(probes, torch.from_numpy(data.x[:, test]), [0.01, 0.1], directions=8, rows=64)
    torch.testing.assert_close(r["robust_mean_0.1"][:, :3], 10 * r["robust_mean_0.01"][:, :3])
    assert bool((r["robust_max_0.1"] >= r["robust_mean_0.1"]).all())
    assert bool((r["robust_max_0.1"][:, 3] <= 1).all())  # a change of probability


def test_robustness_of_a_layer_does_not_depend_on_its_batch(planted):
    data, _, _, test, _, probes, _ = planted
    x = torch.from_numpy(data.x[:, test])
    together = robustness(probes, x, [0.05], directions=4, rows=32, seed=3)
    last = len(x) - 1
    one = dataclasses.replace(probes, **{name: getattr(probes, name)[last:] for name in probes.TENSORS})
    alone = robustness(one, x[last:], [0.05], directions=4, rows=32, seed=3, layer_ids=[last])
    torch.testing.assert_close(alone["robust_max_0.05"][0], together["robust_max_0.05"][last])


def test_settings_default_grid_is_used(planted):
    *_, probes, _ = planted
    assert set(probes.lam[:, :3].flatten().tolist()) <= set(ProbeSettings().ridge_grid)
    assert bool(probes.cv_r2[:, 3].isnan().all()) and not bool(probes.cv_r2[:, :3].isnan().any())


def test_layers_split_among_threads_give_the_probes_of_one_fit(planted):
    data, y, train, _, folds, _, _ = planted
    x, kinds = torch.from_numpy(data.x), [REGRESSION] * 3 + [LOGISTIC]
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        whole = fit_probes(x, y, kinds, train, folds)
        torch.set_num_threads(4)  # 6 layers in groups of 2, 2, 1, 1
        split = fit_probes(x, y, kinds, train, folds)
        assert torch.get_num_threads() == 4  # restored after the workers
    finally:
        torch.set_num_threads(threads)
    for name in whole.TENSORS:
        torch.testing.assert_close(getattr(split, name), getattr(whole, name), rtol=1e-5, atol=1e-7, equal_nan=True)


class _FactoriesWithoutDevice(torch.overrides.TorchFunctionMode):
    """Records tensor factories called without an explicit device: on a GPU those would land on the CPU."""

    FACTORIES = {torch.zeros, torch.ones, torch.full, torch.empty, torch.tensor, torch.as_tensor, torch.arange,
                 torch.eye, torch.rand, torch.randn, torch.randperm, torch.linspace}

    def __init__(self):
        super().__init__()
        self.calls = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in self.FACTORIES and "device" not in kwargs:
            self.calls.append(func.__name__)
        return func(*args, **kwargs)


@pytest.mark.parametrize("width", [24, 400])  # 400 > 300 training rows: the kernel form
def test_fitting_creates_every_tensor_on_the_activations_device(planted, width):
    # CI has no GPU; a factory without device= is what breaks `train-probes device=cuda`, so catch it here
    data, y, train, _, folds, _, _ = planted
    x = torch.from_numpy(data.x) if width == 24 else torch.randn(2, data.x.shape[1], width)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one fit in this thread: modes are per thread, and a GPU fit never splits its layers
    try:
        with _FactoriesWithoutDevice() as mode:
            fit_probes(x, y, [REGRESSION] * 3 + [LOGISTIC], train[::4], folds[::4])
    finally:
        torch.set_num_threads(threads)
    assert mode.calls == []


def test_probes_move_between_devices_whole(planted):
    probes = planted[5]
    moved = probes.to("meta")  # a device every machine has
    tensors = [f.name for f in dataclasses.fields(probes) if isinstance(getattr(probes, f.name), torch.Tensor)]
    assert len(tensors) == 6 and all(getattr(moved, name).is_meta for name in tensors)
    assert moved.kinds == probes.kinds and not probes.weight.is_meta


@pytest.mark.parametrize("family", ["meandiff", "covariance", "partial"])
def test_steering_families_find_the_planted_direction_and_read_in_feature_units(planted, family):
    data, y, train, test, folds, _, _ = planted
    probes = fit_probes(torch.from_numpy(data.x), y, [REGRESSION] * 3 + [LOGISTIC], train, folds,
                        ProbeSettings(family=family))
    readings = probes.readings(torch.from_numpy(data.x)[:, torch.as_tensor(test)])
    m = regression_metrics(readings[..., :3], torch.as_tensor(y[test, :3]), torch.as_tensor(y[train, :3].mean(0)))
    here = torch.as_tensor(data.planted[:, :3])
    # one direction and its scale, not every weight: less than the fitted probes' 0.8, far above the absent features
    assert bool((m["r2"][here] > 0.3).all()) and bool((m["r2"][~here].abs() < 0.2).all()), m["r2"]
    fitted = probes.readings(torch.from_numpy(data.x)[:, torch.as_tensor(train)])
    slope = [np.polyfit(fitted[li, :, fi].numpy(), y[train, fi], 1)[0] for li, fi in zip(*np.nonzero(here.numpy()))]
    assert np.allclose(slope, 1.0, atol=1e-6), slope  # the fitted scale puts the reading in the feature's units
    assert torch.isnan(probes.lam).all() and torch.isnan(probes.cv_r2).all()  # no penalty was chosen
    logits = readings[..., 3][torch.as_tensor(data.planted[:, 3])]
    labels = torch.as_tensor(y[test, 3], dtype=torch.bool)
    assert bool(((logits > 0) == labels).double().mean(-1).min() > 0.6)  # classes about even: 0.5 by chance


def test_partial_direction_holds_the_other_features_where_covariance_mixes_them_in():
    # a moves with b (as the gripper moves with the descent); the representation carries each along its own direction
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(2000, generator=gen, dtype=torch.float64)
    b = a + 0.5 * torch.randn(2000, generator=gen, dtype=torch.float64)
    u, w = torch.randn(2, 16, generator=gen, dtype=torch.float64)
    z = (a[:, None] * u + b[:, None] * w + 0.1 * torch.randn(2000, 16, generator=gen, dtype=torch.float64))[None]
    labels = torch.stack([a, b], 1)
    cos = lambda v, t: float(v @ t / t.norm())  # noqa: E731
    partial = partial_directions(z, labels)[0]
    assert cos(partial[0], u) > 0.99 and cos(partial[1], w) > 0.99
    assert cos(direction(z, a, False, "covariance")[0], u) < 0.9  # drags w (b's direction) along


def test_covariance_direction_is_where_ridge_goes_as_its_penalty_grows(planted):
    data, y, train, test, folds, _, _ = planted
    x = torch.from_numpy(data.x)
    kinds = [REGRESSION] * 3 + [LOGISTIC]
    ridge = fit_probes(x, y, kinds, train, folds, ProbeSettings(ridge_grid=(1e9,)))
    cov = fit_probes(x, y, kinds, train, folds, ProbeSettings(family="covariance"))
    cos = torch.nn.functional.cosine_similarity(ridge.weight[:, :3], cov.weight[:, :3], dim=-1)
    assert bool((cos > 0.999).all()), cos
