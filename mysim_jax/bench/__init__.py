"""Measurement harnesses behind the scripts that write the project's reports
(``scripts/bench.py`` → ``BENCHMARKS.md``, its sections in the modules here and the report's
assembly in :mod:`mysim_jax.bench.report`; ``scripts/stability_margin.py`` →
``docs/stability.md``); tests reach the same code."""
