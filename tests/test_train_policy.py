"""`vlactl train-policy` end to end on a tiny synthetic LeRobot dataset: checkpoint files, exact resume, errors."""

import json

import pytest
import torch
from safetensors.torch import load_file
from synthetic_demos import observation, write_synthetic_demos
from typer.testing import CliRunner

from vlactl.cli import app
from vlactl.config import load_config
from vlactl.errors import UsageError
from vlactl.models.registry import load_policy
from vlactl.training.average import run_average_policies
from vlactl.training.train_policy import STATE_FILE, run_train_policy

TINY = {
    "hybrid": "model.vision_channels=[8,8,8] model.width=32 model.layers=2 model.heads=2 model.kv_heads=1 "
    "model.head_dim=16 model.mlp_width=64 model.expert_width=32 model.expert_mlp_width=64 model.flow_steps=2",
    "autoregressive": "model.vision_channels=[8,8,8] model.width=32 model.layers=2 model.heads=2 model.kv_heads=1 "
    "model.head_dim=16 model.mlp_width=64 model.chunk_size=2 model.replan_every=2",
}


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    return write_synthetic_demos(tmp_path_factory.mktemp("demos") / "synthetic")


def overrides(demos, out, name="hybrid", steps=3, *extra):
    return [f"model={name}", f"dataset={demos}", f"output_dir={out}", f"cache_dir={out.parent / 'cache'}",
            f"steps={steps}", "batch_size=4", "save_every=2", "log_every=1", "threads=1", "warmup_steps=1",
            *TINY[name].split(), *extra]


@pytest.mark.parametrize("name", ["hybrid", "autoregressive"])
def test_cli_trains_and_writes_a_loadable_checkpoint(demos, tmp_path, name):
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train-policy", *overrides(demos, out, name)])
    assert result.exit_code == 0, result.output
    ckpt = out / "checkpoint"
    for file in ("model.safetensors", "config.json", "tokenizer.json", "normalization.json", "provenance.json"):
        assert (ckpt / file).is_file(), file
    provenance = json.loads((ckpt / "provenance.json").read_text())
    assert provenance["step"] == 3 and provenance["dataset"] == str(demos) and provenance["seed"] == 0
    assert [p["step"] for p in provenance["curve"]] == [1, 2, 3]
    assert len(provenance["dataset_fingerprint"]) == 16 and provenance["git_commit"]
    policy = load_policy(str(out))
    assert policy.name == name
    assert policy.predict_action_chunk(observation()).shape == (2, policy.chunk_size, 7)
    assert not list(out.glob(".*"))  # no temporary or half-written folder left behind


def test_resume_continues_exactly(demos, tmp_path, monkeypatch):
    from vlactl.training.train_policy import Run

    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    run_train_policy(load_config("train_policy", overrides(demos, straight, steps=4)))
    save = Run.save

    def save_then_die_at_step_2(run):
        save(run)
        if run.step == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(Run, "save", save_then_die_at_step_2)
    with pytest.raises(KeyboardInterrupt):
        run_train_policy(load_config("train_policy", overrides(demos, resumed, steps=4)))
    monkeypatch.setattr(Run, "save", save)
    assert torch.load(resumed / STATE_FILE, weights_only=False)["step"] == 2
    run_train_policy(load_config("train_policy", overrides(demos, resumed, steps=4)))
    a, b = (load_file(p / "checkpoint" / "model.safetensors") for p in (straight, resumed))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    curves = [json.loads((p / "checkpoint" / "provenance.json").read_text())["curve"] for p in (straight, resumed)]
    assert [c["loss"] for c in curves[0]] == [c["loss"] for c in curves[1]]


def test_resume_refuses_another_model_config(demos, tmp_path):
    out = tmp_path / "run"
    run_train_policy(load_config("train_policy", overrides(demos, out, steps=1)))
    result = CliRunner().invoke(app, ["train-policy", *overrides(demos, out, "hybrid", 2, "model.flow_steps=3")])
    assert result.exit_code != 0 and "another dataset or model config" in str(result.exception)


def test_bad_inputs_are_usage_errors(tmp_path):
    from vlactl.errors import UsageError

    with pytest.raises(UsageError, match="no LeRobot v3 dataset"):
        run_train_policy(load_config("train_policy", [f"dataset={tmp_path}", f"output_dir={tmp_path / 'o'}"]))
    with pytest.raises(UsageError):
        load_config("train_policy", ["model=transformer"])


def test_fine_tuning_starts_from_the_checkpoint_and_refuses_another_architecture(demos, tmp_path, monkeypatch):
    from vlactl.training import train_policy

    source = tmp_path / "source"
    run_train_policy(load_config("train_policy", overrides(demos, source, steps=2)))
    started = {}
    monkeypatch.setattr(train_policy.Run, "save", lambda run: started.setdefault("weights", {
        k: v.clone() for k, v in run.policy.state_dict().items()}))
    run_train_policy(load_config("train_policy", overrides(demos, tmp_path / "tuned", "hybrid", 1, f"init_from={source}")))
    expected = load_policy(str(source)).state_dict()
    assert all(torch.equal(started["weights"][k], expected[k]) for k in expected)
    with pytest.raises(UsageError, match="different hybrid architecture"):
        run_train_policy(load_config("train_policy", overrides(demos, tmp_path / "other", "hybrid", 1,
                                                               f"init_from={source}", "model.layers=3")))


def test_average_policies_writes_the_mean_of_fine_tunes_and_refuses_other_starts(demos, tmp_path):
    """A model soup: two fine-tunes of one start average weight by weight into a checkpoint that loads and predicts,
    uniformly or with given mixing weights (one per checkpoint, non-negative, else a one-line error); the same config
    written in another layout (the shipped soup's, without a trailing newline) still averages; a checkpoint with
    another normalisation, or a single one, is a one-line error and writes nothing."""
    start, other = tmp_path / "start", tmp_path / "other"
    run_train_policy(load_config("train_policy", overrides(demos, start, steps=2)))
    tunes = [tmp_path / f"tune{seed}" for seed in (1, 2)]
    for seed, tune in zip((1, 2), tunes):
        run_train_policy(load_config("train_policy", overrides(demos, tune, "hybrid", 2, f"init_from={start}",
                                                               f"seed={seed}", "lr=1e-2")))
    config = tunes[1] / "checkpoint" / "config.json"
    config.write_text(json.dumps(json.loads(config.read_text())))
    soup = tmp_path / "soup"
    result = CliRunner().invoke(app, ["average-policies", f"policies=[{tunes[0]},{tunes[1]}]", f"output_dir={soup}"])
    assert result.exit_code == 0, result.output
    weights = [load_file(str(t / "checkpoint" / "model.safetensors")) for t in tunes]
    averaged = load_file(str(soup / "checkpoint" / "model.safetensors"))
    assert any(not torch.equal(weights[0][k], weights[1][k]) for k in averaged)
    assert all(torch.allclose(averaged[k], (weights[0][k] + weights[1][k]) / 2) for k in averaged)
    provenance = json.loads((soup / "checkpoint" / "provenance.json").read_text())
    assert [p["checkpoint"] for p in provenance["averaged"]] == [str(t) for t in tunes]
    assert load_policy(str(soup)).predict_action_chunk(observation()).shape[0] == 2
    quarter = tmp_path / "quarter"
    run_average_policies(load_config("average_policies", [f"policies=[{tunes[0]},{tunes[1]}]", "weights=[3,1]",
                                                          f"output_dir={quarter}"]))
    mixed = load_file(str(quarter / "checkpoint" / "model.safetensors"))
    assert all(torch.allclose(mixed[k], 0.75 * weights[0][k] + 0.25 * weights[1][k]) for k in mixed)
    provenance = json.loads((quarter / "checkpoint" / "provenance.json").read_text())
    assert [p["mixing_weight"] for p in provenance["averaged"]] == [0.75, 0.25]
    for bad in ("[1]", "[1,-1]", "[0,0]", "[a,1]"):
        result = CliRunner().invoke(app, ["average-policies", f"policies=[{tunes[0]},{tunes[1]}]", f"weights={bad}",
                                          f"output_dir={tmp_path / 'refused'}"])
        assert isinstance(result.exception, UsageError) and "mixing weight" in str(result.exception)
        assert not (tmp_path / "refused" / "checkpoint").exists()
    run_train_policy(load_config("train_policy", overrides(demos, other, "hybrid", 1)))
    (other / "checkpoint" / "normalization.json").write_text("{}")  # as if fitted on other demonstrations
    for given, message in (([tunes[0], other], "differs from .* in normalization.json"), ([tunes[0]], "two or more")):
        with pytest.raises(UsageError, match=message):
            run_average_policies(load_config("average_policies", [f"policies=[{','.join(map(str, given))}]",
                                                                  f"output_dir={tmp_path / 'refused'}"]))
        assert not (tmp_path / "refused" / "checkpoint").exists()
