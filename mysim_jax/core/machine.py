"""The machine a number was measured on, in one line (no JAX).

Machines sold under one name ("AMD EPYC", 2 cores) differ several times in speed, so every
wall time the project reports names its machine: the CPU's model name with its family and
model numbers and widest vector extension, and the cores this process may use. Training
runs record it in ``summary.json``, the benchmark in BENCHMARKS.md's header.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name with its family and model numbers and widest vector extension
    (from ``/proc/cpuinfo``), e.g. ``AMD EPYC (family 23, model 1, AVX2)``."""
    try:
        fields: dict[str, str] = {}
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if not line.strip():
                break                                  # the first processor's block is enough
            key, _, value = line.partition(":")
            fields[key.strip()] = value.strip()
    except OSError:
        return platform.processor() or "unknown"
    name = fields.get("model name", platform.processor() or "unknown")
    flags = set(fields.get("flags", "").split())
    vector = next((v for f, v in (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX")) if f in flags), None)
    details = [f"family {fields['cpu family']}" if "cpu family" in fields else None,
               f"model {fields['model']}" if "model" in fields else None, vector]
    details = [d for d in details if d]
    return f"{name} ({', '.join(details)})" if details else name


def usable_cores() -> int:
    """Cores this process may run on (its affinity), else the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def machine() -> str:
    """``CPU model (family, model, vector), N cores``: what a wall time is measured on."""
    return f"{cpu_model()}, {usable_cores()} cores"
