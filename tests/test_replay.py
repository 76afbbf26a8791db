"""The interactive HTML replay (mysim_jax/io/replay.py): what it draws for every scene
kind, its geometry against the columns, bad input, and that the file draws and animates
in headless Chromium.

Browser tests use Debian's Chromium (/usr/bin/chromium) through playwright. Without it
they skip, unless MYSIM_REQUIRE_BROWSER=1, when they fail instead.
"""

from __future__ import annotations

import base64
import io
import os
import re
from pathlib import Path

import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import expand_capture, load_config
from mysim_jax.tasks.capture_plots import net_lines
from mysim_jax.io.replay import ReplayError, frame_rows, replay_figure, write_replay_html
from mysim_jax.core.npgeom import rotate

from conftest import CONFIGS, scene_files

SCENES = [p.stem for p in scene_files()]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


# --- helpers ---------------------------------------------------------------------------


def _decode(values):
    if isinstance(values, dict):
        return np.frombuffer(base64.b64decode(values["bdata"]), dtype=values["dtype"]).astype(float)
    return np.asarray(values, float)


def _xyz(trace):
    return np.stack([_decode(trace[a]) for a in "xyz"], axis=-1)


def _quat_z(angle):
    return np.stack([np.cos(angle / 2), 0 * angle, 0 * angle, np.sin(angle / 2)], axis=-1)


def _quat_mul(a, b):
    w1, v1 = a[..., :1], a[..., 1:]
    w2, v2 = b[..., :1], b[..., 1:]
    return np.concatenate([w1 * w2 - np.sum(v1 * v2, -1, keepdims=True),
                           w1 * v2 + w2 * v1 + np.cross(v1, v2)], axis=-1)


def _initial_positions(config):
    """Start positions (and body quaternions) of everything the scene moves, read from the
    config (rope masses evenly spaced between their ends, cameras at their mounts)."""
    full, _ = expand_capture(config)
    pos = {p.name: np.asarray(p.pos, float) for p in full.points}
    quat = {}
    for b in full.bodies:
        pos[b.name], quat[b.name] = np.asarray(b.pos, float), np.asarray(b.quat, float)
    for q in config.quadrotors:
        for cam in q.cameras:
            pos[cam.name] = pos[q.body] + rotate(quat[q.body], cam.offset)
            quat[cam.name] = _quat_mul(quat[q.body], np.asarray(cam.quat, float))
    ends = {a.name: np.asarray(a.pos, float) for a in full.anchors}
    for b in full.bodies:
        for m in b.markers:
            ends[f"{b.name}.{m.name}"] = pos[b.name] + rotate(quat[b.name], m.pos)
    for r in full.ropes:
        start, end = (pos.get(n, ends.get(n)) for n in (r.start, r.end))
        for k in range(r.n_masses):
            pos[f"{r.name}_{k}"] = start + (k + 1) / (r.n_masses + 1) * (end - start)
    return pos, quat


def synthetic_columns(config, n_rows=30, t_end=1.5):
    """Columns as trajectory_columns writes them (positions and quaternions only): the
    scene's start positions drifting by ``t·(0.2, -0.1, -0.3)`` m/s, every body turning
    about world z at 1 rad/s."""
    pos, quat = _initial_positions(config)
    t = np.linspace(0.0, t_end, n_rows)
    shift = t[:, None] * np.array([0.2, -0.1, -0.3])
    cols = {"time": t}
    for name, p in pos.items():
        for c, a in enumerate("xyz"):
            cols[f"{name}_{a}"] = p[c] + shift[:, c]
    for name, q in quat.items():
        turned = _quat_mul(_quat_z(t), q)
        for c, a in enumerate("wxyz"):
            cols[f"{name}_q{a}"] = turned[:, c]
    return cols


def _traces(fig):
    return {trace["name"]: trace for trace in fig["data"]}


# --- what is drawn, for every scene kind ------------------------------------------------


@pytest.mark.parametrize("name", SCENES)
def test_every_scene_kind_replays(name):
    config = load_config(CONFIGS / f"{name}.yaml")
    cols = synthetic_columns(config)
    fig = replay_figure(cols, config, max_frames=12)
    traces = _traces(fig)
    names = set(traces)

    expected = {q.body for q in config.quadrotors}
    if config.net is not None:
        expected.add("net")
        if config.net.tethers is not None:
            expected.add("tethers")
    if config.ropes:
        expected.add("ropes")
    if config.target is not None:
        expected |= {config.target.name, f"{config.target.name} trail"}
    if config.points:
        expected.add("points")
    if config.anchors:
        expected.add("anchors")
    if any(q.cameras for q in config.quadrotors):
        expected.add("cameras")
    drawn = {n.split(" (drawn")[0] for n in names}
    assert expected <= drawn, f"{name}: missing {expected - drawn}"
    has_ground = bool(config.quadrotors) or config.target is not None
    assert ("ground (z = 0)" in names) == has_ground

    # frames: evenly spaced rows, first and last kept; every frame updates every moving trace
    frames = fig["frames"]
    assert 2 <= len(frames) <= 12
    steps = fig["layout"]["sliders"][0]["steps"]
    assert [s["args"][0][0] for s in steps] == [f["name"] for f in frames]
    assert float(steps[-1]["label"]) == pytest.approx(cols["time"][-1], rel=1e-3)
    moving = frames[0]["traces"]
    for frame in frames:
        assert frame["traces"] == moving and len(frame["data"]) == len(moving)

    # fixed ranges with equal scale, holding everything drawn in every frame
    scene = fig["layout"]["scene"]
    ranges = np.array([scene[f"{a}axis"]["range"] for a in "xyz"])
    assert all(not scene[f"{a}axis"]["autorange"] for a in "xyz")
    spans = ranges[:, 1] - ranges[:, 0]
    ratio = np.array([scene["aspectratio"][a] for a in "xyz"])
    np.testing.assert_allclose(ratio, spans / spans.max(), rtol=1e-12)
    if has_ground:        # the ground is the floor of the view, with a small margin under it
        assert -max(0.05 * spans.max(), 0.1) - 1e-9 <= ranges[2, 0] <= 0.0
    for frame in frames:
        for data in frame["data"]:
            xyz = _xyz(data)
            xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
            assert np.all(xyz >= ranges[:, 0] - 1e-6) and np.all(xyz <= ranges[:, 1] + 1e-6)


def test_net_rows_and_columns_are_the_net_lines():
    """The net is drawn as row and column polylines: the same segments, between the same
    masses, as capture_plots.net_lines (which draws every edge separately)."""
    config = load_config(CONFIGS / "capture_env_falling.yaml")
    cols = synthetic_columns(config, n_rows=5)
    fig = replay_figure(cols, config)
    last = fig["frames"][-1]
    drawn = dict(zip([fig["data"][i]["name"] for i in last["traces"]], last["data"]))

    def segments(xyz):
        out = set()
        for a, b in zip(xyz[:-1], xyz[1:]):
            if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
                out.add(tuple(sorted((tuple(np.round(a, 5)), tuple(np.round(b, 5))))))
        return out

    reference = net_lines(cols, config)
    n_tethers = len(config.net.tethers.uavs)
    net_ref = set().union(*(segments(line[-1].astype(np.float32).astype(float)) for line in reference[:-n_tethers]))
    assert segments(_xyz(drawn["net"])) == net_ref
    assert len(net_ref) == 2 * 8 * 7 * (config.net.masses_per_edge + 1)
    # tethers end at the UAV's tether marker (not its centre): knot ... marker
    tethers = _xyz(drawn["tethers"])
    marker_end = tethers[np.isfinite(tethers[:, 0])][config.net.tethers.n_masses + 1]
    uav = config.net.tethers.uavs[0]
    pos = np.array([cols[f"{uav}_{a}"][-1] for a in "xyz"])
    q = np.array([cols[f"{uav}_q{a}"][-1] for a in "wxyz"])
    np.testing.assert_allclose(marker_end, pos + rotate(q, config.net.tethers.attach), atol=1e-5)


def test_quadrotor_glyph_follows_position_and_attitude():
    config = load_config(CONFIGS / "uav_camera_flight.yaml")
    cols = synthetic_columns(config, n_rows=20, t_end=np.pi / 2)     # the last row has turned 90 deg about z
    fig = replay_figure(cols, config)
    last = fig["frames"][-1]
    drawn = dict(zip([fig["data"][i]["name"].split(" (drawn")[0] for i in last["traces"]], last["data"]))
    glyph = _xyz(drawn["uav0"])          # tip0 tip2 gap tip1 tip3 gap centre nose
    centre, nose = glyph[6], glyph[7]
    pos = np.array([cols[f"uav0_{a}"][-1] for a in "xyz"])
    np.testing.assert_allclose(centre, pos, atol=1e-5)
    heading = (nose - centre) / np.linalg.norm(nose - centre)
    np.testing.assert_allclose(heading, [0.0, 1.0, 0.0], atol=1e-5)        # body +x turned onto world +y
    arms = [glyph[1] - glyph[0], glyph[4] - glyph[3]]
    for arm in arms:
        assert abs(arm[2]) < 1e-5                                             # rotor plane stays level
    assert np.dot(arms[0], arms[1]) == pytest.approx(0.0, abs=1e-5)          # the paper's X layout
    # the camera's optical axis is its body +x: for cam_fixed (camera frame = UAV frame) also world +y
    cams = _xyz(drawn["cameras"])
    axis = cams[1] - cams[0]
    np.testing.assert_allclose(axis / np.linalg.norm(axis), [0.0, 1.0, 0.0], atol=1e-5)


def test_frame_rows():
    np.testing.assert_array_equal(frame_rows(5, 200), np.arange(5))
    rows = frame_rows(2001, 200)
    assert len(rows) == 200 and rows[0] == 0 and rows[-1] == 2000 and np.all(np.diff(rows) > 0)
    assert np.ptp(np.diff(rows)) <= 1
    np.testing.assert_array_equal(frame_rows(3, 1), [0])
    for bad in (0, -3, 2.5, True, "200"):
        with pytest.raises(ReplayError, match="max_frames"):
            frame_rows(10, bad)


def test_bad_input_is_a_clear_error(tmp_path):
    config = load_config(CONFIGS / "capture_env_falling.yaml")
    cols = synthetic_columns(config, n_rows=4)
    without = {k: v for k, v in cols.items() if not k.startswith("uav3_")}
    with pytest.raises(ReplayError, match=r"no columns for uav3.*scene 'capture_env_falling'.*config\.yaml"):
        write_replay_html(without, config, tmp_path / "r.html")
    no_quat = {k: v for k, v in cols.items() if k != "target_qw"}
    with pytest.raises(ReplayError, match=r"target \(target_qw\)"):
        replay_figure(no_quat, config)
    with pytest.raises(ReplayError, match="no 'time' column"):
        replay_figure({k: v for k, v in cols.items() if k != "time"}, config)
    with pytest.raises(ReplayError, match="no rows"):
        replay_figure({k: v[:0] for k, v in cols.items()}, config)
    with pytest.raises(ReplayError, match="trail"):
        replay_figure(cols, config, trail=-1.0)
    # a trajectory of another scene: the error lists what is missing, a few at a time
    rope = load_config(CONFIGS / "rope_net.yaml")
    with pytest.raises(ReplayError, match=r"payload, r0_0, .* more"):
        replay_figure(cols, rope)
    assert not (tmp_path / "r.html").exists()


# --- in the browser ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser():
    required = os.environ.get("MYSIM_REQUIRE_BROWSER") == "1"
    problem = None
    if not CHROMIUM.exists():
        problem = "Debian's chromium is not installed: apt-get install chromium"
    else:
        try:
            from playwright.sync_api import sync_playwright
        except ImportError:
            problem = "playwright is not installed: pip install -e '.[test]'"
    if problem:
        if required:
            pytest.fail(f"MYSIM_REQUIRE_BROWSER=1 but {problem}")
        pytest.skip(problem)
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
        yield chromium
        chromium.close()


def _open(browser, path):
    """Load the replay; returns the page and the console / page errors it reported."""
    page = browser.new_page(viewport={"width": 1000, "height": 750})
    errors = []
    page.on("console", lambda m: errors.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
    page.goto(Path(path).resolve().as_uri())
    page.wait_for_function("() => { const gd = document.getElementById('replay');"
                           " return gd && gd._fullLayout && gd._fullLayout.scene && gd._fullLayout.scene._scene; }",
                           timeout=20_000)
    page.wait_for_timeout(300)
    return page, errors


def _scene_pixels(page):
    """The screenshot's 3D scene area as an (h, w, 3) int array (title, legend, buttons and
    slider cut off)."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB")).astype(int)
    return img[90:600, 200:850]


def _near(img, hex_color, tol=40):
    rgb = np.array([int(hex_color[i:i + 2], 16) for i in (1, 3, 5)])
    return int(np.sum(np.abs(img - rgb).sum(axis=-1) < tol))


@pytest.mark.float64
def test_replay_of_a_simulated_run_draws_and_animates(browser, tmp_path):
    from mysim_jax.io.replay import ROPE_COLOR
    from mysim_jax.io.trajectory import trajectory_columns
    from mysim_jax.driver import simulate

    config = load_config(CONFIGS / "rope_net.yaml", ["sim.t_end=0.3", "sim.output_dt=0.01"])
    scene, params, state = build(config)
    cols = trajectory_columns(scene, simulate(scene, params, state, config.run_settings(), progress=False))
    path = write_replay_html(cols, config, tmp_path / "replay.html")
    html = path.read_text()
    assert not re.search(r"<script[^>]*\bsrc=", html)          # plotly.js inline: the file works offline
    assert "Plotly.newPlot" in html
    assert 3e6 < path.stat().st_size < 8e6

    page, errors = _open(browser, path)
    before = _scene_pixels(page)
    background = np.all(before > 235, axis=-1)
    assert background.mean() < 0.99, "the 3D scene is blank"
    assert len(np.unique((before // 16).reshape(-1, 3), axis=0)) > 20, "too few colours for a drawn scene"
    assert _near(before, ROPE_COLOR) > 100, "the ropes are not drawn"
    assert _near(before, "#d62728") > 10, "the payload is not drawn"

    # drag the slider's grip to 80 % of its rail: the frame (and the picture) changes
    rail = page.locator(".slider-rail-rect").bounding_box()
    grip = page.locator(".slider-grip-rect").bounding_box()
    y = grip["y"] + grip["height"] / 2
    page.mouse.move(grip["x"] + grip["width"] / 2, y)
    page.mouse.down()
    page.mouse.move(rail["x"] + 0.8 * rail["width"], y, steps=4)
    page.mouse.up()
    page.wait_for_timeout(500)
    active = page.evaluate("() => document.getElementById('replay')._fullLayout.sliders[0].active")
    n_frames = len(cols["time"])
    assert abs(active - 0.8 * (n_frames - 1)) <= 2
    after = _scene_pixels(page)
    changed = np.any(np.abs(after - before) > 30, axis=-1).mean()
    assert changed > 0.002, "moving the slider did not change the picture"
    assert errors == []


def test_capture_replay_draws_in_the_browser(browser, tmp_path):
    from mysim_jax.io.replay import NET_COLOR, TARGET_COLOR

    config = load_config(CONFIGS / "capture_env_falling.yaml")
    path = write_replay_html(synthetic_columns(config, n_rows=10), config, tmp_path / "capture.html")
    page, errors = _open(browser, path)
    img = _scene_pixels(page)
    assert _near(img, NET_COLOR, tol=30) > 200, "the net is not drawn"
    assert _near(img, TARGET_COLOR, tol=30) > 50, "the target is not drawn"
    assert _near(img, "#1f77b4") > 10, "uav0 is not drawn"
    assert errors == []
