"""The scenes and settings of the accuracy study (mysim_jax/bench/accuracy_cases.py): which
scenes run in quick and full mode, what the method builders put in their overrides, and the
tolerance highlights. Nothing is simulated."""

from __future__ import annotations

import pytest

from mysim_jax.bench import accuracy_cases as ac

FULL = ["rope_net", "rope_net_slack", "rope_net_stiff", "collision_light", "collision_heavy", "capture_falling"]


def test_quick_mode_runs_every_scene_but_the_heavy_contact_one_with_fewer_methods():
    quick, full = ac.accuracy_cases(True), ac.accuracy_cases(False)
    assert [c.name for c in full] == FULL
    assert [c.name for c in quick] == [n for n in FULL if n != "collision_heavy"]
    for q in quick:
        f = next(c for c in full if c.name == q.name)
        assert 0 < len(q.methods) < len(f.methods), q.name
        assert all(m.precision in ("float32", "float64") for m in f.methods)
    capture = {c.name: c for c in quick}["capture_falling"]
    assert "sim.substeps=52" in capture.reference and capture.reference_check == ()
    assert "sim.substeps=400" in full[-1].reference and full[-1].reference_check


def test_the_stiff_rope_net_is_the_rope_net_with_stiff_lines_and_its_own_methods():
    cases = {c.name: c for c in ac.accuracy_cases(False)}
    stiff, rope = cases["rope_net_stiff"], cases["rope_net"]
    assert stiff.config == rope.config and stiff.quantity is rope.quantity
    assert stiff.overrides == tuple(f"ropes.{i}.EA=1e+09" for i in range(4))
    assert stiff.methods == ac.stiff_methods(False) and not stiff.order_note and rope.order_note


def test_the_method_builders_write_the_settings_into_their_overrides():
    fixed = ac.fixed_step_methods("rk4", (1e-4, 3e-4), ("float64", "float32"))
    assert [(m.setting, m.precision, m.step) for m in fixed] == [
        ("dt = 1e-04", "float64", 1e-4), ("dt = 1e-04", "float32", 1e-4),
        ("dt = 3e-04", "float64", 3e-4), ("dt = 3e-04", "float32", 3e-4)]
    assert fixed[0].overrides == ("sim.integrator=rk4", "sim.dt=0.0001", "sim.substeps=1")
    sub = ac.substep_methods("rk4", 2e-3, (26,), ("float64",))[0]
    assert sub.step == pytest.approx(2e-3 / 26) and sub.setting == "h = 7.69e-05 (26 sub-steps)"
    assert sub.overrides == ("sim.integrator=rk4", "sim.substeps=26")
    default, given = ac.adaptive_methods("tsit5", (1e-8,), "float64")[0], ac.adaptive_methods(
        "tsit5", (1e-5,), "float32", max_steps=10, atol=1e-6)[0]
    assert default.setting == "rtol = 1e-08" and "sim.atol=1e-10" in default.overrides
    assert given.setting == "rtol = 1e-05, atol = 1e-06" and given.max_steps == 10 and given.step is None


def test_tolerance_highlights_name_the_cheapest_run_for_each_error():
    case = ac.AccuracyCase("c", ac.CAPTURE_FALLING, "target and net-knot positions [m]", lambda *a: None,
                           extra=(("target", lambda *a: None),), tolerances=(1e-2, 1e-4))
    cheap = ac.AccuracyRow("c", ac.Method("rk4", "h = 1e-04", (), "float32"), "ok", 5e-3, 0.1, extra_errors=(2e-3,))
    exact = ac.AccuracyRow("c", ac.Method("rk4", "h = 1e-05", (), "float64"), "ok", 5e-5, 1.0, extra_errors=(2e-5,))
    rejected = ac.AccuracyRow("c", ac.Method("rk4", "h = 1e-03", (), "float64"), "unstable (rejected)")
    lines = ac.tolerance_highlights(case, [exact, cheap, rejected])
    assert lines == [
        "- cheapest run with target and net-knot positions within 0.01 m: **rk4 h = 1e-04 float32** "
        "(5.0e-03 m, 0.100 s per simulated s)",
        "- cheapest run with target and net-knot positions within 0.0001 m: **rk4 h = 1e-05 float64** "
        "(5.0e-05 m, 1.000 s per simulated s)",
        "- cheapest run with target within 0.01 m: **rk4 h = 1e-04 float32** (2.0e-03 m, 0.100 s per simulated s)",
        "- cheapest run with target within 0.0001 m: **rk4 h = 1e-05 float64** (2.0e-05 m, 1.000 s per simulated s)",
        "- rk4 h = 1e-03 float64: unstable (rejected)",
        ""]
