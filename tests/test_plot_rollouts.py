"""`vlactl plot rollouts` on synthetic constrained-run tables (no simulator)."""

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.errors import UsageError
from vlactl.plots.rollouts import figure_success_vs_satisfaction, load_runs, normalised


def fake_run(root, constraint, method, seed):
    rng = np.random.default_rng(seed)
    out = root / f"hybrid_libero_spatial_{constraint.replace('=', '-')}_{method}"
    out.mkdir(parents=True)
    rows = [{"task_id": t, "episode": k, "success": bool(rng.random() < 0.7), "constraint": constraint,
             "method": method, "satisfaction": rng.random()} for t in range(3) for k in range(2)]
    pd.DataFrame(rows).to_parquet(out / "episodes.parquet")
    steps = pd.DataFrame([{"task_id": t, "episode": k, "t": i, "in_window": i < 4, "constraint_value": rng.normal(),
                           "constraint_level": 0.0, "gripper": rng.random()} for t in range(3) for k in range(2) for i in range(6)])
    steps.to_parquet(out / "steps.parquet")
    return out


def test_figures_from_every_constrained_run_under_the_root(tmp_path):
    for i, (constraint, method) in enumerate([("gripper=open", "none"), ("gripper=open", "control"),
                                              ("gripper=closed", "prompt"), ("height=low", "control")]):
        fake_run(tmp_path, constraint, method, i)
    episodes, steps = load_runs(sorted(p for p in tmp_path.iterdir()))
    assert len(episodes) == 24 and len(steps) == 24 * 4  # in-window steps only
    assert set(steps["feature"]) == {"gripper", "height"} and set(steps["condition"]) == {"open", "closed", "low"}
    result = CliRunner().invoke(app, ["plot", "rollouts", f"root={tmp_path}", "formats=[png]"])
    assert result.exit_code == 0, result.output
    for name in ("violins_gripper", "violins_height", "success_vs_satisfaction"):
        assert (tmp_path / "figures" / f"{name}.png").stat().st_size > 0
    table = (tmp_path / "figures" / "summary.md").read_text().splitlines()
    assert len(table) == 2 + 4 and table[2].startswith("| gripper=closed | prompt | 6 |")
    run = tmp_path / "hybrid_libero_spatial_gripper-closed_prompt"
    k, n, z = pd.read_parquet(run / "episodes.parquet")["success"].sum(), 6, 1.959964
    centre = (k / n + z**2 / (2 * n)) / (1 + z**2 / n)  # Wilson's interval, written out
    half = z * np.sqrt(k / n * (1 - k / n) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    assert f"| {100 * k / n:.0f}% ({100 * (centre - half):.0f}–{100 * (centre + half):.0f}%) |" in table[2]


def test_no_constrained_run_is_a_usage_error(tmp_path):
    with pytest.raises(UsageError, match="no constrained rollout runs"):
        load_runs([])


def test_gripper_is_drawn_as_closure_and_every_condition_has_its_panel(tmp_path):
    for i, (constraint, method) in enumerate([("gripper=open", "none"), ("gripper=closed", "control"),
                                              ("gripper=closed", "filter"), ("height=high", "control")]):
        fake_run(tmp_path, constraint, method, i)
    episodes, steps = load_runs(sorted(p for p in tmp_path.iterdir()))
    gripper = steps[steps["feature"] == "gripper"]
    assert np.allclose(normalised(gripper, "gripper"), 1 - gripper["gripper"])
    height = steps[steps["feature"] == "height"]
    assert np.allclose(normalised(height, "height"), height["constraint_value"] - height["constraint_level"])
    fig = figure_success_vs_satisfaction(episodes)
    titles = [ax.get_title() for ax in fig.axes if ax.axison]
    assert titles == ["gripper=closed", "gripper=open", "height=high"]
    closed = next(ax for ax in fig.axes if ax.get_title() == "gripper=closed")
    assert closed.get_legend_handles_labels()[1] == ["control", "filter"]  # the methods this panel draws
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["none", "control", "filter"]  # one legend, below


def fake_run_of_two(root, seed=9):
    """A run under [height=high,speed=low] as the rollout writes it: each constraint's columns suffixed."""
    rng = np.random.default_rng(seed)
    out = root / "hybrid_libero_spatial_height-high_speed-low_control"
    out.mkdir(parents=True)
    rows = [{"task_id": t, "episode": k, "success": bool(rng.random() < 0.7), "constraint": "height=high,speed=low",
             "method": "control", "satisfaction": 0.25, "satisfaction_height": 0.5, "satisfaction_speed": 0.75}
            for t in range(3) for k in range(2)]
    pd.DataFrame(rows).to_parquet(out / "episodes.parquet")
    steps = pd.DataFrame([{"task_id": t, "episode": k, "t": i, "in_window": i < 5, "in_window_height": i < 3,
                           "in_window_speed": i < 5, "constraint_value_height": rng.normal(),
                           "constraint_level_height": 1.0, "constraint_value_speed": rng.random(),
                           "constraint_level_speed": 0.1, "gripper": rng.random()}
                          for t in range(3) for k in range(2) for i in range(6)])
    steps.to_parquet(out / "steps.parquet")


def test_a_run_under_two_constraints_is_drawn_in_each_panel_under_its_full_name(tmp_path):
    fake_run(tmp_path, "height=high", "control", 0)
    fake_run_of_two(tmp_path)
    episodes, steps = load_runs(sorted(p for p in tmp_path.iterdir()))
    both = "control [height=high,speed=low]"
    assert sorted(episodes.loc[episodes["method"] == both, "constraint"].unique()) == ["height=high", "speed=low"]
    height = steps[(steps["method"] == both) & (steps["feature"] == "height")]
    assert len(height) == 6 * 3 and (height["constraint_level"] == 1.0).all()  # its own window and columns
    assert len(steps[(steps["method"] == both) & (steps["feature"] == "speed")]) == 6 * 5
    fig = figure_success_vs_satisfaction(episodes)
    panel = next(ax for ax in fig.axes if ax.get_title() == "height=high")
    assert panel.get_legend_handles_labels()[1] == ["control", both]
    result = CliRunner().invoke(app, ["plot", "rollouts", f"root={tmp_path}", "formats=[png]"])
    assert result.exit_code == 0, result.output
    for name in ("violins_height", "violins_speed", "success_vs_satisfaction"):
        assert (tmp_path / "figures" / f"{name}.png").stat().st_size > 0
    table = (tmp_path / "figures" / "summary.md").read_text()
    assert "| height=high,speed=low | control | 6 |" in table and "| 25% (height=high 50%, speed=low 75%) |" in table


def _set_of_runs(root, constraint, method, seed, successes, perturbation="none", model="hybrid"):
    """A run of 2 tasks x 2 episodes started with `seed=` (episode k: seed + k), its successes in task-major order."""
    out = root / f"{model}_{constraint}_{method}_{perturbation}_seed{seed}"
    out.mkdir(parents=True)
    rows = [{"task_id": t, "episode": k, "seed": seed + k, "success": bool(successes[2 * t + k]),
             "constraint": constraint, "method": method, "satisfaction": 1.0, "perturbation": perturbation,
             "model": model}
            for t in range(2) for k in range(2)]
    pd.DataFrame(rows).to_parquet(out / "episodes.parquet")
    return out


def test_summary_pools_sets_and_compares_with_their_unconstrained_twins(tmp_path):
    from vlactl.plots.rollouts import summary_table

    runs = [_set_of_runs(tmp_path, "none", "none", 0, [0, 0, 0, 0], perturbation="raise"),  # first: never a twin
            _set_of_runs(tmp_path, "none", "none", 0, [1, 1, 1, 0]),
            _set_of_runs(tmp_path, "none", "none", 1000, [1, 1, 1, 1]),
            _set_of_runs(tmp_path, "height=high", "control+pause", 0, [1, 0, 1, 0]),
            _set_of_runs(tmp_path, "height=high", "control+pause", 1000, [1, 1, 0, 1]),
            _set_of_runs(tmp_path, "speed=low", "filter+pause", 2000, [1, 1, 1, 1])]  # no unconstrained set 2000
    table = summary_table(runs).splitlines()
    row = next(r for r in table if r.startswith("| height=high | control+pause |"))
    assert "| 8 | 62% (" in row and "| 0: 2/4, 1000: 3/4 | 0.714 × (5/7) |" in row
    assert next(r for r in table if r.startswith("| speed=low |")).endswith("| – | – | 100% |")
    assert next(r for r in table if r.startswith("| none | none |")).count("| – |") == 1  # sets listed, no ratio to itself
    assert "| none | none, perturb=raise | 4 | 0% (" in "\n".join(table)  # a row of its own
    assert next(r for r in table if "perturb=raise" in r).endswith("| – | 0.000 × (0/3) | 100% |")  # vs unperturbed


def test_summary_keeps_each_models_rows_and_twins_apart(tmp_path):
    from vlactl.plots.rollouts import summary_table

    runs = [_set_of_runs(tmp_path, "none", "none", 0, [0, 0, 0, 1], model="autoregressive"),  # first: not a twin
            _set_of_runs(tmp_path, "none", "none", 0, [1, 1, 1, 1]),
            _set_of_runs(tmp_path, "gripper=open", "control", 0, [1, 1, 1, 0])]
    table = summary_table(runs)
    assert "| none | autoregressive: none | 4 | 25% (" in table and "| none | hybrid: none | 4 | 100% (" in table
    assert "| gripper=open | hybrid: control | 4 | 75% (" in table and "| 0.750 × (3/4) |" in table
