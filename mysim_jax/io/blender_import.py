"""Import a trajectory CSV into Blender and animate it (paper Alg. blender_rendering).

Inside Blender (no install needed besides Blender itself)::

    blender --background --python mysim_jax/io/blender_import.py -- out/run/trajectory.csv \\
        [--fps 25] [--usd uav0=drone.usd ...] [--kind NAME=quadrotor|camera|sphere|box ...] \\
        [--render OUT_DIR [--frames 0,10,20] [--view cam_fixed] [--resolution 1920x1080]] \\
        [--save scene.blend]

or from Python, with Blender as a module (``pip install -e '.[blender]'``, Python 3.11)::

    from mysim_jax.io.blender_import import import_trajectory, render_frames
    objects = import_trajectory("out/run/trajectory.csv", fps=25)
    render_frames("out/run/render", frames=[0, 25, 50])

This file imports neither mysim_jax nor anything outside Python's standard library,
NumPy (which Blender bundles), its sibling file :mod:`mysim_jax.io.blender_layout` and, where
Blender is needed, ``bpy``. The sibling holds what works without Blender: reading the CSV and
telling its objects and lines apart (:func:`read_columns`, :func:`scene_layout`,
:func:`keyed_rows`, importable from here too); this file builds, animates and renders the
Blender scene, and is the command line.

What it does, as the paper's algorithm: read the CSV (:mod:`mysim_jax.io.trajectory`
writes it; only ``time``, ``NAME_x/y/z`` and, for rigid bodies, ``NAME_qw/qx/qy/qz``
are read); make one object per rigid body and free point mass (a USD file per object
if given, else a simple mesh); keyframe every object's location and rotation per row at
the scene's frame rate; set the frame range. On top of that:

* **Object shapes** (``kind``, default from the name): ``uav*`` a quadrotor (a plate,
  an X of arms, four rotor discs and a red nose on body +x), ``cam*`` a small camera
  (with a Blender camera, below), anything else a sphere (``radius``, default 0.15 m
  for bodies, 0.03 m for free points) or a ``box``.
* **Lines**: the net, tethers and ropes are one mesh whose vertices follow the point
  masses (one shape key per keyed row, each weighted 1 at its row's frame and 0 at its
  neighbours', so the mesh moves through the rows with linear interpolation), drawn as
  tubes of ``line_radius`` by a geometry-nodes modifier. Which masses are joined is read
  from the names mysim_jax gives them (:mod:`mysim_jax.io.blender_layout` says
  how); ``lines`` (lists of names) replaces this guess.
* **Cameras**: every ``camera`` body carries a Blender camera with the paper's
  intrinsics (focal length 50 mm, sensor 36 mm wide, 1920 x 1080 pixels) looking along
  the body's +x axis, with image right = body −y and image down = body −z; ``--view
  NAME`` renders through it.
* An overview camera that sees the whole run, a sun, a sky colour, and the ground plane
  z = 0 when nothing in the run goes below it.

Frames: frame ``F`` shows time ``t0 + F / fps``. One row per frame is keyed (the row
nearest to the frame's time, at its exact time: ``frame = (t - t0) fps``); rows sparser
than the frame rate are all keyed, and Blender interpolates linearly between them.
Quaternions in the CSV are scalar-first, body → world: Blender's ``rotation_quaternion``
order. Their signs are made continuous from row to row (q and −q are the same rotation,
but interpolating between them is not).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

if __name__ == "__main__":   # run as a file (blender --python FILE): import the sibling file, not the package
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from blender_layout import (BlenderImportError, Layout, continuous_quaternions, default_kind, keyed_rows,
                                point_positions, read_columns, scene_layout)
else:
    from .blender_layout import (BlenderImportError, Layout, continuous_quaternions, default_kind, keyed_rows,
                                 point_positions, read_columns, scene_layout)

__all__ = ["import_trajectory", "render_frames", "main", "KINDS", "BlenderImportError", "Layout", "read_columns",
           "scene_layout", "keyed_rows", "continuous_quaternions", "default_kind"]

KINDS = ("quadrotor", "camera", "sphere", "box")
BODY_RADIUS = 0.15          # m, default sphere of a rigid body
POINT_RADIUS = 0.03         # m, default sphere of a free point mass
LINE_RADIUS = 0.01          # m, tube radius of drawn lines
ARM_LENGTH = 0.096          # m, the paper's quadrotor (Table UAV_model)
CAMERA_LENS = 50.0          # mm (paper Table camera)
CAMERA_SENSOR = (36.0, 24.0)  # mm
CAMERA_RESOLUTION = (1920, 1080)
GROUND_COLORS = ((0.55, 0.65, 0.5), (0.42, 0.5, 0.38))
GROUND_SIZE = 200.0         # m, side of the ground plane (at least): scene cameras see it to the horizon
CAMERA_CLIP_START = 0.05    # m: a scene camera sees nothing nearer, so not the inside of its own body
# Blender camera axes (x right, y up, looking along -z) in the camera body's frame, whose
# +x is the optical axis, image right = body -y, image down = body -z.
CAMERA_AXES = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # columns: Blender x, y, z
COLORS = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16), (0.58, 0.4, 0.74),
          (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.09, 0.75, 0.81))


def _parse_pairs(values, what, convert=str) -> dict:
    out = {}
    for item in values or ():
        if "=" not in item:
            raise BlenderImportError(f"--{what} {item}: expected NAME=VALUE")
        name, value = item.split("=", 1)
        try:
            out[name.strip()] = convert(value.strip())
        except ValueError:
            raise BlenderImportError(f"--{what} {item}: '{value}' is not a valid value") from None
    return out


# --- Blender ---------------------------------------------------------------------------------


def _bpy():
    try:
        import bpy                 # an optional extra: pip install -e '.[blender]'
    except ImportError:
        raise ImportError("bpy (Blender as a Python module) is not installed: pip install -e '.[blender]' on "
                          "Python 3.11, or run this file inside Blender: blender --background --python "
                          "mysim_jax/io/blender_import.py -- trajectory.csv") from None
    return bpy


def _material(name, color, emission=0.0):
    bpy = _bpy()
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = (*color, 1.0)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    if bsdf is not None:
        bsdf.inputs["Base Color"].default_value = (*color, 1.0)
        bsdf.inputs["Roughness"].default_value = 0.6
    return mat


def _checker_material(name, size):
    """Two-tone 1 m squares on a plane of side ``size`` (a ground a camera can see move)."""
    mat = _material(name, GROUND_COLORS[0])
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes.get("Principled BSDF")
    if bsdf is not None:
        checker, coords = nodes.new("ShaderNodeTexChecker"), nodes.new("ShaderNodeTexCoord")
        checker.inputs["Scale"].default_value = size
        checker.inputs["Color1"].default_value = (*GROUND_COLORS[0], 1.0)
        checker.inputs["Color2"].default_value = (*GROUND_COLORS[1], 1.0)
        links.new(coords.outputs["Generated"], checker.inputs["Vector"])
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _mesh_object(name, build, materials, collection):
    """An object ``name`` with a mesh made by ``build(bm)`` (bmesh)."""
    import bmesh              # ships with bpy, an optional extra (pip install -e '.[blender]')

    bpy = _bpy()
    bm = bmesh.new()
    build(bm)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    for mat in materials:
        mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def _box(bm, size, center=(0, 0, 0), angle=0.0, material=0):
    import bmesh              # ships with bpy, an optional extra (pip install -e '.[blender]')
    from mathutils import Matrix  # ships with bpy, an optional extra

    matrix = Matrix.Translation(center) @ Matrix.Rotation(angle, 4, "Z") @ Matrix.Diagonal((*size, 1.0))
    geom = bmesh.ops.create_cube(bm, size=1.0, matrix=matrix)
    for face in {f for v in geom["verts"] for f in v.link_faces}:
        face.material_index = material


def _shape(kind, radius):
    """A bmesh builder for ``kind`` (sizes in metres; a quadrotor's nose has material 1)."""
    import bmesh              # ships with bpy, an optional extra (pip install -e '.[blender]')
    from mathutils import Matrix  # ships with bpy, an optional extra

    if kind == "quadrotor":
        def build(bm):
            _box(bm, (0.07, 0.07, 0.025))
            for angle in (math.pi / 4, 3 * math.pi / 4):
                _box(bm, (2 * ARM_LENGTH, 0.012, 0.008), angle=angle)
            for k in range(4):
                a = math.pi / 4 + k * math.pi / 2
                bmesh.ops.create_cone(bm, cap_ends=True, segments=16, radius1=0.05, radius2=0.05, depth=0.004,
                                      matrix=Matrix.Translation((ARM_LENGTH * math.cos(a), ARM_LENGTH * math.sin(a),
                                                                 0.012)))
            _box(bm, (0.03, 0.02, 0.02), center=(0.05, 0.0, 0.01), material=1)
        return build
    if kind == "camera":
        def build(bm):
            _box(bm, (0.025, 0.03, 0.025))
            bmesh.ops.create_cone(bm, cap_ends=True, segments=12, radius1=0.01, radius2=0.008, depth=0.015,
                                  matrix=Matrix.Translation((0.02, 0, 0)) @ Matrix.Rotation(math.pi / 2, 4, "Y"))
        return build
    if kind == "box":
        return lambda bm: _box(bm, (2 * radius,) * 3)
    return lambda bm: bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=12, radius=radius)


def _fcurves(id_data):
    """The F-curves of ``id_data``'s action (the legacy list, or the slot's channel bag in
    Blender versions with layered actions only)."""
    anim = id_data.animation_data
    try:
        return anim.action.fcurves
    except AttributeError:
        from bpy_extras import anim_utils  # ships with bpy, an optional extra

        return anim_utils.action_get_channelbag_for_slot(anim.action, anim.action_slot).fcurves


def _key(id_data, data_path, frames, values):
    """Keyframe ``data_path`` of ``id_data`` with ``values`` ``(n, k)`` at ``frames`` ``(n,)``,
    linear interpolation."""
    values = np.asarray(values, float).reshape(len(frames), -1)
    for i in range(values.shape[1]):
        id_data.keyframe_insert(data_path, index=i if values.shape[1] > 1 else -1, frame=float(frames[0]))
    curves = {(fc.data_path, fc.array_index): fc for fc in _fcurves(id_data)}
    for i in range(values.shape[1]):
        fc = curves[(data_path, i)]
        points = fc.keyframe_points
        points.clear()
        points.add(len(frames))
        co = np.empty(2 * len(frames))
        co[0::2], co[1::2] = frames, values[:, i]
        points.foreach_set("co", co.tolist())
        for p in points:
            p.interpolation = "LINEAR"
        fc.update()


def _lines_node_group(radius, material):
    """Geometry nodes: the mesh's edges as tubes of ``radius`` with ``material``."""
    bpy = _bpy()
    group = bpy.data.node_groups.new("mysim_lines", "GeometryNodeTree")
    if hasattr(group, "interface"):
        group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    else:
        group.inputs.new("NodeSocketGeometry", "Geometry")
        group.outputs.new("NodeSocketGeometry", "Geometry")
    nodes, links = group.nodes, group.links
    given, out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    to_curve, to_mesh = nodes.new("GeometryNodeMeshToCurve"), nodes.new("GeometryNodeCurveToMesh")
    circle, paint = nodes.new("GeometryNodeCurvePrimitiveCircle"), nodes.new("GeometryNodeSetMaterial")
    circle.inputs["Radius"].default_value = radius
    circle.inputs["Resolution"].default_value = 8
    paint.inputs["Material"].default_value = material
    links.new(given.outputs[0], to_curve.inputs["Mesh"])
    links.new(to_curve.outputs["Curve"], to_mesh.inputs["Curve"])
    links.new(circle.outputs["Curve"], to_mesh.inputs["Profile Curve"])
    links.new(to_mesh.outputs["Mesh"], paint.inputs["Geometry"])
    links.new(paint.outputs["Geometry"], out.inputs[0])
    return group


def _lines_object(columns, layout, rows, frames, radius, collection):
    """One mesh for every line; its vertices follow the named points and bodies through
    one shape key per keyed row."""
    bpy = _bpy()
    names = list(dict.fromkeys(n for line in layout.lines for n in line))
    index = {n: k for k, n in enumerate(names)}
    edges = {tuple(sorted((index[a], index[b]))) for line in layout.lines for a, b in zip(line[:-1], line[1:])}
    xyz = np.stack([point_positions(columns, n, rows) for n in names], axis=1)       # (n_rows, n_verts, 3)
    xyz = np.where(np.isfinite(xyz), xyz, 0.0)
    mesh = bpy.data.meshes.new("lines")
    mesh.from_pydata(xyz[0].tolist(), sorted(edges), [])
    obj = bpy.data.objects.new("lines", mesh)
    collection.objects.link(obj)
    basis = obj.shape_key_add(name="Basis", from_mix=False)
    basis.data.foreach_set("co", xyz[0].ravel().tolist())
    key = mesh.shape_keys
    for k in range(1, len(rows)):
        block = obj.shape_key_add(name=f"row{rows[k]}", from_mix=False)
        block.data.foreach_set("co", xyz[k].ravel().tolist())
        around = [frames[j] for j in (k - 1, k, k + 1) if j < len(rows)]
        weights = [0.0, 1.0, 0.0][: len(around)]
        _key(key, f'key_blocks["{block.name}"].value', np.asarray(around), np.asarray(weights))
    mat = _material("lines", (0.35, 0.3, 0.25))
    mesh.materials.append(mat)
    obj.modifiers.new("tubes", "NODES").node_group = _lines_node_group(radius, mat)
    return obj


def _import_usd(name, path, collection):
    """Import ``path`` under an empty named ``name`` (the object that is keyframed)."""
    bpy = _bpy()
    path = Path(path)
    if not path.is_file():
        raise BlenderImportError(f"--usd {name}={path}: no such file")
    before = set(bpy.data.objects)
    result = bpy.ops.wm.usd_import(filepath=str(path.resolve()))
    new = [o for o in bpy.data.objects if o not in before]
    if "FINISHED" not in result or not new:
        raise BlenderImportError(f"--usd {name}={path}: Blender imported no object from it")
    holder = bpy.data.objects.new(name, None)
    collection.objects.link(holder)
    for obj in new:
        if obj.parent is None:
            obj.parent = holder
    return holder


def _scene_camera(name, body, collection):
    """A Blender camera with the paper's intrinsics, child of ``body``: it looks along the
    body's +x axis, image right = body −y, image down = body −z."""
    from mathutils import Matrix  # ships with bpy, an optional extra

    bpy = _bpy()
    data = bpy.data.cameras.new(f"{name}_view")
    data.lens = CAMERA_LENS
    data.sensor_width, data.sensor_height = CAMERA_SENSOR
    data.sensor_fit = "HORIZONTAL"
    data.clip_start = CAMERA_CLIP_START
    data.clip_end = 1000.0
    cam = bpy.data.objects.new(f"{name}_view", data)
    collection.objects.link(cam)
    cam.parent = body
    cam.rotation_mode = "QUATERNION"
    cam.rotation_quaternion = Matrix(CAMERA_AXES.tolist()).to_quaternion()
    return cam


def _overview(positions, collection, ground):
    """An overview camera looking at everything, a sun and a sky colour; the ground plane."""
    bpy = _bpy()
    pts = positions[np.all(np.isfinite(positions), axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 0.5)
    aim = bpy.data.objects.new("overview_target", None)
    aim.location = center.tolist()
    collection.objects.link(aim)
    data = bpy.data.cameras.new("overview")
    data.lens, data.sensor_width, data.sensor_fit = 35.0, 36.0, "HORIZONTAL"
    data.clip_end = 10_000.0
    cam = bpy.data.objects.new("overview", data)
    collection.objects.link(cam)
    vertical_half_fov = math.atan(0.5 * 36.0 * 9 / 16 / 35.0)
    direction = np.array([1.0, -1.3, 0.8]) / np.linalg.norm([1.0, -1.3, 0.8])
    cam.location = (center + direction * 0.9 * radius / math.sin(vertical_half_fov)).tolist()
    track = cam.constraints.new("TRACK_TO")
    track.target, track.track_axis, track.up_axis = aim, "TRACK_NEGATIVE_Z", "UP_Y"
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), math.radians(10), math.radians(30))
    collection.objects.link(sun)
    scene = bpy.context.scene
    if scene.world is None:
        scene.world = bpy.data.worlds.new("sky")
    scene.world.color = (0.75, 0.8, 0.85)
    scene.world.use_nodes = True
    background = scene.world.node_tree.nodes.get("Background")
    if background is not None:
        background.inputs["Color"].default_value = (0.75, 0.8, 0.85, 1.0)
        background.inputs["Strength"].default_value = 0.6
    if ground:
        size = max(GROUND_SIZE, 4.0 * float(np.max(hi[:2] - lo[:2])))
        bpy.ops.mesh.primitive_plane_add(size=1.0)
        plane = bpy.context.active_object
        plane.name = "ground"
        plane.scale = (size, size, 1.0)
        plane.location = (float(center[0]), float(center[1]), 0.0)
        plane.data.materials.append(_checker_material("ground", size))
        for c in plane.users_collection:
            c.objects.unlink(plane)
        collection.objects.link(plane)
    scene.camera = cam
    return cam


def import_trajectory(csv_path, fps: int = 25, usd=None, kinds=None, radius=None, lines=None,
                      line_radius: float = LINE_RADIUS, clear: bool = True, ground: bool | None = None) -> dict:
    """Build and animate the scene of a trajectory CSV in the current Blender session (see
    the module docstring); returns ``{name: object}`` for every keyframed body and point,
    and ``"lines"`` / ``"overview"`` for the line mesh and the overview camera.

    ``usd``, ``kinds``, ``radius``: ``{name: value}`` per object (a USD file, a shape in
    :data:`KINDS`, a sphere radius in m); ``lines``: polylines of names, replacing the guess
    from the names; ``clear``: start from an empty scene; ``ground``: draw the plane z = 0
    (default: when nothing goes below it)."""
    bpy = _bpy()
    columns = read_columns(csv_path)
    time = columns["time"]
    rows, frames = keyed_rows(time, fps)
    layout = scene_layout(columns, lines)
    usd, kinds, radius = dict(usd or {}), dict(kinds or {}), dict(radius or {})
    created = set(layout.bodies) | set(layout.points)
    for what, given in (("usd", usd), ("kind", kinds), ("radius", radius)):
        unknown = sorted(set(given) - created)
        if unknown:
            raise BlenderImportError(f"--{what}: no object named {', '.join(unknown)} in {csv_path} "
                                     f"(objects: {', '.join(sorted(created))})")
    bad = {n: k for n, k in kinds.items() if k not in KINDS}
    if bad:
        raise BlenderImportError(f"--kind: {bad} (kinds: {', '.join(KINDS)})")
    if any(not (r > 0 and math.isfinite(r)) for r in radius.values()) or not line_radius > 0:
        raise BlenderImportError("--radius and --line-radius must be positive (metres)")

    if clear:
        bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    collection = bpy.data.collections.new(Path(csv_path).stem)
    scene.collection.children.link(collection)
    scene.render.fps, scene.render.fps_base = int(fps), 1.0
    scene.frame_start, scene.frame_end = 0, int(math.ceil(frames[-1] - 1e-9))

    objects = {}
    nose = _material("nose", (0.9, 0.1, 0.1))
    for k, name in enumerate(layout.bodies + layout.points):
        body = name in layout.bodies
        kind = kinds.get(name, default_kind(name, body))
        color = (0.1, 0.1, 0.1) if kind == "sphere" and body else COLORS[k % len(COLORS)]
        if name in usd:
            obj = _import_usd(name, usd[name], collection)
        else:
            r = radius.get(name, BODY_RADIUS if body else POINT_RADIUS)
            obj = _mesh_object(name, _shape(kind, r), [_material(name, color), nose], collection)
        pos = point_positions(columns, name, rows)
        _key(obj, "location", frames, np.where(np.isfinite(pos), pos, 0.0))
        if body:
            obj.rotation_mode = "QUATERNION"
            q = np.stack([columns[f"{name}_q{a}"][rows] for a in "wxyz"], axis=-1)
            q = np.where(np.all(np.isfinite(q), axis=-1, keepdims=True), q, [1.0, 0.0, 0.0, 0.0])
            _key(obj, "rotation_quaternion", frames, continuous_quaternions(q))
            if kind == "camera":
                _scene_camera(name, obj, collection)
        objects[name] = obj
    if layout.lines:
        objects["lines"] = _lines_object(columns, layout, rows, frames, line_radius, collection)
    drawn = created | {n for line in layout.lines for n in line}
    everything = np.concatenate([point_positions(columns, n, rows) for n in drawn], axis=0)
    if ground is None:
        ground = bool(np.nanmin(everything[:, 2]) >= -1e-3)
    objects["overview"] = _overview(everything, collection, ground)
    scene.frame_set(0)
    return objects


def render_frames(out_dir, frames=None, view: str | None = None, resolution=CAMERA_RESOLUTION, samples: int = 16,
                  engine: str = "CYCLES") -> list[Path]:
    """Render ``frames`` (default: every frame of the scene) of the current scene to
    ``out_dir/frame_NNNN.png`` through the overview camera, or through the Blender camera
    of camera body ``view``. Cycles renders on the CPU (works headless)."""
    bpy = _bpy()
    scene = bpy.context.scene
    if view is None:
        scene.camera = bpy.data.objects.get("overview", scene.camera)
    else:
        cam = bpy.data.objects.get(f"{view}_view")
        if cam is None:
            names = sorted(o.name[:-5] for o in bpy.data.objects if o.type == "CAMERA" and o.name.endswith("_view"))
            raise BlenderImportError(f"--view {view}: no camera body of that name (camera bodies: "
                                     f"{', '.join(names) or 'none'}; --kind NAME=camera makes one)")
        scene.camera = cam
    if frames is None:
        frames = range(scene.frame_start, scene.frame_end + 1)
    frames = [int(f) for f in frames]
    outside = [f for f in frames if not scene.frame_start <= f <= scene.frame_end]
    if outside:
        raise BlenderImportError(f"--frames {outside}: outside the scene's frames {scene.frame_start} to "
                                 f"{scene.frame_end}")
    scene.render.engine = engine
    if engine == "CYCLES":
        scene.cycles.device = "CPU"
        scene.cycles.samples = int(samples)
        scene.cycles.use_denoising = False
    scene.render.resolution_x, scene.render.resolution_y = (int(v) for v in resolution)
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for f in frames:
        scene.frame_set(f)
        scene.render.filepath = str(out_dir / f"frame_{f:04d}.png")
        bpy.ops.render.render(write_still=True)
        written.append(Path(scene.render.filepath))
    return written


# --- command line ------------------------------------------------------------------------------


def _parser():
    p = argparse.ArgumentParser(
        prog="blender --background --python mysim_jax/io/blender_import.py --",
        description="Import a mysim_jax trajectory CSV into Blender, animate it, and optionally render "
                    "frames and save the .blend file.")
    p.add_argument("csv", help="trajectory.csv (scripts/simulate.py writes it)")
    p.add_argument("--fps", type=int, default=25, help="scene frame rate (default 25)")
    p.add_argument("--usd", action="append", metavar="NAME=FILE", help="a USD file for object NAME (repeatable)")
    p.add_argument("--kind", action="append", metavar="NAME=KIND",
                   help=f"shape of object NAME: {', '.join(KINDS)} (default from the name: uav* quadrotor, "
                        "cam* camera, else sphere)")
    p.add_argument("--radius", action="append", metavar="NAME=R", help="sphere radius of object NAME, m")
    p.add_argument("--line-radius", type=float, default=LINE_RADIUS, help="tube radius of net, tether and "
                   f"rope lines, m (default {LINE_RADIUS})")
    p.add_argument("--render", metavar="OUT_DIR", help="render frames into OUT_DIR/frame_NNNN.png")
    p.add_argument("--frames", help="frames to render, e.g. 0,10,20 (default: all)")
    p.add_argument("--view", metavar="NAME", help="render through camera body NAME (default: the overview)")
    p.add_argument("--resolution", default="1920x1080", help="WIDTHxHEIGHT (default 1920x1080)")
    p.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    p.add_argument("--engine", default="CYCLES", help="render engine (default CYCLES, on the CPU)")
    p.add_argument("--save", metavar="FILE.blend", help="save the scene")
    return p


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    args = _parser().parse_args(argv)
    try:
        usd = _parse_pairs(args.usd, "usd")
        kinds = _parse_pairs(args.kind, "kind")
        radius = _parse_pairs(args.radius, "radius", float)
        try:
            resolution = tuple(int(v) for v in args.resolution.lower().split("x"))
            frames = None if args.frames is None else [int(f) for f in args.frames.split(",") if f.strip()]
        except ValueError:
            raise BlenderImportError("--resolution WIDTHxHEIGHT and --frames 0,10,20 take whole numbers") from None
        if len(resolution) != 2 or min(resolution) < 1:
            raise BlenderImportError(f"--resolution {args.resolution}: expected WIDTHxHEIGHT, e.g. 1920x1080")
        if args.save and not args.save.endswith(".blend"):
            raise BlenderImportError(f"--save {args.save}: the file name must end in .blend")
        read_columns(args.csv)                  # a bad CSV is reported before Blender loads
        bpy = _bpy()
        objects = import_trajectory(args.csv, fps=args.fps, usd=usd, kinds=kinds, radius=radius,
                                    line_radius=args.line_radius)
        scene = bpy.context.scene
        print(f"imported {len(objects) - 1 - ('lines' in objects)} objects from {args.csv}"
              + (", and the lines as one mesh" if "lines" in objects else "")
              + f"; frames {scene.frame_start} to {scene.frame_end} at {args.fps} fps")
        if args.render:
            written = render_frames(args.render, frames, view=args.view, resolution=resolution,
                                    samples=args.samples, engine=args.engine)
            print(f"rendered {len(written)} frames into {args.render}/")
        if args.save:
            bpy.ops.wm.save_as_mainfile(filepath=str(Path(args.save).resolve()))
            print(f"saved {args.save}")
    except (BlenderImportError, ImportError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
