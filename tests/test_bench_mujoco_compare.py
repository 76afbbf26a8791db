"""The MuJoCo comparison's ratio line (mysim_jax/bench/mujoco_compare.py): our batched
throughput from section (a) over MuJoCo's steps/s, judged against the target, or a note
when (a) did not run in the same invocation."""

from __future__ import annotations

import pytest

from mysim_jax.bench import mujoco_compare
from mysim_jax.bench.report import TARGET_MUJOCO_RATIO


def test_without_section_a_the_ratio_is_left_out():
    results = {}
    assert mujoco_compare.ratio_lines(results, 1e5) == [
        "(Run section a in the same invocation for the ours / MuJoCo ratio.)", ""]
    assert "ratio" not in results


@pytest.mark.parametrize("factor, verdict", [(2.0, "MET"), (0.5, "NOT MET")])
def test_the_ratio_to_mujoco_is_judged_against_the_target(factor, verdict):
    results = {"ours_4096": factor * TARGET_MUJOCO_RATIO * 1e4}
    lines = mujoco_compare.ratio_lines(results, 1e4)
    assert results["ratio"] == pytest.approx(factor * TARGET_MUJOCO_RATIO)
    assert f"= {factor * TARGET_MUJOCO_RATIO:.1f}×. Target ≥ {TARGET_MUJOCO_RATIO:.0f}×: {verdict}.**" in lines[0]
    assert lines[-1] == ""


def test_the_header_names_the_installed_mujoco():
    mujoco = pytest.importorskip("mujoco")
    assert mujoco_compare.MUJOCO_VERSION == mujoco.__version__
