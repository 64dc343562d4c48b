"""`vlactl train-probes` and `vlactl plot probes` end to end on a tiny activation folder; bad input is one line.

One real subprocess for the whole CLI; the other cases call the same `main()` in-process (a fresh interpreter costs
seconds of imports on these machines)."""

import subprocess
import sys

import pandas as pd
import pytest
from synthetic_activations import write_store

from vlactl import cli
from vlactl.steering.activations import FEATURES
from vlactl.steering.probe_file import load_probe


def run(*args):
    return subprocess.run([sys.executable, "-m", "vlactl.cli", *args], capture_output=True, text=True, timeout=300)


def run_here(monkeypatch, capsys, *args) -> tuple[int, str]:
    """`vlactl <args>` through cli.main in this process: (exit code, stderr)."""
    monkeypatch.setattr(sys, "argv", ["vlactl", *args])
    with pytest.raises(SystemExit) as done:
        cli.main()
    return done.value.code, capsys.readouterr().err


@pytest.fixture(scope="module")
def acts(tmp_path_factory):
    folder = tmp_path_factory.mktemp("acts") / "run1"
    data = write_store(folder, n_episodes=24, frames=25, d=32)
    return folder, data


def test_train_probes_then_plot(acts, tmp_path, monkeypatch, capsys):
    folder, data = acts
    out = tmp_path / "probes"
    res = run("train-probes", "--activations", str(folder), "--output-dir", str(out), "layer_batch=3")
    assert res.returncode == 0, res.stderr
    table = pd.read_parquet(out / "metrics.parquet")
    assert len(table) == 4 * len(FEATURES) and set(table["feature"]) == set(FEATURES)
    assert (out / "config.yaml").is_file()
    reg = table[table["kind"] == "regression"]
    planted = data.planted[reg["layer_index"], [FEATURES.index(f) for f in reg["feature"]]]
    assert (reg["r2"][planted] > 0.6).all() and (reg["r2"][~planted] < 0.3).all()
    for column in ("mae", "baseline_mae", "robust_mean_0.05", "robust_max_0.1", "cv_r2", "penalty"):
        assert reg[column].notna().all()
    log = table[table["kind"] == "logistic"]
    assert set(log["feature"]) == {"gripper", "gripper_action"} and log["baseline_accuracy"].notna().all()
    probe = load_probe(out / table["probe"].iloc[0], model="synthetic", width=32, pooling="prefix")
    assert probe.layer == table["layer"].iloc[0] and probe.metrics["mae"] == pytest.approx(table["mae"].iloc[0])

    code, err = run_here(monkeypatch, capsys, "plot", "probes", "--run-dir", str(out))
    assert code == 0, err
    for name in ("fig1_best_layer", "layers_r2", "layers_mae", "layers_accuracy", "layers_robustness"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 0
        assert (out / "figures" / f"{name}.pdf").stat().st_size > 0


@pytest.mark.parametrize("args, needle", [
    (["train-probes"], "activations="),
    (["train-probes", "activations=/nowhere"], "/nowhere"),
    (["train-probes", "@ACTS", "layers=[backbone.9]"], "backbone.9"),
    (["train-probes", "@ACTS", "features=[elbow]"], "elbow"),
    (["train-probes", "@ACTS", "test_fraction=1.5"], "test_fraction"),
    (["train-probes", "@ACTS", "cv_folds=40"], "episodes"),
    (["train-probes", "@ACTS", "output_dir=/proc/vlactl-cannot-write"], "/proc/vlactl-cannot-write"),
    (["train-probes", "@ACTS", "frames=elbow > 1"], "elbow"),
    (["train-probes", "@ACTS", "frames=frame_index + 1"], "true/false"),
    (["train-probes", "@ACTS", "frames=frame_index > 1000"], "no frame"),
    (["train-probes", "@ACTS", "device=tpu"], "tpu"),
    (["train-probes", "@ACTS", "family=pca"], "meandiff"),
    (["train-probes", "@ACTS", "device=cuda:99"], "cuda:99"),
    (["plot", "probes"], "run_dir="),
    (["plot", "probes", "run_dir=/nowhere"], "/nowhere"),
])
def test_bad_input_is_one_line_and_exit_2(acts, monkeypatch, capsys, args, needle):
    folder, _ = acts
    code, err = run_here(monkeypatch, capsys, *[f"activations={folder}" if a == "@ACTS" else a for a in args])
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and needle in lines[0], err


def trained(acts, out, monkeypatch, capsys, *args) -> pd.DataFrame:
    """The metrics table of a train-probes run on the fixture's activations that must succeed."""
    code, err = run_here(monkeypatch, capsys, "train-probes", f"activations={acts[0]}", f"output_dir={out}",
                         "robustness_directions=2", *args)
    assert code == 0, err
    return pd.read_parquet(out / "metrics.parquet")


def test_frames_query_trains_on_the_chosen_frames_only(acts, tmp_path, monkeypatch, capsys):
    table = trained(acts, tmp_path / "early", monkeypatch, capsys, "features=[x]", "frames=frame_index < 10")
    full = 24 * 25
    assert (table["n_train"] + table["n_test"] == 24 * 10).all() and (table["n_train"] < full).all()


def test_a_steering_family_is_recorded_per_probe(acts, tmp_path, monkeypatch, capsys):
    table = trained(acts, tmp_path / "md", monkeypatch, capsys, "features=[z,gripper]", "family=meandiff")
    assert set(table["family"]) == {"meandiff"} and table["penalty"].isna().all()
    best = table.groupby("feature")[["r2", "balanced_accuracy"]].max()
    assert best.loc["z", "r2"] > 0.2 and best.loc["gripper", "balanced_accuracy"] > 0.6, best


def test_an_interrupted_run_resumes_from_its_finished_layers(acts, tmp_path, monkeypatch, capsys):
    folder, _ = acts
    args = ["train-probes", f"activations={folder}", "features=[x,gripper]", "robustness_directions=2"]
    code, err = run_here(monkeypatch, capsys, *args, f"output_dir={tmp_path / 'whole'}")  # one batch of 4 layers
    assert code == 0, err
    whole = pd.read_parquet(tmp_path / "whole" / "metrics.parquet")

    from vlactl.steering import train_probes

    fitted, fit = [], train_probes.fit_probes

    def fit_twice_then_stop(x, *rest):
        if len(fitted) == 2:
            raise KeyboardInterrupt  # Ctrl-C during the third layer
        fitted.append(x.shape[0])
        return fit(x, *rest)

    out = tmp_path / "resumed"
    monkeypatch.setattr(train_probes, "fit_probes", fit_twice_then_stop)
    code, err = run_here(monkeypatch, capsys, *args, "layer_batch=1", f"output_dir={out}")
    assert code == 130 and "re-run the same command to resume" in err, err
    assert not (out / "metrics.parquet").exists() and len(list((out / "parts").glob("*.parquet"))) == 2
    fitted.clear()
    monkeypatch.setattr(train_probes, "fit_probes", lambda x, *rest: fitted.append(x.shape[0]) or fit(x, *rest))
    code, err = run_here(monkeypatch, capsys, *args, "layer_batch=2", f"output_dir={out}")
    assert code == 0 and "resuming: 2 of 4 layers" in err, err
    assert fitted == [2]  # only the two layers left; batches may change size, the numbers do not
    pd.testing.assert_frame_equal(pd.read_parquet(out / "metrics.parquet"), whole)

    # other settings start over: the parts and probes of the earlier run go
    code, err = run_here(monkeypatch, capsys, *args[:-1], "robustness_directions=3", "layers=[backbone.2]",
                         f"output_dir={out}")
    assert code == 0 and "resuming" not in err, err
    table = pd.read_parquet(out / "metrics.parquet")
    assert table["layer_index"].tolist() == [2, 2]  # the layer's place in the activation folder, not in the choice
    assert sorted(p.name for p in (out / "probes").iterdir()) == ["backbone.2__gripper.safetensors",
                                                                   "backbone.2__x.safetensors"]
