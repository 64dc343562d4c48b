"""Hydra-style multirun (`vlactl rollout -m constraint=gripper=open,gripper=closed alpha=2,4`): overrides whose value
is a comma-separated sweep expand to the cartesian product, one run per combination, in order.

Hydra's own override parser tells sweeps from lists (`layers=[backbone.2,expert.3]` is one value; `layers=[a],[b]`
is a sweep of two). Runs are named after the swept keys their default name does not already carry, so a sweep over
alpha never resumes into one folder.
"""

from __future__ import annotations

import itertools

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException

from vlactl.errors import UsageError
from vlactl.io import folder_name


def _quote_pieces(item: str) -> str:
    """`constraint=gripper=open,gripper=closed` -> `constraint='gripper=open','gripper=closed'` (Hydra needs
    values holding '=' quoted)."""
    key, _, value = item.partition("=")
    if "=" not in value or "'" in value or '"' in value:
        return item
    return f"{key}=" + ",".join(f"'{piece}'" for piece in value.split(","))


def expand(overrides: list[str], named_by: tuple[str, ...] = ()) -> list[tuple[list[str], str]]:
    """One (overrides, tag) per run. `tag` names the swept keys outside `named_by` (e.g. `alpha-2`), '' if none."""
    quoted = [_quote_pieces(item) for item in overrides]
    try:
        parsed = OverridesParser.create().parse_overrides(quoted)
    except HydraException as exc:
        raise UsageError(f"bad multirun override in {overrides}: {str(exc).strip().splitlines()[0]}") from None
    axes = []
    for override in parsed:
        key = override.get_key_element()
        values = list(override.sweep_string_iterator()) if override.is_sweep_override() else [
            override.get_value_element_as_str()]
        axes.append([(key, value, override.is_sweep_override()) for value in values])
    runs = []
    for combination in itertools.product(*axes):
        items = [f"{key}={value}" for key, value, _ in combination]
        tag = "_".join(f"{key}-{folder_name(value)}" for key, value, swept in combination if swept and key not in named_by)
        runs.append((items, tag))
    return runs
