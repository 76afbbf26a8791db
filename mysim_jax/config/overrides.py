"""``--set dotted.key=value`` overrides on a raw (YAML-parsed) config dict, before it is
validated: :func:`override_list` puts one load's overrides (a profile's, ``--set``, a
fidelity level, values a program sets itself) in the order they apply,
:func:`apply_override` edits one place, :func:`apply_overrides` a copy, :func:`unaliased`
first gives every place its own copy. No schema and no JAX: unknown keys are left for
validation to name."""

from __future__ import annotations

import copy
from typing import Any, Iterable, Mapping


def override_list(sets: Iterable[str] = (), *, first: Iterable[str] = (), level: str | None = None,
                  then: Mapping[str, Any] | None = None) -> list[str]:
    """One load's overrides as one list, in the order they apply (where two set the same
    key, the later one wins):

    1. ``first``: overrides that ``sets`` may change (a training file's profile, the gains
       of ``simulate.py --gains``, ``env={}`` for a scene without an ``env:`` block);
    2. ``sets``: the user's ``--set`` list, or a training file's ``env.set``;
    3. ``level=LEVEL`` when ``level`` is given (a scene's fidelity level; the scene loader
       applies a level's own values before every override, so the place here only decides
       which ``level=`` counts: this one);
    4. ``then``: ``{dotted key: value}`` that a program sets from its own options, over the
       user's (``run.seeds`` from ``--seeds``); each is ``key=value`` with ``str(value)`` as
       the YAML text, and a None value is left out.

    The entries are not parsed here: :func:`apply_override` names a malformed one when it
    is applied."""
    out = [*first, *sets]
    if level is not None:
        out.append(f"level={level}")
    out += [f"{key}={value}" for key, value in (then or {}).items() if value is not None]
    return out


def apply_overrides(raw: dict, overrides: Iterable[str]) -> dict:
    """``key=value`` overrides (``algo.lr=1e-3``) applied in order to a copy of a raw dict."""
    raw = copy.deepcopy(raw)
    for ov in overrides:
        apply_override(raw, ov)
    return raw

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
