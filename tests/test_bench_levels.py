"""Section (i)'s timed call (mysim_jax/bench/levels.py): a level's team step repeated so that
one timed call lasts about the time asked for."""

from __future__ import annotations

from mysim_jax.bench import levels


def test_a_repeated_call_runs_its_call_the_number_of_times_it_reports():
    calls = []
    fn, n = levels._repeated(lambda: calls.append(1), 0.0)       # two warm-up calls, at least one repeat
    assert n == 1 and len(calls) == 2
    fn()
    assert len(calls) == 3
    fn, n = levels._repeated(lambda: calls.append(1), 1e-2)      # a call of ~1 µs: many repeats per timed call
    assert n > 10
    before = len(calls)
    fn()
    assert len(calls) - before == n
