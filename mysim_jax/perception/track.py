"""Gimbal target tracking (paper Alg. target_tracking_process), closed loop in the simulator.

Every UAV carries a gimbal camera (:mod:`mysim_jax.dynamics.gimbal`: a universal joint with
PD servos towards commanded angles, :mod:`mysim_jax.effects.gimbal_servo`). Each camera frame, for every gimbal camera:

1. render the camera's image at the current state (:mod:`mysim_jax.perception.render`);
2. detect the target (any callable ``Frame -> list[Detection]``, best first: the learned
   detector through :func:`image_detector`, or the :class:`OracleDetector` stand-in built
   from the renderer's ground-truth box);
3. turn the pixel error of the box centre from the image centre into gimbal commands
   (:class:`GimbalTracker`), with recovery when the target is lost;
4. set the commanded angles (``angle`` of the servo's params, ``GIMBAL_SERVO.params``, traced) and
   advance the simulation by one frame period.

So the camera's motion comes from the gimbal's own joint dynamics (servo bandwidth, the
UAV's attitude, the tether loads on the UAV) and the images see the camera where the
simulated joint has put it. The simulation runs as jitted ``lax.scan`` chunks of one frame
period; the commands are a parameter, so nothing recompiles between frames.

The pieces: the detectors (:mod:`mysim_jax.perception.track_detectors`), the gimbal's
kinematics and its controller (:mod:`mysim_jax.perception.gimbal_tracker`: control law and
recovery), data association and the detector's region hints
(:mod:`mysim_jax.perception.track_cues`); the report of a run is
:mod:`mysim_jax.perception.track_report`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from mysim_jax.build import build
from mysim_jax.core.npgeom import quat_to_matrix
from mysim_jax.effects.gimbal_servo import GIMBAL_SERVO
from mysim_jax.perception.camera import Intrinsics, PerceptionError, intrinsics as make_intrinsics
from mysim_jax.perception.detect.model import load_detector
from mysim_jax.perception.detect.team import (TEAM_ATTITUDE_SIGMA_RAD, TEAM_POSITION_SIGMA_M, expected_boxes,
                                              perturbed_positions)
from mysim_jax.perception.gimbal_tracker import GimbalGeometry, GimbalTracker, GimbalTrackerConfig
from mysim_jax.perception.localize import RANGE_SIGMA, PoseNoise
from mysim_jax.perception.render import Renderer
from mysim_jax.perception.render_io import Frame
from mysim_jax.perception.render_models import auto_target_style, tip_radius
from mysim_jax.perception.track_cues import _associate_all, _RegionMemory, _team_point
from mysim_jax.perception.track_detectors import (OUT_OF_VIEW, FrameDetector, OracleDetector, RegionDetector,
                                                  image_detector)
from mysim_jax.sim import rollout
from mysim_jax.tasks.scripted import team_policy


# --- closed loop in the simulator -----------------------------------------------------------


def gimbal_cameras(config) -> list[tuple[str, object]]:
    """``[(uav body, camera config), ...]`` of every gimbal camera, in the simulator's gimbal order."""
    return [(q.body, c) for q in config.quadrotors for c in q.cameras if c.mount == "gimbal"]


class _SkyRenderer(Renderer):
    """The renderer for a tracking camera: it may look above the horizon (the target is often
    higher than the UAV), so the check that a camera sees ground (needed by VIO) is skipped."""

    def _check_ground(self, name, columns, poses, rows):
        return None


def check_tracking_scene(config) -> None:
    """Raise unless the scene has a target and a gimbal camera on at least one UAV."""
    if getattr(config, "target", None) is None:
        raise PerceptionError(f"scene '{config.name}' has no target; tracking needs a target: block")
    if not gimbal_cameras(config):
        fixed = [c.name for q in config.quadrotors for c in q.cameras]
        raise PerceptionError(
            f"scene '{config.name}' has no gimbal camera (cameras: {', '.join(fixed) or 'none'}); add one with "
            f"mount: gimbal under a quadrotor's cameras: (see configs/capture_falling_gimbals.yaml)")


@dataclass
class TrackingRecord:
    """What the closed loop saw and did, per frame and gimbal camera (``F`` frames, ``G`` cameras)."""

    cameras: tuple[str, ...]
    uavs: tuple[str, ...]
    t: np.ndarray                   # (F,) s
    camera_R: np.ndarray            # (F, G, 3, 3) OpenCV camera frame -> world (true)
    camera_p: np.ndarray            # (F, G, 3) m, optical centre (true)
    angles: np.ndarray              # (F, G, 2) rad, encoder angles at the frame
    command: np.ndarray             # (F, G, 2) rad, command set after the frame
    mode: np.ndarray                # (F, G) str, tracker mode after the frame
    det_box: np.ndarray             # (F, G, 4) px, best detection (NaN: none)
    true_box: np.ndarray            # (F, G, 4) px, visible ground-truth box (NaN: none visible)
    true_centre: np.ndarray         # (F, G, 2) px, projection of the target's centre
    true_depth: np.ndarray          # (F, G) m, along the optical axis
    visible_fraction: np.ndarray    # (F, G) visible target pixels / its unoccluded silhouette's
    target_pos: np.ndarray          # (F, 3) m, true target centre
    target_vel: np.ndarray          # (F, 3) m/s, true target velocity
    target_radius: float            # m
    intr: Intrinsics
    columns: dict = field(default_factory=dict)    # trajectory columns, one row per frame

    def in_view(self) -> np.ndarray:
        """(F, G) bool: the target's centre projects inside the image, in front of the camera."""
        u, v = self.true_centre[..., 0], self.true_centre[..., 1]
        return ((self.true_depth > 0) & (u >= -0.5) & (u <= self.intr.width - 0.5)
                & (v >= -0.5) & (v <= self.intr.height - 0.5))

    def pixel_error(self) -> np.ndarray:
        """(F, G) px, distance of the target's projected centre from the image centre (NaN behind the camera)."""
        d = np.hypot(self.true_centre[..., 0] - self.intr.cx, self.true_centre[..., 1] - self.intr.cy)
        return np.where(self.true_depth > 0, d, np.nan)

    @classmethod
    def load_npz(cls, path) -> "TrackingRecord":
        """A record written by :meth:`save_npz` (``scripts/perceive.py --track`` writes
        ``tracking.npz``), e.g. to localise again with other settings; ``columns`` stay empty."""
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise PerceptionError(f"{path}: not a tracking record ({err})") from None
        names = [f.name for f in dataclasses.fields(cls) if f.name not in ("intr", "columns")]
        missing = [n for n in names + ["intr"] if n not in data.files]
        if missing:
            raise PerceptionError(f"{path}: not a tracking record of this version (missing {', '.join(missing)}); "
                                  f"write it with scripts/perceive.py --track")
        w, h, fx, fy, cx, cy = data["intr"]
        fields = {n: data[n] for n in names}
        fields["cameras"] = tuple(str(c) for c in fields["cameras"])
        fields["uavs"] = tuple(str(u) for u in fields["uavs"])
        fields["target_radius"] = float(fields["target_radius"])
        return cls(intr=Intrinsics(width=int(w), height=int(h), fx=float(fx), fy=float(fy), cx=float(cx),
                                   cy=float(cy)), **fields)

    def save_npz(self, path) -> None:
        np.savez_compressed(path, **{f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                                     if f.name not in ("intr", "columns")},
                            intr=np.array([self.intr.width, self.intr.height, self.intr.fx, self.intr.fy,
                                           self.intr.cx, self.intr.cy]))


def _point_at_start(config, scene, state):
    """A copy of ``config`` whose gimbal cameras start pointed at the target's start position."""
    bi = {n: i for i, n in enumerate(scene.body_names)}
    target = np.asarray(state.phys.body_pos[bi[config.target.name]], float)
    quads = []
    for q in config.quadrotors:
        cams = []
        for c in q.cameras:
            if c.mount == "gimbal":
                uR = quat_to_matrix(np.asarray(state.phys.body_quat[bi[q.body]], float))
                d = target - np.asarray(state.phys.body_pos[bi[c.name]], float)
                a = GimbalGeometry(c).aim(uR.T @ d, c.command.angle)
                c = c.model_copy(update={"command": c.command.model_copy(update={"angle": (float(a[0]), float(a[1]))})})
            cams.append(c)
        quads.append(q.model_copy(update={"cameras": cams}))
    return config.model_copy(update={"quadrotors": quads})


def _state_columns(scene, state) -> dict[str, np.ndarray]:
    """One-row trajectory columns (time, poses, point positions) of a simulator state."""
    phys = state.phys
    cols = {"time": np.array([float(state.time)])}
    pp, bp, bq = np.asarray(phys.point_pos), np.asarray(phys.body_pos), np.asarray(phys.body_quat)
    for i, n in enumerate(scene.point_names):
        for c, a in enumerate("xyz"):
            cols[f"{n}_{a}"] = pp[i, c:c + 1].astype(float)
    for i, n in enumerate(scene.body_names):
        for c, a in enumerate("xyz"):
            cols[f"{n}_{a}"] = bp[i, c:c + 1].astype(float)
        for c, a in enumerate("wxyz"):
            cols[f"{n}_q{a}"] = bq[i, c:c + 1].astype(float)
    return cols


def _detect(renderer, detector, cams, geoms, cols, bq, bi, t, force_loss, hint_of=None):
    """Every gimbal camera's frame at this row, its detections (none inside ``force_loss``),
    its gimbal angles and its UAV's attitude. ``hint_of(g, frame)``: where camera ``g``
    expects the target (a :class:`RegionHint` or None), for a detector that takes hints."""
    frames, dets, angles, uav_Rs = [], [], [], []
    hints = getattr(detector, "accepts_hints", False) and hint_of is not None
    for g, (uav, cam) in enumerate(cams):
        frame = renderer.render(cols, cam.name, 0)
        found = list(detector(frame, hint_of(g, frame)) if hints else detector(frame))
        if force_loss is not None and force_loss[0] <= t < force_loss[1]:
            found = []
        uR = quat_to_matrix(bq[bi[uav]])
        angles.append(geoms[g].angles(uR, quat_to_matrix(bq[bi[cam.name]])))
        frames.append(frame)
        dets.append(found)
        uav_Rs.append(uR)
    return frames, dets, angles, uav_Rs


def _steer(trackers, t, frames, dets, angles, uav_Rs, omegas, intr, radius, cue, cooperative_cue,
           range_sigma: float = 0.05):
    """Each tracker's gimbal command from its detections, or, without one, from the start
    cue (``cue``, a world point, before its first detection) or from the point the cameras
    that see the target locate (``cooperative_cue``)."""
    seen = [g for g in range(len(trackers)) if dets[g]]
    commands = []
    for g, tracker in enumerate(trackers):
        aim = None
        if cue is not None and not dets[g] and tracker.last_seen_t is None:
            aim = cue - frames[g].p
        elif cooperative_cue and not dets[g] and any(s != g for s in seen):
            point = _team_point([frames[s] for s in seen if s != g], [dets[s][0] for s in seen if s != g],
                                intr, radius, range_sigma)
            if point is not None:
                aim = point - frames[g].p
        commands.append(tracker.update(t, dets[g], angles[g], uav_Rs[g], frames[g].R, aim, uav_omega=omegas[g]))
    return np.asarray(commands, float)


def _record(rec: dict, t, frames, angles, commands, trackers, dets, target_pos, target_vel) -> None:
    """Append one frame's row to the record."""
    tv = [f.target for f in frames]
    rec["t"].append(t)
    rec["camera_R"].append([f.R for f in frames])
    rec["camera_p"].append([f.p for f in frames])
    rec["angles"].append(angles)
    rec["command"].append(commands.copy())
    rec["mode"].append([tr.mode for tr in trackers])
    rec["det_box"].append([d[0].box if d else np.full(4, np.nan) for d in dets])
    rec["true_box"].append([v.box if v.box is not None else np.full(4, np.nan) for v in tv])
    rec["true_centre"].append([v.centre for v in tv])
    rec["true_depth"].append([v.depth for v in tv])
    rec["visible_fraction"].append([v.visible_fraction for v in tv])
    rec["target_pos"].append(target_pos)
    rec["target_vel"].append(target_vel)


def _steps_per_frame(scene, frame_rate: float) -> int:
    steps = int(round(1.0 / (frame_rate * scene.dt)))
    if steps < 1 or abs(steps * scene.dt * frame_rate - 1.0) > 1e-6:
        raise PerceptionError(f"frame_rate {frame_rate:g} Hz is not a whole number of simulator steps "
                              f"(dt = {scene.dt:g} s); pick 1 / (k dt), e.g. "
                              f"{1.0 / (round(1 / (frame_rate * scene.dt)) * scene.dt):g} Hz")
    return steps


def _start_cue(config, params, state, target_body: int):
    """``t -> point``: the target's path predicted from its true start state (ballistic for
    a falling target, constant velocity otherwise)."""
    p0 = np.asarray(state.phys.body_pos[target_body], float)
    v0 = np.asarray(state.phys.body_vel[target_body], float)
    g_acc = np.asarray(params.gravity, float) if config.target.behaviour == "falling" else np.zeros(3)

    def cue_point(t):
        return p0 + v0 * t + 0.5 * g_acc * t * t
    return cue_point


def _tracking_scene(config, initial_cue: bool, frame_rate: float):
    """``(config, scene, params, state, steps per frame)`` of a tracking run: the cameras
    pointed at the target's start with ``initial_cue``, one environment, the gimbals' sine
    commands zeroed (the trackers command them)."""
    scene, params, state = build(config)
    if initial_cue:
        config = _point_at_start(config, scene, state)
        scene, params, state = build(config)
    servo = GIMBAL_SERVO.params(params)
    params = GIMBAL_SERVO.with_params(params, servo.replace(amplitude=0.0 * servo.amplitude))
    return config, scene, params, state, _steps_per_frame(scene, frame_rate)


def _finite_poses(state, t: float) -> tuple[np.ndarray, np.ndarray]:
    """The bodies' quaternions and positions; PerceptionError once the simulation is non-finite."""
    bq = np.asarray(state.phys.body_quat, float)
    bp = np.asarray(state.phys.body_pos, float)
    if not (np.all(np.isfinite(bq)) and np.all(np.isfinite(bp))):
        raise PerceptionError(f"the simulation turned non-finite at t = {t:g} s; simulate the scene with "
                              f"scripts/simulate.py to see where")
    return bq, bp


# what a tracking run records per frame (TrackingRecord's per-frame fields)
_RECORDED = ("t", "camera_R", "camera_p", "angles", "command", "mode", "det_box", "true_box", "true_centre",
             "true_depth", "visible_fraction", "target_pos", "target_vel")


class _Teammates:
    """Where a tracking run's other UAVs are expected in a camera's image
    (:func:`~mysim_jax.perception.detect.team.expected_boxes`), as the team knows it: their
    positions and the camera's pose with the VIO-like errors of
    :func:`~mysim_jax.perception.detect.team.perturbed_positions`, drawn each frame from
    ``seed``; with ``seed`` None nobody is told."""

    def __init__(self, config, intr: Intrinsics, seed: int | None):
        self.rng = None if seed is None else np.random.default_rng(seed)
        self.radius = {q.body: tip_radius(q.rotors.arm_length) for q in config.quadrotors}
        self.intr = intr

    def told(self, hint, frame: Frame, own: str, positions: dict):
        """``hint`` with the boxes of the UAVs other than ``own`` (``positions``: body -> (3,)
        m) in ``frame``; ``hint`` as it is when there is none or nobody is told."""
        if hint is None or hint is OUT_OF_VIEW or self.rng is None:
            return hint
        others = [u for u in self.radius if u != own]
        pos, R = perturbed_positions(self.rng, [positions[u] for u in others], frame.R, TEAM_POSITION_SIGMA_M,
                                     TEAM_ATTITUDE_SIGMA_RAD)
        return dataclasses.replace(hint, teammates=expected_boxes(self.intr, R, frame.p, pos,
                                                                   [self.radius[u] for u in others]))


def run_tracking(config, detector: FrameDetector | None = None, intr: Intrinsics | None = None,
                 frame_rate: float = 25.0, tracker_config: GimbalTrackerConfig = GimbalTrackerConfig(),
                 t_end: float | None = None, initial_cue: bool = True, cooperative_cue: bool = True,
                 force_loss: tuple[float, float] | None = None, target_style: str = "auto",
                 range_sigma: float | None = None, team_seed: int | None = 0,
                 progress: bool = True) -> TrackingRecord:
    """Simulate ``config`` (a scene config with gimbal cameras and a target) with every gimbal
    steered by a :class:`GimbalTracker` from its rendered images (see the module doc).

    ``detector``: ``Frame -> detections`` (default: :class:`OracleDetector`); ``intr``: the
    cameras' intrinsics (default: the paper's camera at 640 x 360); ``frame_rate``: Hz, a
    whole number of simulator steps per frame; ``t_end``: s (default: the config's).
    ``initial_cue``: until a camera first detects the target, it points at the target's
    path predicted from its true start state (ballistic for a falling target, constant
    velocity otherwise): the cue that starts a capture; without it the cameras search. ``cooperative_cue``: a
    camera that has lost the target points at the target located by the cameras that see it
    (least squares over their rays and box ranges; one camera with a whole box suffices). ``force_loss``: ``(t0, t1)`` s, a window in which every
    detection is dropped (to test recovery). ``target_style``: how the renderer draws the
    target (:class:`~mysim_jax.perception.render.Renderer`; ``"auto"``: a drone for a
    maneuvering target, else a sphere). ``range_sigma``: the relative noise of ranges from
    box sizes in the teammates' point (the cooperative cue and the region hints; default
    :data:`~mysim_jax.perception.localize.RANGE_SIGMA` of the target's look). A detector
    that takes hints (:class:`RegionDetector`) is told where each camera expects the
    target (:func:`region_hint`, :func:`point_hint`) and where the team's other UAVs are
    (:class:`_Teammates`, its errors drawn from ``team_seed``; None: it is not told).
    """
    check_tracking_scene(config)
    if not frame_rate > 0:
        raise PerceptionError(f"frame_rate must be positive, got {frame_rate}")
    intr = make_intrinsics(width=640, height=360) if intr is None else intr
    detector = OracleDetector() if detector is None else detector
    config, scene, params, state, steps = _tracking_scene(config, initial_cue, frame_rate)
    frame_dt = steps * scene.dt
    n_frames = int(np.floor((config.sim.t_end if t_end is None else float(t_end)) / frame_dt + 1e-9)) + 1
    policy = team_policy(config, scene)
    cams = gimbal_cameras(config)
    names, uavs = tuple(c.name for _, c in cams), tuple(u for u, _ in cams)
    geoms = [GimbalGeometry(c) for _, c in cams]
    renderer = _SkyRenderer(config, intr, target_style=target_style)
    trackers = [GimbalTracker(g, intr, frame_dt, tracker_config, c.command.angle) for g, (_, c) in zip(geoms, cams)]
    advance = jax.jit(rollout, static_argnums=(0, 3, 4, 5))
    bi = {n: i for i, n in enumerate(scene.body_names)}
    target = config.target.name

    cue_point = _start_cue(config, params, state, bi[target])
    range_sigma = RANGE_SIGMA[auto_target_style(config)] if range_sigma is None else float(range_sigma)
    memory = _RegionMemory(len(cams), (tracker_config.hold_frames + 1) * frame_dt, intr, config.target.radius,
                           range_sigma)
    team = _Teammates(config, intr, team_seed)
    rec = {k: [] for k in _RECORDED}
    rows = []
    bar = tqdm(total=n_frames, desc="track (render, detect, steer, simulate)", unit="frame", disable=not progress)
    for k in range(n_frames):
        cols = _state_columns(scene, state)
        rows.append(cols)
        t = float(cols["time"][0])
        bq, bp = _finite_poses(state, t)
        cue_now = cue_point(t) if initial_cue else None
        hint_of = lambda g, frame: team.told(memory.hint(g, trackers[g], t, frame, cue_now), frame,  # noqa: E731
                                             uavs[g], {u: bp[bi[u]] for u in team.radius})
        frames, dets, angles, uav_Rs = _detect(renderer, detector, cams, geoms, cols, bq, bi, t, force_loss, hint_of)
        if tracker_config.gate_deg is not None:
            ref_of = lambda g: cue_point(t) if initial_cue and trackers[g].last_seen_t is None else None  # noqa: E731
            dets = _associate_all(dets, frames, ref_of, tracker_config.gate_deg, intr, config.target.radius)
        memory.update(t, frames, dets)
        omegas = [np.asarray(state.phys.body_angvel[bi[u]], float) for u in uavs]
        commands = _steer(trackers, t, frames, dets, angles, uav_Rs, omegas, intr, config.target.radius,
                          cue_point(t) if initial_cue else None, cooperative_cue, range_sigma)
        _record(rec, t, frames, angles, commands, trackers, dets, bp[bi[target]],
                np.asarray(state.phys.body_vel[bi[target]], float))
        bar.update(1)
        if k == n_frames - 1:
            break
        servo = GIMBAL_SERVO.params(params)
        params = GIMBAL_SERVO.with_params(params, servo.replace(angle=jax.numpy.asarray(commands, servo.angle.dtype)))
        state, _ = advance(scene, params, state, steps, steps, policy)
    bar.close()
    return TrackingRecord(cameras=names, uavs=uavs, intr=intr, target_radius=float(config.target.radius),
                          columns={key: np.concatenate([r[key] for r in rows]) for key in rows[0]},
                          **{k: np.asarray(v) for k, v in rec.items()})


MOVING_SPEED = 0.5      # m/s: above this the target counts as moving (falling, evading), below as held


def target_moving(record: TrackingRecord) -> np.ndarray:
    """(F,) bool: frames in which the target's speed (central differences) is above MOVING_SPEED."""
    if len(record.t) < 2:
        return np.zeros(len(record.t), bool)
    v = np.gradient(record.target_pos, record.t, axis=0)
    return np.linalg.norm(v, axis=1) > MOVING_SPEED


def tracking_metrics(record: TrackingRecord) -> dict:
    """In-view fraction, detection fraction and pixel error of the target's centre from the
    image centre (px; mean and 95th percentile over frames with the target in front), per
    camera, over all, and over the frames with the target moving (:func:`target_moving`)."""
    inview = record.in_view()
    err = record.pixel_error()
    detected = np.all(np.isfinite(record.det_box), axis=-1)

    def stats(sel):
        e = err[sel]
        e = e[np.isfinite(e)]
        iv = inview[sel]
        return {"camera_frames": int(iv.size), "in_view_fraction": float(iv.mean()) if iv.size else None,
                "detected_fraction": float(detected[sel].mean()) if iv.size else None,
                "pixel_error_mean_px": float(e.mean()) if e.size else None,
                "pixel_error_p95_px": float(np.percentile(e, 95)) if e.size else None,
                "pixel_error_median_px": float(np.median(e)) if e.size else None}

    out = {"all": stats(np.ones_like(inview, bool))}
    moving = target_moving(record)
    out["target_moving"] = stats(np.broadcast_to(moving[:, None], inview.shape))
    out["target_moving"]["note"] = f"frames with the target faster than {MOVING_SPEED:g} m/s"
    for g, name in enumerate(record.cameras):
        sel = np.zeros_like(inview, bool)
        sel[:, g] = True
        out[name] = stats(sel)
    modes, counts = np.unique(record.mode, return_counts=True)
    out["modes"] = {str(m): int(c) for m, c in zip(modes, counts)}
    out["image_centre_px"] = [record.intr.cx, record.intr.cy]
    return out


def make_detector(kind: str, weights=None, noise_px: float = 1.0, miss_rate: float = 0.0, seed: int = 0,
                  region: bool = True):
    """The frame detector a tracking run uses: ``"oracle"`` (the true box with edge noise
    and misses) or ``"learned"`` (the CNN, with ``weights`` or the committed ones; with
    ``region`` a :class:`RegionDetector`, which looks where the tracker expects the target,
    else the whole image every frame). PerceptionError for weights that do not fit the
    choice or do not exist."""
    if weights is not None and kind != "learned":
        raise PerceptionError("--weights is for --detector learned")
    if weights is not None and not Path(weights).is_file():
        raise PerceptionError(f"--weights {weights}: no such file; train one with scripts/train_detector.py")
    if kind == "oracle":
        return OracleDetector(noise_px=noise_px, miss_rate=miss_rate, seed=seed)
    cnn = load_detector(weights)
    return RegionDetector(cnn) if region else image_detector(cnn)


def make_pose_noise(position_m: float, rotation_rad: float, correlation_time: float = 0.0, seed: int = 0) -> PoseNoise:
    """Camera-pose noise for localisation (standard deviations, Gauss-Markov correlation
    time; 0: white). PerceptionError for a negative value."""
    if not (position_m >= 0 and rotation_rad >= 0 and correlation_time >= 0):
        raise PerceptionError(f"--pose-noise values and --pose-noise-time must be >= 0, got "
                              f"{[position_m, rotation_rad]}, {correlation_time}")
    return PoseNoise(position_m=position_m, rotation_rad=rotation_rad, seed=seed, correlation_time=correlation_time)
