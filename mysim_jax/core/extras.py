"""Optional dependencies: which extra installs them, and a clear error when one is missing.

``pip install -e .`` installs what simulation, the environment and training need. The rest
are extras (``pyproject.toml``): ``perception`` (gtsam for VIO, evo for trajectory error
metrics, allantools for the IMU's Allan deviation), ``plots`` (plotly, for the interactive
HTML replay), ``bench`` (MuJoCo and SciPy, the benchmark's independent references),
``blender``, ``gpu``. The module that needs one asks :func:`require` before it imports it.
"""

from __future__ import annotations

import importlib.util

# import name -> (distribution, extra)
EXTRAS = {
    "gtsam": ("gtsam", "perception"),
    "evo": ("evo", "perception"),
    "allantools": ("allantools", "perception"),
    "plotly": ("plotly", "plots"),
    "mujoco": ("mujoco", "bench"),
    "scipy": ("scipy", "bench"),
}


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message says which extra installs it."""


def available(module: str) -> bool:
    """Whether ``module`` can be imported (without importing it)."""
    return importlib.util.find_spec(module) is not None


def require(what: str, *modules: str) -> None:
    """Raise :class:`MissingExtra` naming the extras to install when any of ``modules`` is
    missing; ``what`` says what needs them (e.g. ``"scripts/perceive.py"``)."""
    missing = [m for m in modules if not available(m)]
    if missing:
        extras = sorted({EXTRAS[m][1] for m in missing if m in EXTRAS})
        raise MissingExtra(f"{what} needs {', '.join(missing)}, not installed: pip install -e '.[{','.join(extras)}]' "
                           f"(or pip install {' '.join(EXTRAS.get(m, (m,))[0] for m in missing)})")
