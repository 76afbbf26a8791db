"""The throughput sections' pure pieces (mysim_jax/bench/throughput.py): which step variants
the profile (f) times, its findings from measured rates, the HLO op census, the kernel table
of (a) and the throughput plot. Nothing here is timed."""

from __future__ import annotations

from mysim_jax.bench import throughput
from mysim_jax.bench.timing import ThroughputRow


def test_a_throughput_row_counts_env_steps_per_second_from_the_median_call():
    row = ThroughputRow("64", 64, 100, [1.0, 2.0, 4.0], 0.5, 1024.0)
    assert row.env_steps_per_s == 64 * 100 / 2.0


def test_the_profile_times_eight_variants_and_five_in_quick_mode():
    # the variants are compiled lazily: listing them builds nothing
    full = throughput._profile_variants(None, None, None, 4096, 100, quick=False)
    quick = throughput._profile_variants(None, None, None, 4096, 100, quick=True)
    assert [k for k, _, _ in full] == ["library", "first", "matmul", "index", "params_batched", "chunked", "floor",
                                       "kernel"]
    assert [k for k, _, _ in quick] == ["library", "first", "index", "floor", "kernel"]
    assert "the 4096 envs as 64 chunks × 64" in dict((k, d) for k, d, _ in full)["chunked"]


def test_profile_findings_compare_every_variant_with_the_library():
    rate = {"library": 100.0, "first": 50.0, "kernel": 125.0, "floor": 400.0, "chunked": 130.0, "index": 90.0}
    lines = throughput._profile_findings(rate)
    text = "\n".join(lines)
    assert "run at 400 env-steps/s, 4.0× the library" in text
    assert "(`jax.vmap`) for the same per-environment code: 2.00×; against the hand-written kernel: 0.80×" in text
    assert "`x[index_array]` gathers instead: 0.90× the library" in text and "matmul" not in text
    assert "64 chunks (a call-site change): 1.30× — cache blocking helps." in text
    assert "params" not in text and lines[-1] == ""


def test_hlo_census_counts_ops_by_name():
    text = ("%a = f32[4] gather(%x, %i)\n%b = f32[4] gather(%y, %j)\n%c = f32[4,4] dot(%a, %b)\n"
            "%d = f32[4] fusion(%c), kind=kLoop\n%e = f32[4] custom-call(%d)")
    census = throughput._hlo_census(text)
    assert census == {"gather": 2, "scatter": 0, "transpose": 0, "copy": 0, "dot": 1, "concatenate": 0, "fusion": 1}


def test_the_kernel_table_gives_each_batch_the_library_over_kernel_ratio():
    rows = {}
    for b, lib, ker, first in ((64, 2.0, 4.0, 1.0), (1024, 1.0, 1.25, 0.5)):
        rows[f"B={b}"] = ThroughputRow(f"{b}", b, 10, [lib], 1.0, 1.0)
        rows[f"B={b} kernel"] = ThroughputRow("kernel", b, 10, [ker], 1.0, 1.0)
        rows[f"B={b} jax.vmap"] = ThroughputRow("first", b, 10, [first], 1.0, 1.0)
    ratio = {b: rows[f"B={b}"].env_steps_per_s / rows[f"B={b} kernel"].env_steps_per_s for b in (64, 1024)}
    first = {b: rows[f"B={b}"].env_steps_per_s / rows[f"B={b} jax.vmap"].env_steps_per_s for b in (64, 1024)}
    lines = throughput._kernel_table((64, 1024), rows, ratio, first)
    assert lines[1] == "### Against a hand-written batch-last kernel and against `jax.vmap`"
    assert lines[-2] == "| 64 | 320 | 160 | **2.00×** | 640 | 0.50× |"
    assert lines[-1] == "| 1024 | 10,240 | 8,192 | **1.25×** | 20,480 | 0.50× |"


def test_the_throughput_plot_needs_section_a(tmp_path):
    assert throughput.plot_throughput({}, tmp_path) is None
    rows = [ThroughputRow(f"{b}", b, 10, [0.01], 1.0, 1.0) for b in (1, 64)]
    rows.append(ThroughputRow("64, params batched too", 64, 10, [0.01], 1.0, 1.0))
    path = throughput.plot_throughput({"a": rows, "mujoco_steps_per_s": 1e4}, tmp_path)
    assert path == tmp_path / "throughput.png" and path.stat().st_size > 0
