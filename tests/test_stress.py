"""The declared stress suite (mysim_jax/tasks/stress.py, scripts/stress.py): the committed
stress files plan to the shifts they declare (each point's scene checked: the factor's
draw or perception block set to the value, everything else at the training ranges); bad
files are one-line errors; the criterion, the table and the figure from given results;
the script runs every sweep, then resumes from the sweeps already written.

Nothing here compiles a simulation: the sweeps themselves are scripts/sweep.py's
(tests/test_sweep_script.py); the script's own loop runs with a stand-in for the sweep."""

from __future__ import annotations

import json

import pytest
import yaml

from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.tasks.stress import (NOMINAL, factor_override, load_stress, perception_block, plan_stress,
                                    stress_rows, table_markdown, write_stress)

from conftest import ROOT, run_script_main

STRESS = ROOT / "configs" / "stress"


def test_every_committed_stress_file_loads_and_names_what_exists():
    """Every stress file validates, names a scene, teams and a perception block that are
    in the repository, and its scene loads at its level (a run folder's scene.yaml holds
    the level train only; the planning of the two tasks' own files is checked below; the
    others reuse their scenes and factors)."""
    files = sorted(STRESS.glob("*.yaml"))
    assert len(files) >= 5
    for path in files:
        cfg = load_stress(path)
        for spec in (cfg.scene, cfg.policy, cfg.compare, cfg.perception):
            if spec is not None and spec not in ("scripted", "random"):
                assert (ROOT / spec).exists(), (path.name, spec)
        assert load_config(ROOT / cfg.scene, [f"level={cfg.level}"]).level == cfg.level, path.name


@pytest.mark.parametrize("name", ["falling", "maneuvering"])
def test_committed_stress_files_plan_the_shifts_they_declare(name, tmp_path):
    cfg = load_stress(STRESS / f"{name}.yaml")
    plan = plan_stress(STRESS / f"{name}.yaml", tmp_path / "out")
    scene = load_config(ROOT / cfg.scene, [f"level={cfg.level}"])
    assert [n for n, _ in plan.sweeps] == [NOMINAL] + [f.name for f in cfg.factors]
    nominal = plan.sweeps[0][1]
    assert len(nominal.points) == 1 and nominal.points[0].seed == cfg.seed
    assert nominal.points[0].config.env.randomize == scene.env.randomize and nominal.points[0].config.level == cfg.level
    block = perception_block(ROOT / cfg.perception)
    for (_, sweep), f in zip(plan.sweeps[1:], cfg.factors):
        assert [p.seed for p in sweep.points] == [cfg.seed] * len(f.values)
        assert sweep.episodes == cfg.episodes and sweep.policy == cfg.policy and sweep.compare == cfg.compare
        lo, hi = plan.ranges[f.name]
        for p, v in zip(sweep.points, f.values):
            env = p.config.env
            assert v > hi, f"{f.name} = {v} is not beyond the training range {lo}-{hi}"
            if f.kind == "draw":
                r = getattr(env.randomize, f.draw)
                assert r.low == r.high == v
            elif f.kind == "box":
                assert tuple(env.randomize.wind_force.high) == (v, v, 0.0)
                assert tuple(env.randomize.wind_force.low) == (-v, -v, 0.0)
            elif f.kind == "thrust_loss":
                t = env.randomize.thrust_loss
                assert t.fraction.low == t.fraction.high == pytest.approx(1.0 - v, abs=1e-12)
                assert (t.time.low, t.time.high) == f.fault_time
            elif f.kind == "latency":
                assert env.perception.target_latency == v and env.perception.target_position.sigma == 0.0
            else:
                for k, b in block.items():
                    if k in ("target_latency", "target_dropout"):       # the block's own, unscaled
                        got = getattr(env.perception, k)
                        assert (got.model_dump() if hasattr(got, "model_dump") else got) == b
                        continue
                    assert getattr(env.perception, k).sigma == pytest.approx(v * b["sigma"], rel=1e-12)
                    assert getattr(env.perception, k).correlation_time == b["correlation_time"]
                assert "scale" not in block and env.perception.scale.low == env.perception.scale.high == 1.0
            # every other draw keeps its training range
            for other in type(env.randomize).model_fields:
                if f.kind == "thrust_loss" and other == "thrust_loss":
                    continue
                if f.kind in ("perception_scale", "latency", "thrust_loss") or other != f.draw:
                    assert getattr(env.randomize, other) == getattr(scene.env.randomize, other), other
            if f.kind not in ("perception_scale", "latency"):
                assert env.perception is None


GOOD = {"name": "t", "scene": "docs/train/falling/scene.yaml", "policy": "scripted", "compare": "random",
        "episodes": 4, "batch": 4, "seed": 3,
        "factors": [{"name": "mass", "label": "target mass [kg]", "kind": "draw", "draw": "target_mass",
                     "values": [0.2, 0.3], "judged_at": 0.3}]}


def _file(tmp_path, **changes) -> str:
    data = json.loads(json.dumps(GOOD))
    factor = changes.pop("factor", {})
    data["factors"][0].update(factor)
    data.update(changes)
    path = tmp_path / "stress.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.mark.parametrize("changes, message", [
    ({"factor": {"judged_at": 0.25}}, "judged_at 0.25 is not one of values"),
    ({"factor": {"draw": None}}, "kind draw needs draw"),
    ({"factor": {"draw": "gravity"}}, "draw 'gravity' is not an env.randomize field"),
    ({"factor": {"draw": "wind_force"}}, "draw wind_force is a box range: write kind box"),
    ({"factor": {"kind": "perception_scale", "draw": None}}, "needs perception: the env.perception block file"),
    ({"factor": {"values": [0.2, 0.2], "judged_at": 0.2}}, "values repeat"),
    ({"factor": {"kind": "latency"}}, "kind latency takes no draw"),
    ({"factor": {"kind": "thrust_loss", "draw": None}}, "fault_time [low, high] (s) goes with kind thrust_loss"),
    ({"factor": {"kind": "thrust_loss", "draw": None, "fault_time": [0.5, 1], "values": [1.5], "judged_at": 1.5}},
     "at most 1"),
    ({"factor": {"name": "nominal"}}, "not 'nominal'"),
    ({"factor": {"values": [-0.1], "judged_at": -0.1}}, "values"),
    ({"episodes": 0}, "episodes"),
    ({"seeds": 3}, "seeds"),
])
def test_bad_stress_files_are_one_error_naming_the_problem(tmp_path, changes, message):
    with pytest.raises(ConfigError, match="stress.yaml") as err:
        load_stress(_file(tmp_path, **changes))
    assert message in str(err.value)


def test_a_perception_block_with_its_own_scale_is_refused(tmp_path):
    """The suite sets the errors' scale (the factor's values); a block's own would be lost."""
    block = yaml.safe_load((ROOT / "docs/perception_gap/perception_learned.yaml").read_text())
    path = tmp_path / "block.yaml"
    path.write_text(yaml.safe_dump({**block, "scale": {"low": 0.5, "high": 2.0}}))
    with pytest.raises(ConfigError, match="block.yaml: scale {low: 0.5, high: 2}: a stress suite sets"):
        perception_block(path)


def test_a_factor_the_scene_does_not_draw_is_refused(tmp_path):
    path = _file(tmp_path, scene="configs/capture_env_falling.yaml",
                 factor={"draw": "jink_acceleration", "values": [5.0], "judged_at": 5.0})
    with pytest.raises(ConfigError, match="does not draw env.randomize.jink_acceleration"):
        plan_stress(path, tmp_path / "out")


def test_the_files_scene_overrides_reach_every_point_and_the_table(tmp_path):
    """``set`` (scene overrides of every point, here the allocation's saturation handling)
    reaches the nominal and every shifted point, and the table says so; a bad one is
    refused naming the key before anything runs."""
    sets = [f"quadrotors.{i}.controller.saturation=attitude_priority" for i in range(4)]
    plan = plan_stress(_file(tmp_path, set=sets), tmp_path / "out")
    points = [p for _, sweep in plan.sweeps for p in sweep.points]
    assert len(points) == 3
    for p in points:
        assert [q.controller.saturation for q in p.config.quadrotors] == ["attitude_priority"] * 4
    plain = plan_stress(_file(tmp_path), tmp_path / "out2")
    assert {q.controller.saturation for _, s in plain.sweeps for p in s.points for q in p.config.quadrotors} == {"clip"}
    rows = stress_rows(plan, _records(plan, {NOMINAL: [(1.0, 1.0, -0.1, 0.1)],
                                             "mass": [(1.0, 1.0, -0.1, 0.1), (0.5, 0.5, -0.1, 0.1)]}))
    assert table_markdown(plan, rows).startswith("Every point with `quadrotors.0.controller.saturation=attitude_priority`")
    with pytest.raises(ConfigError, match="saturation"):
        plan_stress(_file(tmp_path, set=["quadrotors.0.controller.saturation=always"]), tmp_path / "out3")


def test_overrides_are_yaml_the_scene_loader_reads():
    cfg = load_stress(STRESS / "maneuvering.yaml")
    wind = next(f for f in cfg.factors if f.kind == "box")
    assert factor_override(wind, 0.5) == 'env.randomize.wind_force={"low": [-0.5, -0.5, -0.0], "high": [0.5, 0.5, 0.0]}'
    mass = next(f for f in cfg.factors if f.kind == "draw")
    assert factor_override(mass, 0.7) == 'env.randomize.target_mass={"low": 0.7, "high": 0.7}'
    scale = next(f for f in cfg.factors if f.kind == "perception_scale")
    assert factor_override(scale, 0.0) == "env.perception=null"
    latency = next(f for f in cfg.factors if f.kind == "latency")
    assert factor_override(latency, 0.06) == 'env.perception={"target_latency": 0.06}'
    assert load_config(ROOT / cfg.scene, [factor_override(latency, 0.1)]).env.perception.target_latency == 0.1
    with pytest.raises(ConfigError, match="more than one policy period"):
        load_config(ROOT / cfg.scene, [factor_override(latency, 0.15)])
    # a block with its own latency and losses: the error levels scale, the latency and the losses do not
    block = {"target_position": {"sigma": 0.1, "correlation_time": 1.0}, "target_latency": 0.03,
             "target_dropout": {"fraction": 0.05, "mean_duration": 0.3}}
    scaled = load_config(ROOT / cfg.scene, [factor_override(scale, 2.0, block)]).env.perception
    assert scaled.target_position.sigma == pytest.approx(0.2) and scaled.target_position.correlation_time == 1.0
    assert scaled.target_latency == 0.03 and scaled.target_dropout.model_dump() == block["target_dropout"]
    assert scaled.uav_position.sigma == 0.0


def _records(plan, rates: dict) -> dict:
    """Sweep records as run_sweep returns them: ``rates`` maps a sweep's name to one
    (policy, compare, difference low95, difference high95) per point."""
    out = {}
    for name, _ in plan.sweeps:
        rows = []
        for i, (p, c, low, high) in enumerate(rates[name]):
            rows.append({"point": i, "team": "policy", "episodes": 100, "success_rate": p, "success_low95": p - 0.05,
                         "success_high95": p + 0.04, "difference": p - c, "difference_low95": low,
                         "difference_high95": high})
            rows.append({"point": i, "team": "compare", "episodes": 100, "success_rate": c,
                         "success_low95": c - 0.05, "success_high95": c + 0.05})
        out[name] = {"rows": rows, "wall_s": 1.0}
    return out


def test_a_failing_value_is_shown_with_the_decimals_that_show_it_fails(tmp_path):
    """A lower end of -1.048 points against -1 fails and reads -1.05, not -1.0; a fraction
    of 0.7996 against 0.8 reads 0.7996; values away from the bound keep their usual digits."""
    path = _file(tmp_path, criterion={"fraction_of_nominal": 0.8, "lead_low95_points": -1})
    plan = plan_stress(path, tmp_path / "out")
    records = _records(plan, {NOMINAL: [(0.9, 0.4, 0.45, 0.55)],
                              "mass": [(0.9, 0.4, 0.4, 0.6), (0.71964, 0.3, -0.01048, 0.5)]})
    judged = [r for r in stress_rows(plan, records) if r["judged"]]
    assert judged[0]["failing"] == "0.7996 of nominal < 0.8; difference's lower end -1.05 < -1 points"
    records = _records(plan, {NOMINAL: [(0.9, 0.4, 0.45, 0.55)],
                              "mass": [(0.9, 0.4, 0.4, 0.6), (0.5, 0.3, -0.02, 0.5)]})
    judged = [r for r in stress_rows(plan, records) if r["judged"]]
    assert judged[0]["failing"] == "0.56 of nominal < 0.8; difference's lower end -2.0 < -1 points"


def test_the_criterion_the_table_and_the_figure(tmp_path):
    path = _file(tmp_path, factors=[GOOD["factors"][0], {**GOOD["factors"][0], "name": "mass_b"},
                                    {**GOOD["factors"][0], "name": "mass_c"}],
                 criterion={"fraction_of_nominal": 0.8, "lead_points": 20, "lead_low95_points": -1})
    plan = plan_stress(path, tmp_path / "out")
    records = _records(plan, {
        NOMINAL: [(0.9, 0.4, 0.45, 0.55)],
        "mass": [(0.85, 0.4, 0.4, 0.5), (0.75, 0.3, 0.40, 0.50)],        # judged 0.3: 0.83 of nominal, +45: meets
        "mass_b": [(0.9, 0.4, 0.4, 0.6), (0.70, 0.3, 0.35, 0.45)],       # 0.78 of nominal: fails
        "mass_c": [(0.9, 0.4, 0.4, 0.6), (0.80, 0.65, -0.02, 0.30)],     # +15 points, lower end -2: fails twice
    })
    rows = stress_rows(plan, records)
    assert [(r["factor"], r["value"]) for r in rows] == [(NOMINAL, None), ("mass", 0.2), ("mass", 0.3), ("mass_b", 0.2),
                                                         ("mass_b", 0.3), ("mass_c", 0.2), ("mass_c", 0.3)]
    judged = {r["factor"]: r for r in rows if r["judged"]}
    assert judged["mass"]["passes"] and judged["mass"]["fraction_of_nominal"] == pytest.approx(0.75 / 0.9)
    assert not judged["mass_b"]["passes"] and judged["mass_b"]["failing"] == "0.78 of nominal < 0.8"
    assert not judged["mass_c"]["passes"]
    assert judged["mass_c"]["failing"] == "difference +15.0 < +20 points; difference's lower end -2.0 < -1 points"
    assert not any(r["judged"] for r in rows if r["value"] == 0.2)
    table = table_markdown(plan, rows)
    assert "| nominal (training ranges) | – | – | 90.0% (85.0%–94.0%) | 40.0% (35.0%–45.0%) |" in table
    assert "| target mass [kg] | 0.3 | 0.08–0.15 |" in table and "**meets**" in table
    assert "**fails**: 0.78 of nominal < 0.8" in table
    (tmp_path / "out").mkdir()
    record = write_stress(plan, records, "cmd")
    assert record["judged"] == {"shifts": 3, "met": 1, "failing": ["mass_b", "mass_c"]}
    for name in ("stress.csv", "stress.json", "table.md", "stress.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0, name


def test_the_script_runs_every_sweep_then_resumes_from_them(tmp_path, capsys, monkeypatch):
    """The script's loop with a stand-in for the sweep (which writes sweep.json as the
    real one does): every sweep runs once; run again, each is read, none runs."""
    import mysim_jax.tasks.stress as stress

    path = _file(tmp_path)
    ran = []

    def fake_run_sweep(plan, make_policy, progress=True, command=""):
        ran.append(plan.out.name)
        n = len(plan.points)
        rows = _records(type("P", (), {"sweeps": [("x", None)]}), {"x": [(0.9, 0.5, 0.3, 0.5)] * n})["x"]["rows"]
        record = {"episodes": plan.episodes, "policy": plan.policy, "compare": plan.compare, "wall_s": 0.0,
                  "points": [{"point": p.index, "overrides": list(p.overrides), "seed": p.seed} for p in plan.points],
                  "rows": rows}
        plan.out.mkdir(parents=True, exist_ok=True)
        (plan.out / "sweep.json").write_text(json.dumps(record))
        return record

    monkeypatch.setattr(stress, "run_sweep", fake_run_sweep)
    out = tmp_path / "out"
    code, stdout, stderr, _ = run_script_main("stress", [path, "--out", out], capsys)
    assert code == 0, stderr
    assert ran == [NOMINAL, "mass"]
    assert "t: 1 of 1 judged shifts meet the criterion" in stdout
    code, stdout, stderr, compiled = run_script_main("stress", [path, "--out", out], capsys)
    assert code == 0, stderr
    assert ran == [NOMINAL, "mass"] and stdout.count("(already run)") == 2
    # fewer episodes is another plan: the sweeps run again
    code, stdout, stderr, _ = run_script_main("stress", [path, "--out", out, "--episodes", "2"], capsys)
    assert code == 0 and ran == [NOMINAL, "mass", NOMINAL, "mass"]


@pytest.mark.parametrize("args, message", [
    (["configs/stress/missing.yaml"], "missing.yaml"),
    (["configs/stress/falling.yaml", "--episodes", "0"], "episodes 0: must be at least 1"),
])
def test_bad_input_is_one_line_before_anything_compiles(tmp_path, capsys, args, message):
    code, out, err, compiled = run_script_main("stress", [*args, "--out", tmp_path / "out"], capsys)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
    assert all(seconds < 0.5 for _, seconds in compiled)
