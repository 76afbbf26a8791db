"""Shared test setup.

Tests marked ``@pytest.mark.float64`` run inside ``jax.enable_x64(True)``; all others run
in JAX's default 32-bit mode, so the switch never leaks into float32 tests.
"""

from __future__ import annotations

from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


@pytest.fixture(autouse=True)
def _x64_for_marked_tests(request):
    if request.node.get_closest_marker("float64") is not None:
        with jax.enable_x64(True):
            yield
    else:
        yield
