"""The renderer (mysim_jax/perception/render.py): geometry against independent formulas,
occlusion, the net, the camera's own UAV, the horizon, bad input, determinism, and one real
simulated capture run end to end.

References are computed here independently of the renderer: the sphere's image extent from
points on its silhouette circle pushed through ``camera.project``, depths from ray-plane and
ray-sphere intersections in float64, the horizon row by hand from the camera's pitch.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import yaml

from mysim_jax.config.scene import config_from_dict, dump_config
from mysim_jax.core.npgeom import quat_to_matrix
from mysim_jax.perception.camera import Intrinsics, PerceptionError, intrinsics, project
from mysim_jax.perception.render import Renderer, load_run, look_at, write_images, write_video

from conftest import CONFIGS, sphere_extent

W, H = 640, 360
INTR = intrinsics(width=W, height=H)
# Measured (640 x 360, three views of the target): the box of whole target pixels is within
# 0.04-0.18 px of the silhouette's continuous extent (it differs by < 0.5 px by construction, so
# the bound is 1 px); target depths 4.7e-7 m off the float64 ray-sphere depth at ~6 m (float32);
# ground depth 6.6e-6 relative (float32 ray components near the horizon, 12 km away).
BOX_TOL = 1.0          # px
DEPTH_TOL = 5e-6       # m
GROUND_REL_TOL = 6e-5


def _quat(yaw=0.0, pitch=0.0):
    """Scalar-first quaternion of a yaw (about z) then a pitch (about the new y; + pitches +x down)."""
    qz = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    qy = np.array([np.cos(pitch / 2), 0.0, np.sin(pitch / 2), 0.0])
    w1, v1, w2, v2 = qz[0], qz[1:], qy[0], qy[1:]
    return np.r_[w1 * w2 - v1 @ v2, w1 * v2 + w2 * v1 + np.cross(v1, v2)]


def _scene_dict(knots=3, cameras=True) -> dict:
    raw = yaml.safe_load((CONFIGS / "capture_falling.yaml").read_text())
    raw["net"]["knots"] = knots
    raw["output"]["plot"] = ["target"]
    if cameras:
        raw["quadrotors"][0]["cameras"] = [{"name": "cam0", "mount": "fixed",
                                            "quat": _quat(np.pi / 4, np.radians(35)).round(6).tolist()}]
        raw["quadrotors"][1]["cameras"] = [{"name": "cam1", "mount": "fixed"}]
    return raw


CONFIG = config_from_dict(_scene_dict())


def _columns(config, bodies: dict, net_z=2.9, far=False):
    """Synthetic trajectory columns (one row): ``bodies`` name -> (pos, quat); bodies not given
    are parked 100 m under the ground (hidden by it); the net is flat at ``net_z`` (knots on the
    config's grid; under the ground too if ``far``), its edge and tether masses on straight lines
    (tethers to the UAV's centre less 1 cm)."""
    net = config.net
    g, size = net.knots, net.size
    cols = {"time": np.array([0.0])}
    everything = [q.body for q in config.quadrotors] + [c.name for q in config.quadrotors for c in q.cameras]
    everything.append(config.target.name)
    for k, name in enumerate(everything):
        pos, quat = bodies.get(name, ((3.0 * k, 0.0, -100.0), (1.0, 0.0, 0.0, 0.0)))
        for a, v in zip("xyz", pos):
            cols[f"{name}_{a}"] = np.array([float(v)])
        for a, v in zip("wxyz", quat):
            cols[f"{name}_q{a}"] = np.array([float(v)])

    def knot(i, j):
        return np.array([net.center[0] - size / 2 + j * size / (g - 1),
                         net.center[1] - size / 2 + i * size / (g - 1), -100.0 if far else net_z])

    def put(name, p):
        for a, v in zip("xyz", p):
            cols[f"{name}_{a}"] = np.array([float(v)])

    n = net.masses_per_edge
    for i in range(g):
        for j in range(g):
            put(f"net_k{i}_{j}", knot(i, j))
            for kind, (i2, j2) in (("h", (i, j + 1)), ("v", (i + 1, j))):
                if i2 < g and j2 < g:
                    for m in range(n):
                        f = (m + 1) / (n + 1)
                        put(f"net_{kind}{i}_{j}_{m}", (1 - f) * knot(i, j) + f * knot(i2, j2))
    for k, (uav, (i, j)) in enumerate(zip(net.tethers.uavs, net.tether_knots())):
        end = np.array([cols[f"{uav}_{a}"][0] for a in "xyz"]) + (0, 0, -0.01)
        for m in range(net.tethers.n_masses):
            f = (m + 1) / (net.tethers.n_masses + 1)
            put(f"net_t{k}_{m}", (1 - f) * knot(i, j) + f * end)
    return cols


def _cam_pose(eye, target):
    """Camera body pose (pos, scalar-first quat) whose optical axis (+x) looks from eye to target, level."""
    d = np.asarray(target, float) - eye
    yaw = np.arctan2(d[1], d[0])
    pitch = np.arctan2(-d[2], np.hypot(d[0], d[1]))
    return tuple(eye), tuple(_quat(yaw, pitch))


TARGET_AT = np.array([1.0, 0.5, 3.0])
EYE = np.array([-4.0, -2.0, 5.0])


@pytest.fixture(scope="module")
def renderer():
    return Renderer(CONFIG, INTR)


def test_target_box_and_depth_match_the_projected_sphere(renderer):
    r = CONFIG.target.radius
    cols = _columns(CONFIG, {"cam0": _cam_pose(EYE, TARGET_AT), "target": (TARGET_AT, (1, 0, 0, 0))}, far=True)
    frame = renderer.render(cols, "cam0", 0)
    tv = frame.target
    assert tv.visible_fraction == 1.0 and np.array_equal(tv.box, tv.full_box)
    extent = sphere_extent(INTR, frame.R, frame.p, TARGET_AT, r)
    assert np.abs(tv.box - extent).max() < BOX_TOL, (tv.box, extent)
    uv, z = project(INTR, frame.R, frame.p, TARGET_AT)
    np.testing.assert_allclose(tv.centre, uv, atol=1e-9)
    assert tv.box[0] < uv[0] < tv.box[2] and tv.box[1] < uv[1] < tv.box[3]
    # the optical axis passes through the target's centre (the camera looks at it) and through
    # the centre of pixel (W/2, H/2): its depth there is the distance minus the radius
    np.testing.assert_allclose(uv, (W / 2, H / 2), atol=1e-9)
    assert abs(frame.depth[H // 2, W // 2] - (np.linalg.norm(TARGET_AT - EYE) - r)) < DEPTH_TOL
    # every pixel of the id image marked target has its centre's ray hit the sphere (float64 check)
    vs, us = np.nonzero(frame.mask("target"))
    rays = np.stack([(us - INTR.cx) / INTR.fx, (vs - INTR.cy) / INTR.fy, np.ones_like(us, float)], -1) @ frame.R.T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    c = TARGET_AT - frame.p
    b = rays @ c
    disc = b ** 2 - (c @ c - r ** 2)
    assert (disc >= 0).all()
    # and its depth is the near intersection's, along the optical axis
    t_hit = (b - np.sqrt(disc)) * (rays @ frame.R[:, 2])
    assert np.abs(frame.depth[vs, us] - t_hit).max() < DEPTH_TOL
    # the pixels around the box are not target
    u0, v0, u1, v1 = (tv.box + [0.5, 0.5, -0.5, -0.5]).astype(int)
    ring = np.r_[frame.ids[v0 - 1, u0:u1 + 1], frame.ids[v1 + 1, u0:u1 + 1], frame.ids[v0:v1 + 1, u0 - 1],
                 frame.ids[v0:v1 + 1, u1 + 1]]
    assert not np.any(ring == frame.names.index("target"))


def test_ground_depth_is_the_ray_plane_intersection(renderer):
    cols = _columns(CONFIG, {"cam0": _cam_pose(np.array([3.0, -7.0, 2.5]), (13.0, 20.0, 0.0))}, far=True)
    frame = renderer.render(cols, "cam0", 0)
    ground = frame.ids == frame.names.index("ground")
    assert ground.mean() > 0.5 and (frame.ids == 0).any()         # ground and sky in view
    vs, us = np.nonzero(ground)
    d = np.stack([(us - INTR.cx) / INTR.fx, (vs - INTR.cy) / INTR.fy, np.ones_like(us, float)], -1) @ frame.R.T
    depth = -frame.p[2] / d[:, 2]                                    # rays with z_c = 1: parameter = depth
    assert np.abs(frame.depth[vs, us] / depth - 1).max() < GROUND_REL_TOL
    assert np.isinf(frame.depth[frame.ids == 0]).all()


@pytest.mark.parametrize("pitch_deg", [0.0, 5.0])
def test_horizon_row_from_the_pitch(renderer, pitch_deg):
    """A level camera pitched down by theta sees the horizon (rays parallel to the ground) at
    theta above its optical axis: row v_h = cy - fy tan(theta). Above it only sky, below only ground."""
    theta = np.radians(pitch_deg)
    cols = _columns(CONFIG, {"cam0": ((0.0, 0.0, 50.0), tuple(_quat(0.3, theta)))}, far=True)
    frame = renderer.render(cols, "cam0", 0)
    v_h = INTR.cy - INTR.fy * np.tan(theta)
    rows = np.arange(H)
    sky = frame.ids == 0
    assert sky[rows < v_h - 0.5].all() and not sky[rows > v_h + 0.5].any()
    assert np.isinf(frame.depth[rows < v_h - 0.5]).all()
    # the sky is blue above, and bluer towards the zenith
    top, low = frame.image[0].mean(axis=0), frame.image[int(v_h) - 2].mean(axis=0)
    assert top[2] > top[0] and top[2] - top[0] > low[2] - low[0]


def test_uav_in_front_hides_part_of_the_target(renderer):
    eye = EYE
    clear = renderer.render(_columns(CONFIG, {"cam0": _cam_pose(eye, TARGET_AT), "target": (TARGET_AT, (1, 0, 0, 0))},
                                     far=True), "cam0", 0)
    # uav2 1.5 m in front of the target on the line of sight to its top: it hides the top rows
    top = TARGET_AT + (0.0, 0.0, CONFIG.target.radius)
    blocker = top + (eye - top) / np.linalg.norm(eye - top) * 1.5
    frame = renderer.render(_columns(CONFIG, {"cam0": _cam_pose(eye, TARGET_AT), "target": (TARGET_AT, (1, 0, 0, 0)),
                                              "uav2": (blocker, (1, 0, 0, 0))}, far=True), "cam0", 0)
    tv = frame.target
    assert 0.05 < tv.visible_fraction < 0.95, tv.visible_fraction
    assert np.array_equal(tv.full_box, clear.target.box)
    area = lambda b: (b[2] - b[0]) * (b[3] - b[1])
    assert area(tv.box) < area(tv.full_box) and tv.box[1] > tv.full_box[1]
    assert tv.visible_px == frame.mask("target").sum() < clear.target.visible_px
    uv, _ = project(INTR, frame.R, frame.p, blocker)
    assert frame.ids[int(round(uv[1])), int(round(uv[0]))] == frame.names.index("uav2")
    assert frame.depth[int(round(uv[1])), int(round(uv[0]))] < clear.depth[int(round(uv[1])), int(round(uv[0]))]


def test_net_lines_are_drawn_at_least_a_pixel_wide(renderer):
    # looking down at the flat net from 6 m: its lines (1 mm) are far thinner than a pixel (~7 mm)
    cols = _columns(CONFIG, {"cam0": ((0.1, -0.2, 8.9), tuple(_quat(0.2, np.pi / 2 - 0.05)))})
    frame = renderer.render(cols, "cam0", 0)
    net = frame.mask("net")
    g = CONFIG.net.knots
    checked = 0
    for i in range(g):                                   # every edge between knots, column by column
        for j in range(g - 1):
            a = np.array([cols[f"net_k{i}_{j}_{x}"][0] for x in "xyz"])
            b = np.array([cols[f"net_k{i}_{j + 1}_{x}"][0] for x in "xyz"])
            (ua, va), (ub, vb) = project(INTR, frame.R, frame.p, np.stack([a, b]))[0]
            if abs(ub - ua) < abs(vb - va):              # walk the major axis
                ua, va, ub, vb = va, ua, vb, ub
                swap = True
            else:
                swap = False
            for u in range(int(np.ceil(min(ua, ub))) + 2, int(np.floor(max(ua, ub))) - 1):
                v = int(round(va + (vb - va) * (u - ua) / (ub - ua)))
                pix = (u, v) if swap else (v, u)
                if not (0 <= pix[0] < H and 0 <= pix[1] < W):
                    continue
                assert net[pix], (i, j, u, v)
                checked += 1
    assert checked > 500
    # drawn thin: the net covers little of the image, and sub-pixel lines are not drawn fat
    assert net.mean() < 0.05
    assert frame.mask("tether0").any()


def test_own_uav_is_not_drawn_unless_asked():
    # cam0 (on uav0) is placed 1.2 m behind uav0, looking at it; cam1 (on uav1) also sees it
    uav0 = np.array([0.0, 0.0, 3.0])
    bodies = {"uav0": (uav0, (1, 0, 0, 0)), "cam0": _cam_pose(uav0 + (-1.2, 0.3, 0.4), uav0),
              "uav1": ((1.5, 1.0, 3.4), (1, 0, 0, 0)), "cam1": _cam_pose(np.array([-3.0, -3.0, 4.0]), (-0.6, 0.15, 3.2))}
    cols = _columns(CONFIG, bodies, far=True)
    default = Renderer(CONFIG, INTR).render(cols, "cam0", 0)
    assert not default.mask("uav0").any()
    asked = Renderer(CONFIG, INTR, draw_own_uav=True).render(cols, "cam0", 0)
    assert asked.mask("uav0").sum() > 100
    other = Renderer(CONFIG, INTR).render(cols, "cam1", 0)
    assert other.mask("uav0").sum() > 100 and other.mask("cam0").sum() > 10
    assert not other.mask("cam1").any() and not other.mask("uav1").any()
    # hide: named bodies are never drawn, from a scene camera or a free one
    hidden = Renderer(CONFIG, INTR, hide=("uav0",)).render(cols, "cam1", 0)
    assert not hidden.mask("uav0").any() and hidden.mask("cam0").sum() > 10
    observer = look_at(np.array([-2.5, 1.0, 4.5]), uav0, cols["time"])
    assert Renderer(CONFIG, INTR).render(cols, observer, 0).mask("uav0").sum() > 100
    assert not Renderer(CONFIG, INTR, hide=("uav0",)).render(cols, observer, 0).mask("uav0").any()
    with pytest.raises(PerceptionError, match="hide: no body 'uav9'"):
        Renderer(CONFIG, INTR, hide=("uav9",))


def test_free_camera_and_drone_target():
    raw = _scene_dict()
    raw["target"]["behaviour"] = "maneuvering"
    config = config_from_dict(raw)
    cols = _columns(config, {"target": (TARGET_AT, (1, 0, 0, 0))}, far=True)
    observer = look_at(EYE, TARGET_AT, cols["time"])
    frame = Renderer(config, INTR).render(cols, observer, 0)
    tv = frame.target
    sphere = sphere_extent(INTR, frame.R, frame.p, TARGET_AT, config.target.radius)
    # the drone fits inside the target's sphere: its box does too, and is not much smaller
    assert tv.visible_px > 100
    assert (tv.box[:2] >= sphere[:2] - BOX_TOL).all() and (tv.box[2:] <= sphere[2:] + BOX_TOL).all()
    assert (tv.box[2] - tv.box[0]) > 0.6 * (sphere[2] - sphere[0])


def test_bad_input_is_named(renderer):
    cols = _columns(CONFIG, {"cam0": _cam_pose(EYE, TARGET_AT)})
    with pytest.raises(PerceptionError, match=r"lacks 2 column\(s\).*target_qw, net_k1_1_z.*config it was"):
        renderer.render({k: v for k, v in cols.items() if k not in ("net_k1_1_z", "target_qw")}, "cam0", 0)
    with pytest.raises(PerceptionError, match="image width must be a positive"):
        intrinsics(width=0, height=360)
    with pytest.raises(PerceptionError, match="image height must be a positive"):
        Renderer(CONFIG, Intrinsics(width=640, height=-2, fx=889.0, fy=889.0, cx=320.0, cy=-1.0))
    with pytest.raises(PerceptionError, match="camera 'cam9' is not in the run; its cameras: cam0, cam1"):
        renderer.render(cols, "cam9", 0)
    with pytest.raises(PerceptionError, match="row 1 is out of range: the run has 1 output rows, 0 to 0"):
        renderer.render(cols, "cam0", 1)
    with pytest.raises(PerceptionError, match="row -1 is out of range"):
        list(renderer.render_many(cols, "cam0", [0, -1]))
    up = _columns(CONFIG, {"cam0": ((0.0, 0.0, 3.0), tuple(_quat(0.0, -np.radians(30))))})
    with pytest.raises(PerceptionError, match="camera 'cam0' sees nothing of the ground.*Pitch the camera down"):
        renderer.render(up, "cam0", 0)
    with pytest.raises(PerceptionError, match="does not exist; write one with scripts/simulate.py"):
        load_run("/nonexistent/run")


def test_rendering_is_deterministic(renderer):
    cols = _columns(CONFIG, {"cam0": _cam_pose(EYE, TARGET_AT), "target": (TARGET_AT, (1, 0, 0, 0)),
                             "uav1": ((0.5, 0.0, 3.6), (0.9, 0.1, 0.2, 0.3))})
    a = renderer.render(cols, "cam0", 0)
    b = Renderer(CONFIG, INTR).render(cols, "cam0", 0)
    for key in ("image", "depth", "ids"):
        assert np.array_equal(getattr(a, key), getattr(b, key))


# --- a real run -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def capture_run(tmp_path_factory):
    """configs/capture_falling.yaml (a 3 x 3 net, cameras on uav0 and uav1) simulated for 0.04 s,
    written as scripts/simulate.py writes a run folder."""
    from mysim_jax.build import build
    from mysim_jax.io.trajectory import trajectory_columns, write_trajectory_csv
    from mysim_jax.driver import simulate
    from mysim_jax.tasks.scripted import team_policy

    raw = _scene_dict()
    raw["sim"]["t_end"] = 0.04
    config = config_from_dict(raw)
    scene, params, state = build(config)
    traj = simulate(scene, params, state, config.run_settings(), progress=False, policy=team_policy(config, scene))
    assert traj.ok
    folder = tmp_path_factory.mktemp("capture")
    (folder / "config.yaml").write_text(dump_config(config))
    write_trajectory_csv(folder / "trajectory.csv", trajectory_columns(scene, traj))
    return folder


def test_real_run_renders_to_video_and_images(capture_run, tmp_path):
    run = load_run(capture_run)
    renderer = Renderer(run.config, INTR)
    assert set(renderer.required_columns()) <= set(run.columns)
    assert renderer.cameras == ("cam0", "cam1")
    frames = list(renderer.render_many(run.columns, "cam0", progress=False))
    assert len(frames) == len(run.columns["time"]) == 3
    last = frames[-1]
    # cam0 (on uav0, yawed to the net's centre, pitched 35 deg down) sees the net over the ground
    assert last.mask("net").sum() > 500 and last.mask("ground").mean() > 0.5
    assert not last.mask("uav0").any()
    # a net knot seen by the camera projects onto net pixels
    knot = np.array([run.columns[f"net_k1_1_{a}"][-1] for a in "xyz"])
    uv, z = project(INTR, last.R, last.p, knot)
    assert z > 0 and last.mask("net")[int(round(uv[1])), int(round(uv[0]))]
    assert write_video(frames, tmp_path / "cam0.mp4", fps=run.fps) == 3
    cap = cv2.VideoCapture(str(tmp_path / "cam0.mp4"))
    ok, image = cap.read()
    assert ok and image.shape == (H, W, 3)
    assert write_images(frames, tmp_path / "images") == 3
    assert (tmp_path / "images" / "frame_00002.png").is_file()
    rows = (tmp_path / "images" / "targets.csv").read_text().splitlines()
    assert rows[0].startswith("row,t,u_min") and len(rows) == 4
    # a trajectory without the net's columns is refused, naming them
    cols = {k: v for k, v in run.columns.items() if not re.match(r"net_v0_0_0_[xyz]$", k)}
    with pytest.raises(PerceptionError, match="lacks 3 column.*net_v0_0_0_x, net_v0_0_0_y, net_v0_0_0_z"):
        renderer.render(cols, "cam0", 0)


def test_ground_view_albedo_is_the_texture_at_the_seen_points():
    """view_ground samples the texture at each pixel's ground point relative to the camera's
    nadir; GroundTexture.albedo at the world points, with the footprint written out here
    (range / f, stretched by sqrt(|d| / -d_z)), must give the same albedo."""
    from mysim_jax.perception.ground import GroundTexture, view_ground

    texture = GroundTexture(seed=3)
    R = quat_to_matrix(_quat(0.7, np.radians(25))) @ np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    p = np.array([1234.5, -987.6, 3.2])                  # far from the world origin
    view = view_ground(INTR, R, p, texture)
    vs, us = np.nonzero(view.hit)
    d = np.stack([(us - INTR.cx) / INTR.fx, (vs - INTR.cy) / INTR.fy, np.ones(len(us))], -1) @ R.T
    norm = np.linalg.norm(d, axis=1)
    depth = -p[2] / d[:, 2]
    points = p + depth[:, None] * d
    footprint = depth * norm / INTR.fx * np.sqrt(norm / -d[:, 2])
    # measured: points 6e-5 m off within 1 km (float32 offsets from the nadir), albedo 2.9e-5
    # (bilinear lookups at 1/32 texel of coordinates rounded differently)
    near = depth < 1000
    assert np.abs(view.points[vs, us] - points)[near].max() < 6e-4
    assert np.abs(view.albedo[vs, us] - texture.albedo(points[:, 0], points[:, 1], footprint)).max() < 3e-4
