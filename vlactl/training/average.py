"""`vlactl average-policies`: the average of the weights of checkpoints fine-tuned from one start (a "model soup",
Wortsman et al., 2022), uniform or with given mixing weights (a fine-tune kept at less than half of its start's weights,
as WiSE-FT interpolates). Two fine-tunes of the shipped hybrid that fail on different tasks average into one that
fails on fewer (docs/models.md). The checkpoints must share the architecture, the normalisation and the
tokenizer (every file but the weights and the provenance), so the average reads its inputs as each of them does.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

PROVENANCE = "provenance.json"


def run_average_policies(cfg: DictConfig) -> Path:
    """Write `<output_dir>/checkpoint` (atomically) and return it."""
    import json
    import shutil

    from safetensors.torch import load_file, save_file

    from vlactl.config import resolve_path
    from vlactl.errors import UsageError
    from vlactl.io import atomic_dir, atomic_write_json, ensure_writable_dir
    from vlactl.models.parts.policy import WEIGHTS_FILE
    from vlactl.models.registry import CHECKPOINT_DIR, resolve_checkpoint, weights_fingerprint
    from vlactl.training.provenance import environment, git_commit

    names = [str(p) for p in (cfg.policies or [])]
    if len(names) < 2:
        raise UsageError(f"policies={names}: give two or more checkpoints to average, e.g. "
                         "policies=[data/policies/hybrid,outputs/policies/hybrid-robust/checkpoint]")
    mix = list(cfg.weights or [1.0] * len(names))
    if (len(mix) != len(names) or not all(isinstance(m, (int, float)) and not isinstance(m, bool) for m in mix)
            or min(mix) < 0 or sum(mix) <= 0):
        raise UsageError(f"weights={mix}: give one non-negative mixing weight per checkpoint ({len(names)}), not all "
                         "zero, e.g. weights=[3,1] keeps a quarter of the second; they are normalised to sum to 1")
    total = sum(mix)
    mix = [m / total for m in mix]
    folders = [resolve_checkpoint(name) for name in names]
    first = folders[0]
    shared = sorted(p.name for p in first.iterdir() if p.is_file() and p.name not in (WEIGHTS_FILE, PROVENANCE))

    def content(path: Path):
        """What a checkpoint file says: JSON by value (writers differ in layout and a trailing newline), else bytes."""
        return json.loads(path.read_text()) if path.suffix == ".json" else path.read_bytes()

    for name, folder in zip(names[1:], folders[1:]):
        for file in shared:
            if not (folder / file).is_file() or content(folder / file) != content(first / file):
                raise UsageError(f"{name!r} differs from {names[0]!r} in {file}; only checkpoints of one architecture, "
                                 "normalisation and tokenizer (fine-tunes of one start) can be averaged")
    weights = [load_file(str(folder / WEIGHTS_FILE)) for folder in folders]
    for name, w in zip(names[1:], weights[1:]):
        if {k: v.shape for k, v in w.items()} != {k: v.shape for k, v in weights[0].items()}:
            raise UsageError(f"{name!r} has other weights than {names[0]!r}; only one architecture can be averaged")
    sources = [json.loads((f / PROVENANCE).read_text()) if (f / PROVENANCE).is_file() else {} for f in folders]
    renders = {json.dumps(source.get("env"), sort_keys=True) for source in sources}
    if len(renders) > 1:
        raise UsageError(f"policies={names} were trained on images rendered otherwise (provenance.json, env: "
                         f"{sorted(renders)}); average fine-tunes on one render setting")
    averaged = {key: sum(m * w[key].float() for m, w in zip(mix, weights)).to(value.dtype)
                for key, value in weights[0].items()}
    out = ensure_writable_dir(resolve_path(cfg.output_dir), cfg.output_dir)
    with atomic_dir(out / CHECKPOINT_DIR) as tmp:
        for file in shared:
            shutil.copy2(first / file, tmp / file)
        save_file(averaged, str(tmp / WEIGHTS_FILE), metadata={"format": "pt"})
        atomic_write_json(tmp / PROVENANCE, {
            "averaged": [{"checkpoint": name, "weights": weights_fingerprint(name), "mixing_weight": m,
                          "provenance": source} for name, m, source in zip(names, mix, sources)],
            "env": sources[0].get("env"),  # how the images were rendered (every source's): stages warn on others
            "git_commit": git_commit(),
            "environment": environment(),
        })
    return out / CHECKPOINT_DIR
