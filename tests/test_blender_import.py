"""The Blender importer (mysim_jax/io/blender_import.py): reading the CSV and guessing the
lines from the names (no Blender needed), then, where ``bpy`` imports, the keyframes of
every object against the CSV, the scene cameras, USD import, renders and the command line."""

from __future__ import annotations

import ast
import subprocess
import sys

import numpy as np
import pytest

from mysim_jax.config.scene import expand_capture, load_config
from mysim_jax.io import blender_import as bi
from mysim_jax.io.trajectory import write_trajectory_csv

from conftest import CONFIGS, ROOT
from test_replay import synthetic_columns

SCRIPT = ROOT / "mysim_jax" / "io" / "blender_import.py"
FPS = 25
DT = 0.02          # output step of the synthetic runs: two rows per frame at 25 fps
BPY_REASON = ("bpy (Blender as a Python module) is not installed: pip install -e '.[blender]' on Python 3.11; "
              "the importer also runs inside Blender: blender --background --python mysim_jax/io/blender_import.py")


def _csv(tmp_path, scene, n_rows=31, extra=None):
    config = load_config(CONFIGS / f"{scene}.yaml")
    cols = synthetic_columns(config, n_rows=n_rows, t_end=DT * (n_rows - 1))
    cols.update(extra or {})
    path = tmp_path / f"{scene}.csv"
    write_trajectory_csv(path, cols)
    return path, cols, config


def _expected_edges(config):
    """Pairs of names joined by a rope of the scene (markers stand for their body; a rope
    end at an anchor joins nothing: anchors are not in the CSV)."""
    full, _ = expand_capture(config)
    anchors = {a.name for a in full.anchors}
    edges = set()
    for r in full.ropes:
        names = [r.start.split(".")[0]] + [f"{r.name}_{k}" for k in range(r.n_masses)] + [r.end.split(".")[0]]
        edges |= {frozenset(pair) for pair in zip(names[:-1], names[1:]) if not anchors & set(pair)}
    return edges


def _edges(lines):
    return {frozenset(pair) for line in lines for pair in zip(line[:-1], line[1:])}


# --- without Blender ----------------------------------------------------------------------


def test_file_imports_only_what_blender_has():
    """Blender runs the file as a script: no mysim_jax, nothing beyond the standard library,
    NumPy, Blender's own modules and its sibling file (which imports no further)."""
    allowed = {"__future__", "argparse", "csv", "math", "re", "sys", "warnings", "dataclasses", "pathlib", "numpy",
               "bpy", "bmesh", "mathutils", "bpy_extras"}
    for path, also in ((SCRIPT, {"blender_layout"}), (SCRIPT.with_name("blender_layout.py"), set())):
        tree = ast.parse(path.read_text())
        modules = {a.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for a in node.names}
        modules |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
        assert modules <= allowed | also, (path.name, modules - allowed - also)


@pytest.mark.parametrize("scene", ["capture_env_falling", "capture_falling", "rope_net", "collision_light",
                                   "uav_camera_flight"])
def test_layout_from_the_names(tmp_path, scene):
    extra = {"uav0_ref_x": np.zeros(31), "uav0_ref_y": np.zeros(31), "uav0_ref_z": np.ones(31),
             "uav0_ref_yaw": np.zeros(31), "uav0_rotor1": np.ones(31)} if scene.startswith("uav") else None
    path, cols, config = _csv(tmp_path, scene, extra=extra)
    layout = bi.scene_layout(bi.read_columns(path))
    full, _ = expand_capture(config)
    bodies = [b.name for b in full.bodies] + [c.name for q in config.quadrotors for c in q.cameras]
    assert sorted(layout.bodies) == sorted(bodies)
    assert sorted(layout.points) == sorted(p.name for p in config.points)     # free points; rope masses are lines
    assert _edges(layout.lines) == _expected_edges(config)


def test_keyed_rows():
    t = np.arange(51) * 0.02                        # 50 Hz rows at 25 fps: every other row, on whole frames
    rows, frames = bi.keyed_rows(t, 25)
    np.testing.assert_array_equal(rows, np.arange(0, 51, 2))
    np.testing.assert_allclose(frames, np.arange(26), atol=1e-9)
    t = np.arange(11) * 0.1 + 3.0                   # sparser than the frame rate: every row, between frames
    rows, frames = bi.keyed_rows(t, 25)
    np.testing.assert_array_equal(rows, np.arange(11))
    np.testing.assert_allclose(frames, 2.5 * np.arange(11), atol=1e-9)
    t = np.arange(8) * 0.03                         # 0, 0.75, 1.5, ... frames: the nearest row per frame
    rows, frames = bi.keyed_rows(t, 25)
    np.testing.assert_array_equal(rows, [0, 1, 3, 4, 5, 7])
    for bad in (0, -25, 2.5, True):
        with pytest.raises(bi.BlenderImportError, match="fps"):
            bi.keyed_rows(t, bad)
    with pytest.raises(bi.BlenderImportError, match="increasing"):
        bi.keyed_rows([0.0, 0.1, 0.1], 25)


def test_continuous_quaternions():
    angle = np.linspace(0, 4 * np.pi, 40)
    q = np.stack([np.cos(angle / 2), 0 * angle, 0 * angle, np.sin(angle / 2)], axis=-1)
    flipped = q * np.where(np.arange(40) % 3 == 0, -1.0, 1.0)[:, None]
    out = bi.continuous_quaternions(flipped)
    assert np.all(np.sum(out[1:] * out[:-1], axis=1) > 0)
    np.testing.assert_allclose(np.abs(np.sum(out * q, axis=1)), 1.0, atol=1e-12)   # same rotations


def test_bad_csv_is_a_clear_error(tmp_path):
    with pytest.raises(bi.BlenderImportError, match="no such trajectory CSV"):
        bi.read_columns(tmp_path / "nope.csv")
    (tmp_path / "a.csv").write_text("t,x\n0,1\n")
    with pytest.raises(bi.BlenderImportError, match="'time' column"):
        bi.read_columns(tmp_path / "a.csv")
    (tmp_path / "b.csv").write_text("time,p_x,p_y,p_z\n")
    with pytest.raises(bi.BlenderImportError, match="no rows"):
        bi.read_columns(tmp_path / "b.csv")
    (tmp_path / "c.csv").write_text("time,p_x\n0,1\n")
    with pytest.raises(bi.BlenderImportError, match="no objects"):
        bi.scene_layout(bi.read_columns(tmp_path / "c.csv"))
    path, _, _ = _csv(tmp_path, "rope_net")
    with pytest.raises(bi.BlenderImportError, match="lines: ghost not in the CSV"):
        bi.scene_layout(bi.read_columns(path), lines=[["payload", "ghost"]])


def test_command_line_bad_input(tmp_path):
    path, _, _ = _csv(tmp_path, "rope_net")
    for args, message in (([str(tmp_path / "nope.csv")], "no such trajectory CSV"),
                          ([str(path), "--usd", "payload"], "expected NAME=VALUE"),
                          ([str(path), "--resolution", "big"], "--resolution"),
                          ([str(path), "--save", "scene.txt"], ".blend")):
        res = subprocess.run([sys.executable, str(SCRIPT), "--", *args], capture_output=True, text=True, cwd=tmp_path)
        assert res.returncode == 2 and message in res.stderr, res.stderr


# --- in Blender -----------------------------------------------------------------------------


def _bpy():
    return pytest.importorskip("bpy", reason=BPY_REASON)


def _rotation(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _world(obj):
    m = np.array(obj.matrix_world)
    return m[:3, 3], m[:3, :3]


def test_keyframes_follow_the_csv(tmp_path):
    bpy = _bpy()
    path, cols, config = _csv(tmp_path, "capture_env_falling")
    objects = bi.import_trajectory(path, fps=FPS)
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end, scene.render.fps) == (0, 15, FPS)
    layout = bi.scene_layout(cols)
    lines = objects["lines"]
    lines.modifiers["tubes"].show_viewport = False        # read the shape-keyed vertices, not the tubes
    names = list(dict.fromkeys(n for line in layout.lines for n in line))
    assert len(lines.data.vertices) == len(names)
    for frame in (0, 4, 9, 15):
        scene.frame_set(frame)
        row = 2 * frame                                    # t = frame / 25 s = row * 0.02 s
        for name in layout.bodies:
            pos, rot = _world(objects[name])
            np.testing.assert_allclose(pos, [cols[f"{name}_{a}"][row] for a in "xyz"], atol=2e-6)
            q = np.array([cols[f"{name}_q{a}"][row] for a in "wxyz"])
            np.testing.assert_allclose(rot, _rotation(q), atol=2e-6)
        mesh = lines.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
        verts = np.array([v.co[:] for v in mesh.vertices])
        expected = np.array([[cols[f"{n}_{a}"][row] for a in "xyz"] for n in names])
        np.testing.assert_allclose(verts, expected, atol=2e-6)
    # between two keyed rows Blender interpolates linearly (positions of rows 18 and 20)
    scene.frame_set(9, subframe=0.5)
    pos, _ = _world(objects["target"])
    np.testing.assert_allclose(pos, [0.5 * (cols[f"target_{a}"][18] + cols[f"target_{a}"][20]) for a in "xyz"],
                               atol=2e-6)


def test_cameras_renders_and_usd(tmp_path):
    bpy = _bpy()
    from PIL import Image

    # a USD model for the target, made with Blender itself
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add(size=0.2)
    usd = tmp_path / "cube.usda"
    bpy.ops.wm.usd_export(filepath=str(usd))

    # a ball 3 m ahead of the UAV's start (+x), 0.8 m to its left (+y) and 0.4 m below
    ball = {f"ball_{a}": np.full(31, v) for a, v in zip("xyz", (3.0, 0.8, 1.1))}
    path, cols, config = _csv(tmp_path, "uav_camera_flight", extra=ball)
    objects = bi.import_trajectory(path, fps=FPS, radius={"ball": 0.2})
    assert objects["ball"].type == "MESH"
    scene = bpy.context.scene
    scene.frame_set(10)
    for name in ("cam_fixed", "cam_gimbal"):
        view = bpy.data.objects[f"{name}_view"]
        assert view.data.lens == 50.0 and view.data.sensor_width == 36.0 and view.data.sensor_fit == "HORIZONTAL"
        _, cam = _world(view)
        q = np.array([cols[f"{name}_q{a}"][20] for a in "wxyz"])
        body = _rotation(q)
        np.testing.assert_allclose(-cam[:, 2], body[:, 0], atol=1e-6)      # looks along body +x
        np.testing.assert_allclose(cam[:, 0], -body[:, 1], atol=1e-6)      # image right = body -y
        np.testing.assert_allclose(-cam[:, 1], -body[:, 2], atol=1e-6)     # image down = body -z
    frames = bi.render_frames(tmp_path / "render", frames=[0, 15], resolution=(160, 90), samples=4)
    images = [np.asarray(Image.open(f).convert("RGB")).astype(int) for f in frames]
    for img in images:
        assert img.shape == (90, 160, 3)
        assert len(np.unique((img // 8).reshape(-1, 3), axis=0)) > 20, "the render is (nearly) one colour"
    assert np.any(np.abs(images[0] - images[1]).sum(axis=-1) > 30), "nothing moved between the frames"
    # through cam_fixed at t = 0 (camera frame = UAV frame = world axes): the (red) ball is
    # left of and below the image centre, the ground fills the lower half, the sky the upper
    view = bi.render_frames(tmp_path / "view", frames=[0], view="cam_fixed", resolution=(160, 90), samples=4)
    img = np.asarray(Image.open(view[0]).convert("RGB")).astype(int)
    red = np.argwhere((img[..., 0] > img[..., 1] + 50) & (img[..., 0] > img[..., 2] + 50))
    assert len(red) > 30, "the ball is not in the camera's view"
    row, col = red.mean(axis=0)
    assert col < 80 - 10 and row > 45 + 5
    top, bottom = img[:35].reshape(-1, 3).mean(axis=0), img[55:].reshape(-1, 3).mean(axis=0)
    assert np.abs(top - bottom).sum() > 15, "no horizon: sky and ground look alike"
    with pytest.raises(bi.BlenderImportError, match="camera bodies: cam_fixed, cam_gimbal"):
        bi.render_frames(tmp_path / "view", frames=[5], view="uav0")
    with pytest.raises(bi.BlenderImportError, match="outside the scene's frames 0 to 15"):
        bi.render_frames(tmp_path / "view", frames=[99])

    # the USD model replaces the target's sphere and follows the target's keyframes
    path, cols, _ = _csv(tmp_path, "capture_env_falling")
    objects = bi.import_trajectory(path, fps=FPS, usd={"target": usd})
    holder = objects["target"]
    assert holder.type == "EMPTY" and any(c.type == "MESH" for c in holder.children_recursive)
    bpy.context.scene.frame_set(12)
    pos, _ = _world(holder)
    np.testing.assert_allclose(pos, [cols[f"target_{a}"][24] for a in "xyz"], atol=2e-6)
    with pytest.raises(bi.BlenderImportError, match="--usd: no object named ghost"):
        bi.import_trajectory(path, usd={"ghost": usd})


def test_command_line_renders_and_saves(tmp_path):
    _bpy()
    path, _, _ = _csv(tmp_path, "rope_net")
    res = subprocess.run([sys.executable, str(SCRIPT), "--", str(path), "--render", str(tmp_path / "out"),
                          "--frames", "0,10", "--resolution", "160x90", "--samples", "2",
                          "--save", str(tmp_path / "scene.blend")], capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "rendered 2 frames" in res.stdout and "frames 0 to 15 at 25 fps" in res.stdout
    assert (tmp_path / "out" / "frame_0010.png").stat().st_size > 1000
    assert (tmp_path / "scene.blend").stat().st_size > 10_000
