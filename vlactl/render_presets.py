"""Render presets (`conf/env/<name>.yaml`) and the check that a run renders as its policy was trained.

A policy sees pixels, and all render settings but culling change them: the embedded models were trained on `env=fast`
renders, the real LIBERO checkpoints (π0.5, OpenVLA, SmolVLA) on LIBERO's own, `env=standard`. A real adapter
names its preset (`env_preset`), which rollouts use unless the user chose one; a checkpoint vlactl trains records the
settings of its demo set (`provenance.json`, key `env`), and a demo set records those it was rendered with
(`meta/vlactl_demos.json`). Rollout, collect and sweep call `warn_if_rendered_otherwise` at their start.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

# EnvConfig fields that change what a policy sees (culling changes no pixel without reflections, a few reflected
# ones with them; settling is physics)
PIXEL_KEYS = ("image_size", "reflections", "shadows", "skybox", "msaa_samples", "mesh_cell_mm")
PROVENANCE = "provenance.json"


def presets() -> dict[str, dict]:
    """Every preset's settings by name."""
    from omegaconf import OmegaConf

    from vlactl.config import CONF_DIR

    paths = sorted((CONF_DIR / "env").glob("*.yaml"))
    return {path.stem: OmegaConf.to_container(OmegaConf.load(path)) for path in paths}


def stage_env_override(stage: str, model: str, overrides: list[str]) -> list[str]:
    """`env=<preset>` of a real model's adapter, for a stage that renders (its config has the `env` group) when the
    user chose no preset; else nothing. `env.<field>=` overrides still apply on top."""
    from omegaconf import OmegaConf

    from vlactl.config import CONF_DIR
    from vlactl.models.registry import ADAPTERS, adapter_class

    if model not in ADAPTERS or any(item.lstrip("+~").split("=", 1)[0] == "env" for item in overrides):
        return []
    defaults = OmegaConf.to_container(OmegaConf.load(CONF_DIR / f"{stage}.yaml")).get("defaults", [])
    if not any(isinstance(item, dict) and "env" in item for item in defaults):
        return []
    return [f"env={adapter_class(model).env_preset}"]


def dataset_env(root: Path) -> dict | None:
    """The env settings a demo set was rendered with (None: not written by `vlactl demos`, or before they were
    recorded)."""
    from vlactl.data.demos import SUMMARY_NAME

    path = Path(root) / "meta" / SUMMARY_NAME
    return json.loads(path.read_text()).get("config", {}).get("env") if path.is_file() else None


def trained_env(model: str, vla=None) -> dict | None:
    """The env settings the policy `model` stands for was trained on: its adapter's preset, or what its checkpoint
    recorded; None when unknown (`random`, `scripted`, a checkpoint from before the record, a test's loader)."""
    from vlactl.errors import UsageError
    from vlactl.models.registry import resolve_checkpoint

    name = getattr(vla, "env_preset", None)
    if name:
        return presets()[name]
    try:
        path = resolve_checkpoint(model) / PROVENANCE
    except UsageError:
        return None
    return json.loads(path.read_text()).get("env") if path.is_file() else None


def warn_if_rendered_otherwise(model: str, vla, env: dict | None = None, dataset: Path | None = None) -> None:
    """One line on stderr when the images a stage feeds the policy - rendered with the run's `env` settings, or read
    from a demo set (`dataset`) - are rendered otherwise than its training images; silent when either is unknown."""
    run_env = dataset_env(dataset) if dataset is not None else env
    source = f"dataset {Path(dataset).name} was rendered with" if dataset is not None else "this run uses"
    trained = None if run_env is None else trained_env(model, vla)
    if trained is None:
        return
    keys = [k for k in PIXEL_KEYS if k in trained and k in run_env and trained[k] != run_env[k]]
    if not keys:
        return

    def shown(env: dict) -> str:
        return "{" + ", ".join(f"{k}: {json.dumps(env[k])}" for k in keys) + "}"

    match = [n for n, env in presets().items() if all(env.get(k) == trained[k] for k in PIXEL_KEYS if k in trained)]
    command = "vlactl demos " if dataset is not None else ""
    hint = f" ({command}env={match[0]} renders as it was trained)" if match else ""
    print(f"warning: model {model} was trained on env settings {shown(trained)}; {source} {shown(run_env)}{hint}",
          file=sys.stderr)
