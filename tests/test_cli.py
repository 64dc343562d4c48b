"""Bad input gets one line naming the value and what is allowed, exit code 2, never a traceback."""

import subprocess
import sys

import pytest


def run(*args):
    return subprocess.run([sys.executable, "-m", "vlactl.cli", *args], capture_output=True, text=True, timeout=120)


def test_help_lists_the_pipeline():
    out = run("--help").stdout
    for stage in ["tasks", "demos", "train-policy", "collect", "train-probes", "sweep", "rollout", "plot"]:
        assert stage in out


@pytest.mark.parametrize(
    "args, needle",
    [
        (["demos", "suite=libero_nope"], "libero_nope"),
        (["demos", "--suite", "libero_nope"], "libero_nope"),
        (["demos", "episodes_per_task=-1"], "episodes_per_task"),
        (["demos", "tasks=[99]"], "99"),
        (["demos", "output_dir=/proc/vlactl-cannot-write"], "/proc/vlactl-cannot-write"),
        (["demos", "suite"], "suite"),
        (["demos", "no_such_key=3"], "unknown setting 'no_such_key' in conf/demos.yaml; known: "),
        (["demos", "episodes_per_task=abc"], "episodes_per_task='abc': expected an integer"),
        (["rollout", "model=random", "episodes_per_task=2.5"], "episodes_per_task='2.5': expected an integer"),
        (["train-probes", "activations=x", "test_fraction=most"], "test_fraction='most': expected a number"),
        (["train-policy", "model=autoregressive", "model.widht=64"], "unknown setting 'model.widht'"),
        (["tasks", "--suite", "libero_nope"], "libero_nope"),
        (["rollout", "model=/tmp"], "'/tmp' is a folder but not a checkpoint (no config.json"),
        (["rollout", "model=random", "env.image_size=-3"], "env.image_size must be > 0, got -3"),
        (["demos", "env.mesh_cell_mm=-2"], "env.mesh_cell_mm must be >= 0, got -2"),
        (["demos", "tilt_size=[0.04,0.01]", "output_dir=/tmp/vlactl-never-made"], "tilt_size=[0.04,0.01] out of range"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, needle):
    res = run(*args)
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip() and "robosuite" not in line]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error:") and needle in lines[0]
    assert "Traceback" not in res.stderr


def test_tasks_lists_instructions():
    res = run("tasks", "--suite", "libero_spatial")
    assert res.returncode == 0
    assert "libero_spatial (10 tasks)" in res.stdout
    assert "pick up the black bowl" in res.stdout
