"""``--set dotted.key=value`` overrides on a raw (YAML-parsed) config dict, before it is
validated: :func:`apply_override` edits one place, :func:`unaliased` first gives every
place its own copy. No schema and no JAX: unknown keys are left for validation to name."""

from __future__ import annotations

import copy
from typing import Any

from mysim_jax.core.config_base import ConfigError, parse_yaml


def apply_override(raw: dict, assignment: str) -> None:
    """Apply one ``dotted.key=value`` override to a raw config dict, in place.

    The value is parsed as YAML (``5e-4`` and ``[0, 0, -9.81]`` work). List entries are
    addressed by index (``ropes.0.EA=2e5``). Unknown keys are left for validation to
    reject, so the error names them.
    """
    if "=" not in assignment:
        raise ConfigError(f"--set '{assignment}': expected key=value")
    key, text = assignment.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set '{assignment}': empty key")
    value = parse_yaml(text, f"--set {key}", "value")
    node: Any = raw
    for depth, part in enumerate(parts[:-1]):
        where = ".".join(parts[: depth + 1])
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ConfigError(f"--set {key}: '{where}' has no entry {part} (it has {len(node)})")
            node = node[int(part)]
        elif isinstance(node, dict):
            if part not in node:
                node[part] = {}
            node = node[part]
        else:
            raise ConfigError(f"--set {key}: '{where}' is a value, not a section")
    last = parts[-1]
    if isinstance(node, list):
        if not last.isdigit() or int(last) >= len(node):
            raise ConfigError(f"--set {key}: no entry {last} (it has {len(node)})")
        node[int(last)] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise ConfigError(f"--set {key}: parent is a value, not a section")


def unaliased(raw: Any) -> Any:
    """A copy of a YAML-parsed value in which no mapping or list is shared. YAML anchors
    (``&ctrl`` ... ``*ctrl``) make one object appear at several places; a ``--set`` override
    addresses one place and must change only that one."""
    if isinstance(raw, dict):
        return {k: unaliased(v) for k, v in raw.items()}
    if isinstance(raw, list):
        return [unaliased(v) for v in raw]
    return copy.deepcopy(raw)
