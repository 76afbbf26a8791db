"""What the renderer draws: every object's model, as ellipsoids and capsules in its body
frame, and the scene's list of them.

A quadrotor is a hull, four arms to its rotor positions (the scene's rotor layout; the front
pair, body +x, in red so the heading shows), motors and rotor discs; a camera body a small
box with a lens along its optical axis; the target a sphere of its radius or a small
quadrotor that fits inside it (:func:`auto_target_style`). :func:`body_models` lists the
bodies of a scene with their models, :func:`stack_models` concatenates the models into
arrays, and :func:`line_segments` lists the net's lines and the tethers as segments between
trajectory points. :mod:`mysim_jax.perception.render` places and draws them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Model", "quadrotor_model", "camera_model", "sphere_model", "stack_models", "auto_target_style",
           "body_models", "line_segments", "HULL", "FRONT", "REAR", "MOTOR", "ROTOR", "TARGET", "TARGET_DRONE",
           "NET", "TETHER", "CAMERA", "LENS", "TIP_RATIO", "tip_radius"]


@dataclass
class Model:
    """Primitives of one object in its body frame (x forward, y left, z up; m)."""

    e_centre: list = field(default_factory=list)      # (3,)
    e_axes: list = field(default_factory=list)        # (3, 3)
    e_semi: list = field(default_factory=list)        # (3,)
    e_colour: list = field(default_factory=list)
    c_a: list = field(default_factory=list)
    c_b: list = field(default_factory=list)
    c_radius: list = field(default_factory=list)
    c_colour: list = field(default_factory=list)

    def ellipsoid(self, centre, semi, colour, axes=None):
        self.e_centre.append(np.asarray(centre, float))
        self.e_semi.append(np.asarray(semi, float))
        self.e_axes.append(np.eye(3) if axes is None else np.asarray(axes, float))
        self.e_colour.append(np.asarray(colour, float))

    def capsule(self, a, b, radius, colour):
        self.c_a.append(np.asarray(a, float))
        self.c_b.append(np.asarray(b, float))
        self.c_radius.append(float(radius))
        self.c_colour.append(np.asarray(colour, float))


HULL = (0.80, 0.81, 0.84)
FRONT = (0.85, 0.12, 0.08)
REAR = (0.16, 0.16, 0.18)
MOTOR = (0.10, 0.10, 0.11)
ROTOR = (0.62, 0.64, 0.68)
TARGET = (0.95, 0.42, 0.05)
TARGET_DRONE = (0.10, 0.10, 0.10)
NET = (0.93, 0.93, 0.88)
TETHER = (0.95, 0.80, 0.15)
CAMERA = (0.12, 0.12, 0.14)
LENS = (0.02, 0.02, 0.03)


# a quadrotor's rotor tips from its centre / its mean arm length: the arm (1) and the rotor
# disc's semi-axis (0.48) of quadrotor_model
TIP_RATIO = 1.48


def tip_radius(arm_length) -> float:
    """m, a drawn quadrotor's rotor tips from its centre, for its arm lengths (m)."""
    return TIP_RATIO * float(np.mean(arm_length))


def quadrotor_model(arm_length, angle, hull=HULL, front=FRONT, rear=REAR) -> Model:
    """A quadrotor: hull, arms to ``d_i = l_i (sin a_i, cos a_i, 0)`` (the scene's rotor layout),
    motors and rotor discs, sized by the mean arm length L (rotor tips at ``TIP_RATIO`` L)."""
    arm = np.asarray(arm_length, float)
    ang = np.asarray(angle, float)
    L = float(arm.mean())
    m = Model()
    m.ellipsoid((0, 0, 0), (0.42 * L, 0.30 * L, 0.16 * L), hull)
    for l_i, a_i in zip(arm, ang):
        d = np.array([l_i * np.sin(a_i), l_i * np.cos(a_i), 0.0])
        m.capsule((0, 0, 0), d, 0.07 * L, front if d[0] > 1e-9 else rear)
        m.capsule(d - (0, 0, 0.10 * L), d + (0, 0, 0.18 * L), 0.11 * L, MOTOR)
        m.ellipsoid(d + (0, 0, 0.24 * L), (0.48 * L, 0.48 * L, 0.025 * L), ROTOR)
    return m


def camera_model() -> Model:
    """A camera body: a small dark box (ellipsoid) with a lens along the optical axis (+x)."""
    m = Model()
    m.ellipsoid((0, 0, 0), (0.018, 0.015, 0.015), CAMERA)
    m.capsule((0.012, 0, 0), (0.024, 0, 0), 0.008, LENS)
    return m


def sphere_model(radius: float, colour=TARGET) -> Model:
    m = Model()
    m.ellipsoid((0, 0, 0), (radius, radius, radius), colour)
    return m


def stack_models(models: list[Model]):
    """Concatenate models: ellipsoid and capsule arrays with the index of their model."""
    e_owner = np.concatenate([np.full(len(m.e_centre), k) for k, m in enumerate(models)] or [np.zeros(0)]).astype(int)
    c_owner = np.concatenate([np.full(len(m.c_a), k) for k, m in enumerate(models)] or [np.zeros(0)]).astype(int)

    def cat(key, shape):
        rows = [x for m in models for x in getattr(m, key)]
        return np.asarray(rows, dtype=float).reshape((-1,) + shape)

    return (e_owner, cat("e_centre", (3,)), cat("e_axes", (3, 3)), cat("e_semi", (3,)), cat("e_colour", (3,)),
            c_owner, cat("c_a", (3,)), cat("c_b", (3,)), cat("c_radius", ()), cat("c_colour", (3,)))


def auto_target_style(config) -> str:
    """How ``target_style="auto"`` draws the scene's target: ``"drone"`` for a maneuvering
    target (the evading drone), else ``"sphere"``."""
    return "drone" if config.target.behaviour == "maneuvering" else "sphere"


def body_models(config, target_style):
    """The bodies drawn, in the order of their models (the target, the quadrotors, their
    cameras), the models, and each camera's quadrotor."""
    bodies: list[str] = []
    models: list[Model] = []
    camera_owner: dict[str, str] = {}
    target = getattr(config, "target", None)
    if target is not None:
        style = auto_target_style(config) if target_style == "auto" else target_style
        bodies.append(target.name)
        if style == "drone":
            L = target.radius / TIP_RATIO
            models.append(quadrotor_model((L,) * 4, tuple(np.pi / 4 + k * np.pi / 2 for k in range(4)),
                                          hull=TARGET_DRONE, front=TARGET, rear=TARGET_DRONE))
        else:
            models.append(sphere_model(target.radius))
    for q in config.quadrotors:
        bodies.append(q.body)
        models.append(quadrotor_model(q.rotors.arm_length, q.rotors.angle))
    for q in config.quadrotors:
        for cam in q.cameras:
            bodies.append(cam.name)
            models.append(camera_model())
            camera_owner[cam.name] = q.body
    return bodies, models, camera_owner


def line_segments(net, bodies, names):
    """The net's lines and tethers as segments between trajectory points (or, at a UAV's
    end, tether markers): ``(points, [(point a, point b, object id)], radii, colours,
    [(body index, attach point in the body frame)])``. Appends the net's and each tether's
    object name to ``names``."""
    points: list[str] = []
    segments: list[tuple[int, int, int]] = []
    radius: list[float] = []
    colours: list[tuple] = []
    markers: list[tuple[int, np.ndarray]] = []
    if net is None:
        return points, segments, radius, colours, markers
    index: dict[str, int] = {}

    def point(n):
        if n not in index:
            index[n] = len(points)
            points.append(n)
        return index[n]

    net_id = len(names)
    names.append(net.name)
    for chain in net.edge_chains():
        ids = [point(n) for n in chain]
        segments += [(a, b, net_id) for a, b in zip(ids[:-1], ids[1:])]
        radius += [net.line.diameter / 2] * (len(ids) - 1)
        colours += [NET] * (len(ids) - 1)
    if net.tethers is not None:
        t = net.tethers
        for k, (uav, knot) in enumerate(zip(t.uavs, net.tether_knots())):
            tether_id = len(names)
            names.append(f"tether{k}")
            chain = [point(net.knot_name(*knot))] + [point(f"{net.name}_t{k}_{m}") for m in range(t.n_masses)]
            markers.append((bodies.index(uav), np.asarray(t.attach, float)))
            chain.append(-len(markers))           # negative: a tether marker (resolved at render)
            segments += [(a, b, tether_id) for a, b in zip(chain[:-1], chain[1:])]
            radius += [t.line.diameter / 2] * (len(chain) - 1)
            colours += [TETHER] * (len(chain) - 1)
    return points, segments, radius, colours, markers
