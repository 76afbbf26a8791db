"""mysim_jax: a JAX-vectorised, differentiable multibody simulator of quadrotor teams
carrying a tethered net (docs/library.md is the map of the package).

Importing the package sets one XLA flag for the CPU backend, unless ``XLA_FLAGS`` already
names it: ``--xla_cpu_enable_concurrency_optimized_scheduler=false``. With XLA's
concurrency-optimised scheduler, some of the trainer's vmapped programs on jaxlib 0.10's
CPU backend never finish (every thread parked on a lock, nothing computing); without it
they hang far less often, though not never (docs/training.md, "Known problem", has the
counts and the workaround). The scheduler orders the same operations, so the values are
the same; its effect on speed has not been measured by ``scripts/bench.py``. It is set here, before
JAX starts a backend (XLA reads ``XLA_FLAGS`` then), and imports nothing; a backend
started before ``mysim_jax`` is imported keeps the flags it started with.
"""

import os

_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
if _SCHEDULER_FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_SCHEDULER_FLAG}=false".strip()
