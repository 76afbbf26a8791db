"""Export a point-mass / spring scene to MuJoCo MJCF, for cross-checks with an independent engine.

``scene_to_mjcf(scene, params, state, timestep)`` writes the scene as MuJoCo sees it:

* every point mass is a body placed at its current position with three slide joints
  (world x, y, z, in that order) and its mass (a tiny diagonal inertia: slide joints never
  rotate the body, so the inertia does not enter the dynamics); a site at its centre;
* every anchor is a site on the world body;
* every spring (rope segments are springs in the scene's spring table, see
  :mod:`mysim_jax.core.types` for the node numbering) is a spatial tendon between two sites with
  ``stiffness`` = k, ``damping`` = c and ``springlength`` = rest length, which gives the
  force ``k (s − s̄) + c ṡ`` along the segment (tension positive) — the same law as
  :func:`mysim_jax.dynamics.forces.spring_tension` for ``linear`` springs;
* contact is disabled, gravity is ``params.gravity``, the integrator is ``Euler``.

MuJoCo's ``Euler`` is semi-implicit (velocity first, then positions with the new
velocity), like :class:`mysim_jax.dynamics.integrators.SemiImplicitEuler`. Its "implicit
damping" option (``eulerdamp``) is switched off so that damping is explicit as in our
integrator; with MuJoCo 4.0.0 it only ever covered joint (dof) damping, and tendon damping
was explicit either way (checked: one step of a damped tendon reproduces the explicit
semi-implicit update to round-off with the flag on or off).

Initial velocities (and the time) go into a keyframe named ``initial``; a fresh ``MjData``
starts at rest, so call ``mujoco.mj_resetDataKeyframe(model, data, 0)`` before stepping.
Joint positions are displacements from the initial positions: use
:func:`mujoco_point_positions` / :func:`mujoco_point_velocities` to read world values in
the scene's point order.

Anything MuJoCo cannot reproduce with this mapping raises :class:`ValueError` naming it:
rigid bodies and markers, joints, tension-only springs (a MuJoCo tendon spring pushes as
well as pulls), constant applied loads, batched (vmapped) params/state.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

from mysim_jax.core.types import Params, Scene, State

# Slide joints never rotate a body, so the inertia is irrelevant; it only has to be
# positive for MuJoCo's compiler.
_TINY_INERTIA = 1e-9


def _num(x) -> str:
    """A float as text that parses back to the same float64."""
    return format(float(x), ".17g")


def _vec(v) -> str:
    return " ".join(_num(c) for c in np.asarray(v, dtype=np.float64).reshape(-1))


def _check_exportable(scene: Scene, params: Params, state: State) -> None:
    problems = []
    if scene.n_bodies:
        problems.append(f"rigid bodies {list(scene.body_names)}")
    if scene.n_markers:
        problems.append(f"markers {list(scene.marker_names)}")
    if scene.joint_buckets:
        problems.append("joints")
    tension_only = [n for n, t in zip(scene.spring_names, scene.spring_tension_only) if t]
    if tension_only:
        shown = ", ".join(tension_only[:4]) + (", ..." if len(tension_only) > 4 else "")
        problems.append(
            f"{len(tension_only)} tension-only spring(s) ({shown}); MuJoCo tendon springs push "
            "when compressed, so only 'model: linear' ropes/springs can be exported"
        )
    if scene.has_loads:
        problems.append("constant applied loads (MuJoCo models have no constant force element; "
                        "set data.xfrc_applied yourself)")
    if problems:
        raise ValueError(
            "the scene cannot be exported to MJCF: it has " + "; ".join(problems)
            + ". The exporter handles point masses, anchors and linear springs only."
        )
    if np.ndim(state.phys.point_pos) != 2 or np.ndim(params.point_mass) != 1:
        raise ValueError(
            "scene_to_mjcf exports one environment: got batched params/state "
            f"(point_pos shape {np.shape(state.phys.point_pos)}, point_mass shape "
            f"{np.shape(params.point_mass)}); index one environment first"
        )


def scene_to_mjcf(scene: Scene, params: Params, state: State, timestep: float, name: str = "mysim_jax") -> str:
    """MJCF text of a scene of point masses, anchors and linear springs (see module doc).

    ``timestep`` [s] is MuJoCo's step (use the scene's ``substep`` to compare step for step).
    Raises :class:`ValueError` for anything that cannot be exported.
    """
    _check_exportable(scene, params, state)
    if not (timestep > 0 and np.isfinite(timestep)):
        raise ValueError(f"timestep must be a positive number of seconds, got {timestep!r}")

    mass = np.asarray(params.point_mass, dtype=np.float64)
    pos = np.asarray(state.phys.point_pos, dtype=np.float64)
    vel = np.asarray(state.phys.point_vel, dtype=np.float64)
    anchor_pos = np.asarray(params.anchor_pos, dtype=np.float64).reshape(-1, 3)
    stiffness = np.asarray(params.spring_stiffness, dtype=np.float64)
    damping = np.asarray(params.spring_damping, dtype=np.float64)
    rest = np.asarray(params.spring_rest_length, dtype=np.float64)
    gravity = np.asarray(params.gravity, dtype=np.float64) if scene.has_gravity else np.zeros(3)
    # node index -> site name (points, then markers [none here], then anchors)
    site_of = list(scene.point_names) + list(scene.anchor_names)

    q = quoteattr
    lines = [
        f"<mujoco model={q(name)}>",
        '  <compiler angle="radian" autolimits="true"/>',
        f'  <option timestep="{_num(timestep)}" gravity="{_vec(gravity)}" integrator="Euler">',
        '    <flag contact="disable" eulerdamp="disable"/>',
        "  </option>",
        "  <worldbody>",
    ]
    for name, p in zip(scene.anchor_names, anchor_pos):
        lines.append(f'    <site name={q(name)} pos="{_vec(p)}" size="0.01"/>')
    for i, name in enumerate(scene.point_names):
        lines.append(f'    <body name={q(name)} pos="{_vec(pos[i])}">')
        for axis, direction in zip("xyz", ("1 0 0", "0 1 0", "0 0 1")):
            lines.append(f'      <joint name={q(f"{name}_{axis}")} type="slide" axis="{direction}"/>')
        lines.append(
            f'      <inertial pos="0 0 0" mass="{_num(mass[i])}" '
            f'diaginertia="{_TINY_INERTIA:g} {_TINY_INERTIA:g} {_TINY_INERTIA:g}"/>'
        )
        lines.append(f'      <site name={q(name)} pos="0 0 0" size="0.01"/>')
        lines.append("    </body>")
    lines.append("  </worldbody>")
    if scene.n_springs:
        lines.append("  <tendon>")
        for k, (name, a, b) in enumerate(zip(scene.spring_names, scene.spring_node_a, scene.spring_node_b)):
            lines.append(
                f'    <spatial name={q(name)} stiffness="{_num(stiffness[k])}" '
                f'damping="{_num(damping[k])}" springlength="{_num(rest[k])}" width="0.002">'
            )
            lines.append(f"      <site site={q(site_of[a])}/>")
            lines.append(f"      <site site={q(site_of[b])}/>")
            lines.append("    </spatial>")
        lines.append("  </tendon>")
    n_dof = 3 * scene.n_points
    time = float(np.asarray(state.time, dtype=np.float64))
    lines.append("  <keyframe>")
    lines.append(
        f'    <key name="initial" time="{_num(time)}" qpos="{_vec(np.zeros(n_dof))}" qvel="{_vec(vel)}"/>'
        if n_dof else f'    <key name="initial" time="{_num(time)}"/>'
    )
    lines.append("  </keyframe>")
    lines.append("</mujoco>")
    return "\n".join(lines) + "\n"


def mujoco_point_positions(model, data) -> np.ndarray:
    """World positions ``(n_points, 3)`` of the point masses of an exported model, in the
    scene's point order (body origin + slide displacements; valid right after ``mj_step``)."""
    n = model.nbody - 1
    return model.body_pos[1:] + np.asarray(data.qpos).reshape(n, 3)


def mujoco_point_velocities(model, data) -> np.ndarray:
    """World velocities ``(n_points, 3)`` of the point masses of an exported model."""
    return np.asarray(data.qvel).reshape(model.nbody - 1, 3).copy()
