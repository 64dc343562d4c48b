"""Hydra configs: compose `conf/<stage>.yaml` with user overrides, and save the resolved config with the outputs."""

from __future__ import annotations

import os
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import ConfigAttributeError, OmegaConfBaseException

from vlactl.errors import UsageError

REPO_ROOT = Path(__file__).resolve().parent.parent
SHIPPED_PROBES = REPO_ROOT / "data" / "probes"  # data/probes/<model>/{steer,observe,stop}: `make probes` rebuilds them
CONF_DIR = Path(os.environ.get("VLACTL_CONF_DIR", REPO_ROOT / "conf"))


def load_config(stage: str, overrides: list[str] | None = None) -> DictConfig:
    """Compose the config of a pipeline stage. Malformed or unknown overrides become a one-line UsageError."""
    overrides = list(overrides or [])
    for item in overrides:
        if "=" not in item:
            raise UsageError(f"malformed override {item!r}; expected key=value, e.g. suite=libero_object")
    cfg = _compose(stage, overrides)
    # Hydra takes `frames=abc` as a string; caught here, it would otherwise fail deep inside the run. The defaults
    # are those of the config groups the overrides choose (`model=autoregressive` in train-policy).
    groups = {path.name for path in CONF_DIR.iterdir() if path.is_dir()}
    settings = [item for item in overrides if _key(item) not in groups]
    if not settings:
        return cfg
    defaults = _compose(stage, [item for item in overrides if _key(item) in groups])
    for item in settings:
        key, value = _key(item), item.split("=", 1)[1]
        default, given = OmegaConf.select(defaults, key), OmegaConf.select(cfg, key)
        if given is not None and not _same_kind(default, given):
            kind = {bool: "true or false", int: "an integer", float: "a number"}[type(default)]
            raise UsageError(f"{key}={value!r}: expected {kind} (default: {default})")
    return cfg


def _compose(stage: str, overrides: list[str]) -> DictConfig:
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name=stage, overrides=overrides)
        OmegaConf.resolve(cfg)
    except (HydraException, OmegaConfBaseException) as exc:
        cause = exc.__cause__
        if isinstance(cause, ConfigAttributeError) and cause.full_key and overrides:
            parent, _, _ = cause.full_key.rpartition(".")
            node = _compose(stage, [item for item in overrides if _key(item) != cause.full_key])
            node = OmegaConf.select(node, parent) if parent else node
            if isinstance(node, DictConfig):
                raise UsageError(
                    f"unknown setting {cause.full_key!r} in conf/{stage}.yaml; known: {', '.join(node)}"
                ) from None
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UsageError(f"bad override in {overrides}: {first_line}") from None
    return cfg


def _key(item: str) -> str:
    return item.split("=", 1)[0].lstrip("+~")


def _same_kind(default, given) -> bool:
    """Whether an override keeps a scalar default's type (an integer where a number is expected is fine); defaults
    that are strings, lists or null take anything."""
    if isinstance(default, bool):
        return isinstance(given, bool)
    if isinstance(default, int):
        return isinstance(given, int) and not isinstance(given, bool)
    if isinstance(default, float):
        return isinstance(given, (int, float)) and not isinstance(given, bool)
    return True


def quote_values(overrides: list[str] | None, *keys: str) -> list[str]:
    """`key=value` overrides of these keys with the value quoted, so Hydra takes it as written (`gripper=open`,
    `frame_index < 25` would otherwise be grammar errors); values already holding a quote are left alone."""
    def quoted(item: str) -> str:
        key, _, value = item.partition("=")
        return f"{key}='{value}'" if key in keys and "'" not in value else item

    return [quoted(item) for item in overrides or []]


def load_policy_stage_config(stage: str, overrides: list[str] | None = None) -> DictConfig:
    """The config of a stage that runs a policy, with `model=<name or path>` applied after composing.

    `conf/model/` is a config group (the architectures `train-policy` builds), so Hydra would read `model=x` as
    choosing a file of that group; in these stages `model` is a plain string: a registry name or a checkpoint path.
    Options of a real model's adapter come as `model.<option>=<value>` (e.g. `model.checkpoint=<path>`) and land
    in `cfg.model_args`, which `vlactl.models.registry.policy_loader` binds. A real model renders with its adapter's
    env preset unless `env=<preset>` is given.
    """
    from vlactl.render_presets import stage_env_override

    overrides = list(overrides or [])
    models = [item.split("=", 1)[1] for item in overrides if item.startswith("model=")]
    options = [item.split(".", 1)[1] for item in overrides if item.startswith("model.")]
    rest = [item for item in overrides if not item.startswith(("model=", "model."))]
    cfg = load_config(stage, (stage_env_override(stage, models[-1], rest) if models else []) + rest)
    if models:
        cfg.model = models[-1]
    if options:
        try:
            args = OmegaConf.from_dotlist(options)
        except OmegaConfBaseException as exc:
            raise UsageError(f"bad model option in {options}: {str(exc).strip().splitlines()[0]}") from None
        with open_dict(cfg):
            cfg.model_args = args
    return cfg


def save_config(cfg: DictConfig, out_dir: Path, name: str = "config.yaml") -> Path:
    """Write the resolved config beside a run's outputs (atomically, like every result file)."""
    from vlactl.io import atomic_write_text

    path = Path(out_dir) / name
    atomic_write_text(path, OmegaConf.to_yaml(cfg, resolve=True))
    return path


def resolve_path(path: str | Path) -> Path:
    """Relative paths in configs are relative to the repository root, so commands work from any directory."""
    path = Path(path).expanduser()
    return path if path.is_absolute() else REPO_ROOT / path


def stage_output(path: str | Path, marker: str, kind: str, command: str) -> Path:
    """The output folder of an earlier stage, recognised by its `marker` file; a UsageError naming it otherwise."""
    folder = resolve_path(path)
    if not (folder / marker).is_file():
        raise UsageError(f"{str(path)!r} is not a {kind} folder (no {marker}); write one with `{command}`")
    return folder
