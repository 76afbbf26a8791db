"""Random edits of a parsed YAML document, shared by the property-based config tests
(tests/test_fuzz_config.py, tests/test_fuzz_train_config.py)."""

from __future__ import annotations

import copy

from hypothesis import strategies as st


def yaml_paths(node, prefix=()):
    """Every path (tuple of keys / indices) to a value in a parsed YAML document."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += yaml_paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += yaml_paths(v, prefix + (i,))
    return out


def edit(draw, raw, junk, unknown_keys, duplicate: bool = False):
    """A copy of ``raw`` with 1 to 3 random edits: a value replaced by one of ``junk``, a
    key deleted, an unknown key (one of ``unknown_keys``) added, or, with ``duplicate``,
    a list entry repeated."""
    raw = copy.deepcopy(raw)
    actions = ["replace", "replace", "replace", "delete", "unknown_key"] + (["duplicate"] if duplicate else [])
    for _ in range(draw(st.integers(1, 3))):
        paths = yaml_paths(raw)
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = raw
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(actions))
        if action == "replace":
            parent[path[-1]] = draw(junk)
        elif action == "delete":
            del parent[path[-1]]
        elif action == "unknown_key" and isinstance(parent, dict):
            parent[draw(st.sampled_from(unknown_keys))] = draw(junk)
        elif action == "duplicate" and isinstance(parent, list):
            parent.append(copy.deepcopy(parent[path[-1]]))
    return raw
