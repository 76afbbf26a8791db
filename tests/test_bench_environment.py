"""The capture-environment section's pure pieces (mysim_jax/bench/environment.py): the stage
variants of where a team step's time goes, the target line and the findings written from
measured call times. Nothing here is compiled or timed."""

from __future__ import annotations

from types import SimpleNamespace

from mysim_jax.bench import environment
from mysim_jax.bench.timing import ThroughputRow

ENV = SimpleNamespace(control_steps=4, scene=SimpleNamespace(substeps=10))
CFG = SimpleNamespace(env_repeats=3, env_first_max_batch=1024)
TIMES = {"env": 1.5, "physics": 1.0, "no_contact": 0.6, "no_line_contact": 0.9, "no_friction": 0.95,
         "no_drag": 0.8, "no_target_drag": 1.0, "no_wind": 0.99}


def test_the_stage_variants_remove_one_stage_each_from_the_physics():
    variants = environment._stage_variants(12)
    assert list(variants) == list(TIMES)
    assert variants["env"][2] == "env" and all(v[2] == "control" for k, v in variants.items() if k != "env")
    assert "12 control periods" in variants["physics"][0]
    assert variants["physics"][1] == [] and variants["no_contact"][1] == ["contact=null"]
    assert variants["no_drag"][1] == ["net.line.drag_coefficient=0", "net.tethers.line.drag_coefficient=0"]


def test_the_stage_table_names_the_rate_at_the_largest_batch_and_where_the_targets_are():
    variants = environment._stage_variants(4)
    rows = [ThroughputRow("4096", 4096, 1, [4096 / 10_000.0], 1.0, 1.0)]
    text = "\n".join(environment._stage_table(CFG, ENV, rows, 256, variants, TIMES))
    assert "targets are section (i)'s (at 10 Hz); at B = 4096 this section's environment runs 10,000.0 team steps/s" in text
    assert "MET" not in text
    assert "### Where a team step's time goes (B = 256)" in text
    assert "| physics without contact (`contact: null`) | 0.600 | 0.60× |" in text


def test_the_stage_findings_are_shares_of_the_physics():
    per_sub = TIMES["physics"] / (256 * 4 * 10)
    text = "\n".join(environment._stage_findings(CFG, ENV, 256, TIMES, per_sub, 25))
    assert "A team step is 4 control periods × 10 physics sub-steps = 40 sub-steps" in text
    assert "40 sub-steps of the whole multibody system; the physics alone runs 10,240 sub-steps/s" in text
    assert "adds 50% to the physics of a team step" in text
    assert "Contact costs 40% of the physics" in text and "1.67× faster" in text
    assert "allow 25 sub-steps per period instead of 10" in text
    assert "line drag 20%" in text and "wind 1%" in text
