"""The accuracy section's pure pieces (mysim_jax/bench/accuracy.py): the observed order of the
fixed-step methods from rows of known error, the highlights, a case's table and the precision
switch. Rows are synthetic; nothing is simulated."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.bench import accuracy
from mysim_jax.bench.accuracy_cases import AccuracyCase, AccuracyRow, Method, fixed_step_methods
from mysim_jax.bench.report import ROPE_NET


def _rows(integrator: str, precision: str, order: int, steps=(1e-4, 2e-4, 4e-4), c: float = 3.0):
    return [AccuracyRow("case", m, "ok", c * m.step ** order, 1e-3 / m.step)
            for m in fixed_step_methods(integrator, steps, (precision,))]


def test_the_observed_order_is_the_slope_of_log_error_against_log_step():
    rejected = AccuracyRow("case", Method("rk4", "dt = 1e-03", (), "float64", step=1e-3), "unstable (rejected)")
    adaptive = AccuracyRow("case", Method("tsit5", "rtol = 1e-08", (), "float64"), "ok", 1e-9, 1.0)
    rows = (_rows("semi_implicit_euler", "float64", 1) + _rows("rk4", "float64", 4) + [rejected, adaptive]
            + _rows("rk4", "float32", 4, steps=(1e-4,)))          # one point: no slope
    orders = accuracy.observed_orders(rows)
    assert set(orders) == {("semi_implicit_euler", "float64"), ("rk4", "float64")}
    assert orders[("semi_implicit_euler", "float64")]["slope"] == pytest.approx(1.0)
    rk4 = orders[("rk4", "float64")]
    assert rk4["slope"] == pytest.approx(4.0) and rk4["pairs"] == pytest.approx([4.0, 4.0])
    assert rk4["steps"] == pytest.approx([1e-4, 2e-4, 4e-4])
    case = AccuracyCase("rope", ROPE_NET, "payload z [m]", lambda *a: None)
    lines = accuracy.order_lines(case, orders)
    assert lines[0].startswith("Observed order on rope (error ∝ h^p;")
    assert "- rk4 float64: **p = 4.00** (h = 0.0001, 0.0002, 0.0004 s; neighbouring slopes 4.00, 4.00)" in lines
    assert accuracy.order_lines(case, {}) == []


def test_the_highlights_pick_the_cheapest_run_within_each_tolerance():
    fast = AccuracyRow("case", Method("rk4", "dt = 2e-04", (), "float32"), "ok", 1e-4, 0.1)
    good = AccuracyRow("case", Method("rk4", "dt = 1e-04", (), "float64"), "ok", 1e-7, 0.3)
    best = AccuracyRow("case", Method("tsit5", "rtol = 1e-10", (), "float64"), "ok", 1e-10, 2.0)
    failed = AccuracyRow("case", Method("kvaerno5", "rtol = 1e-04", (), "float64"), "did not finish")
    lines = accuracy.accuracy_highlights([best, good, fast, failed])
    assert lines == ["- cheapest run within 0.0002 m: rk4 dt = 2e-04 float32 (1.0e-04 m, 0.100 s per simulated s)",
                     "- cheapest run within 1e-06 m: rk4 dt = 1e-04 float64 (1.0e-07 m, 0.300 s per simulated s)",
                     "- cheapest run within 1e-09 m: tsit5 rtol = 1e-10 float64 (1.0e-10 m, 2.000 s per simulated s)",
                     "- kvaerno5 rtol = 1e-04 float64: did not finish", ""]


def test_the_contact_highlights_ask_for_a_tenth_of_the_drift_tolerance():
    case = AccuracyCase("collision", ROPE_NET, "ball and payload z [m]", lambda *a: None, t_end=1.5,
                        drift_tolerance=2e-3)
    lucky = AccuracyRow("collision", Method("semi_implicit_euler", "dt = 1e-06", (), "float64"), "ok", 1e-3, 0.5,
                        drift_time=None)
    robust = AccuracyRow("collision", Method("tsit5", "rtol = 1e-12", (), "float64"), "ok", 1e-5, 2.0)
    drifting = AccuracyRow("collision", Method("rk4", "dt = 2e-06", (), "float64"), "ok", 5e-2, 1.0,
                           drift_time=0.75)
    text = "\n".join(accuracy.contact_highlights(case, [lucky, robust, drifting]))
    assert "Fastest single run within 0.002 m over 1.5 s: semi_implicit_euler dt = 1e-06 float64" in text
    assert ("Fastest within 0.0002 m (tolerance / 10, robust to the scene's chaos): "
            "**tsit5 rtol = 1e-12 float64**") in text
    assert "- no rk4 run stays within 0.0002 m (dt = 2e-06 float64: 5.0e-02 m, drifts past 0.002 m at 0.750 s" in text


def test_a_case_table_has_a_drift_column_when_the_case_has_a_tolerance():
    plain = AccuracyCase("rope", ROPE_NET, "payload z [m]", lambda *a: None)
    drift = AccuracyCase("collision", ROPE_NET, "ball z [m]", lambda *a: None, drift_tolerance=2e-3,
                         extra=(("ball", lambda *a: None),))
    ok = AccuracyRow("x", Method("rk4", "dt = 1e-04", (), "float64", note="capped"), "ok", 1e-3, 0.25, 1.5,
                     drift_time=0.5, extra_errors=(2e-3,))
    bad = AccuracyRow("x", Method("rk4", "dt = 1e-03", (), "float32"), "diverged (non-finite)")
    lines = accuracy._case_table(plain, [dataclasses.replace(ok, extra_errors=()), bad])
    assert lines[0].endswith("| wall s / simulated s | compile [s] | status |") and "drift" not in lines[0]
    assert lines[2] == "| rk4 | dt = 1e-04 | float64 | 1.000e-03 | 0.250 | 1.5 | ok (capped) |"
    assert lines[3] == "| rk4 | dt = 1e-03 | float32 | — | — | — | diverged (non-finite) |"
    lines = accuracy._case_table(drift, [ok, bad])
    assert "drifts past 0.002 m at [s]" in lines[2] and "max error, ball [m]" in lines[2]
    assert lines[4] == "| rk4 | dt = 1e-04 | float64 | 1.000e-03 | 2.000e-03 | 0.500 | 0.250 | 1.5 | ok (capped) |"
    assert lines[5] == "| rk4 | dt = 1e-03 | float32 | — | — | n/a | — | — | diverged (non-finite) |"


def test_precision_mode_switches_jax_between_64_and_32_bits():
    with accuracy.precision_mode("float64"):
        assert jnp.zeros(1).dtype == np.float64
    with accuracy.precision_mode("float32"):
        assert jnp.zeros(1).dtype == np.float32
