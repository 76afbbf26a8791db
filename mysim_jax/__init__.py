"""mysim_jax: a JAX-vectorised, differentiable multibody simulator of quadrotor teams
carrying a tethered net (docs/library.md is the map of the package).

Importing the package sets one XLA flag for the CPU backend, unless ``XLA_FLAGS`` already
names it: ``--xla_cpu_enable_concurrency_optimized_scheduler=false``. With XLA's
concurrency-optimised scheduler, some of the trainer's vmapped programs on this jaxlib
never finish on a 2-core CPU (every thread parked on a futex, nothing computing: the
seeds' initialisation of ``scripts/train.py --seeds`` hung in most runs), and with the
default scheduler they finish every time; it computes the same values, and
``scripts/bench.py`` measured no speed difference between the two. It is set here, before
JAX starts a backend (XLA reads ``XLA_FLAGS`` then), and imports nothing; a backend
started before ``mysim_jax`` is imported keeps the flags it started with.
"""

import os

_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler"
if _SCHEDULER_FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_SCHEDULER_FLAG}=false".strip()
