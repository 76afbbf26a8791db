"""Checks of a capture scene across its blocks (``target:``, ``team:``, ``env:``, ``net:``,
``contact:``, the quadrotors, ``sim:``): what no single block can check alone. Each
function takes a :class:`~mysim_jax.config.scene.SceneConfig` (read only) and returns
its problems as one-line messages naming the field and how to fix it;
:func:`capture_problems` runs them all. Pydantic-free and JAX-free: plain reads of the
validated blocks."""

from __future__ import annotations

from mysim_jax.config.env import ranking_problems


def capture_problems(scene) -> list[str]:
    """Every problem of the capture blocks of ``scene`` (empty for a scene without them)."""
    return (team_problems(scene) + env_problems(scene) + target_contact_problems(scene) + arena_problems(scene)
            + clearance_problems(scene))


def target_contact_problems(scene) -> list[str]:
    """The target's contact sphere must have the target's radius (both are given)."""
    if scene.target is None or scene.contact is None:
        return []
    return [f"contact.groups.{i}.radius: {g.radius:g} m, but target '{scene.target.name}' has radius "
            f"{scene.target.radius:g} m (target.radius); give its contact group the same radius"
            for i, g in enumerate(scene.contact.groups)
            if scene.target.name in (g.members or []) and g.radius != scene.target.radius]


def arena_problems(scene) -> list[str]:
    """A maneuvering target's arena must hold the net: a net wider than the arena
    could cover the whole arena at once."""
    prop = scene.target.propulsion if scene.target is not None else None
    if prop is None or prop.arena is None or scene.net is None:
        return []
    low, high = prop.arena.low, prop.arena.high
    small = [axis for axis, lo, hi in zip("xy", low, high) if hi - lo <= scene.net.size]
    if not small:
        return []
    return [f"target.propulsion.arena: {' and '.join(f'{hi - lo:g} m' for lo, hi in zip(low[:2], high[:2]))} "
            f"wide, no wider than the net (net.size = {scene.net.size:g} m) on axis {', '.join(small)}: widen the "
            "arena, or the net covers it whole"]


def clearance_problems(scene) -> list[str]:
    """A spawn clearance must leave part of the spawn box outside it (around the
    quadrotors' centroid at the start)."""
    if scene.target is None or scene.target.spawn.clearance <= 0.0:
        return []
    if not scene.quadrotors:
        return ["target.spawn.clearance: keeps the spawn away from the quadrotors' centroid, and the scene has "
                "no quadrotors"]
    bodies = {b.name: b for b in scene.bodies}
    if any(q.body not in bodies for q in scene.quadrotors):
        return []        # a quadrotor on a missing body is reported by the quadrotor checks
    centre = [sum(bodies[q.body].pos[a] for q in scene.quadrotors) / len(scene.quadrotors) for a in (0, 1)]
    low, high = scene.target.spawn.position.low, scene.target.spawn.position.high
    # the farthest point of the spawn rectangle from the centroid
    far = sum(max(abs(lo - c), abs(hi - c)) ** 2 for lo, hi, c in zip(low[:2], high[:2], centre)) ** 0.5
    clearance = scene.target.spawn.clearance
    if far <= clearance:
        return [f"target.spawn.clearance: {clearance:g} m, but no spawn position (x, y in the box low "
                f"{list(low[:2])}, high {list(high[:2])}) is farther than {far:.3g} m from the quadrotors' centroid "
                f"({centre[0]:g}, {centre[1]:g}): lower the clearance or widen target.spawn.position"]
    return []


def team_problems(scene) -> list[str]:
    team = scene.team
    if team is None:
        return []
    if not scene.quadrotors:
        return ["team: the scene has no quadrotors to give setpoints to"]
    problems = []
    if team.policy == "scripted" and scene.target is None:
        problems.append("team.policy: scripted intercepts a target, and the scene has none")
    for i, q in enumerate(scene.quadrotors):
        if q.controller is None:
            problems.append(f"team: quadrotors.{i} has no controller to take setpoints")
            continue
        lo, hi = q.controller.flyable_box.low[2], q.controller.flyable_box.high[2]
        if team.altitude is not None and not lo <= team.altitude <= hi:
            problems.append(f"team.altitude: {team.altitude:g} m is outside quadrotors.{i}'s flyable box "
                            f"(z from {lo:g} to {hi:g} m, quadrotors.{i}.controller.flyable_box)")
    return problems


def env_problems(scene, discount: float | None = None) -> list[str]:
    """The problems of a capture scene's ``env:`` block; the reward ranking checked with
    the shaping's discount ``discount`` (None: the block's ``env.discount``)."""
    env = scene.env
    if env is None:
        return []
    problems = []
    missing = [block for block, value in (("net", scene.net), ("target", scene.target), ("quadrotors", scene.quadrotors))
               if not value]
    if missing:
        problems.append(f"env: a capture environment needs {' and '.join(missing)}: block(s)")
    problems += [f"env: quadrotors.{i} has no controller to take the actions (setpoints)"
                 for i, q in enumerate(scene.quadrotors) if q.controller is None]
    if env.fault_failsafe != "none":
        modes = {q.controller.setpoint_mode for q in scene.quadrotors if q.controller is not None}
        if modes - {"velocity"}:
            problems.append(f"env.fault_failsafe: {env.fault_failsafe} floors vertical velocity setpoints: it needs "
                            "controller.setpoint_mode: velocity (this scene's is position), or fault_failsafe: none")
    period = 1.0 / env.policy_rate
    ratio = period / scene.sim.dt
    if round(ratio) < 1 or abs(ratio - round(ratio)) > 1e-6 * ratio:
        problems.append(f"env.policy_rate: {env.policy_rate:g} Hz is a period of {period:g} s, not a whole "
                        f"multiple of sim.dt = {scene.sim.dt:g} s (e.g. {1.0 / (max(round(ratio), 1) * scene.sim.dt):g} Hz)")
    elif round(scene.sim.t_end / (round(ratio) * scene.sim.dt)) < 1:
        problems.append(f"env.policy_rate: sim.t_end = {scene.sim.t_end:g} s is shorter than one policy period")
    else:
        max_steps = int(round(scene.sim.t_end / (round(ratio) * scene.sim.dt)))
        problems += ranking_problems(env.weights(), max(len(scene.quadrotors), 1), max_steps,
                                     env.discount if discount is None else discount)
    return problems
