"""Checks of a scene's entries across its blocks: names used twice, rope and spring ends,
joint markers, loads and plotted names that refer to nothing, contact and quadrotor
references, and scenes too large to build or to save. Each function takes a
:class:`~mysim_jax.config.scene.SceneConfig` (read only, the net and the target already
expanded into entries) and returns its problems as one-line messages naming the field;
:func:`reference_problems` runs them all. Pydantic-free and JAX-free: plain reads of the
validated blocks."""

from __future__ import annotations

from mysim_jax.config.quadrotor import quadrotor_problems
from mysim_jax.contact.config import contact_problems

# Scene-size limits: a scene beyond these is almost always a typo (t_end in ms, dt in s...).
MAX_OUTPUT_VALUES = 200_000_000    # saved numbers (rows x columns): 1.6 GB in memory, ~4 GB of CSV
MAX_OBJECTS = 100_000              # point masses (rope masses included) and bodies of a scene


def reference_problems(scene) -> list[str]:
    """Every problem of the entries of ``scene`` (ValueError first if it is too large:
    :func:`check_size`)."""
    check_size(scene)
    problems = name_problems(scene)
    problems += attachment_problems(scene)
    problems += joint_problems(scene)
    attachable = scene.attachment_names()
    for i, ld in enumerate(scene.loads):
        if ld.at not in attachable or ld.at in scene.anchor_names():
            problems.append(f"loads.{i}.at: '{ld.at}' is not a point, body or body.marker")
        elif any(ld.torque) and ld.at not in {b.name for b in scene.bodies}:
            problems.append(f"loads.{i}.torque: a torque needs a body, '{ld.at}' is not one")
    plottable = scene.trajectory_names()
    for i, name in enumerate(scene.output.plot):
        if name not in plottable:
            problems.append(f"output.plot.{i}: '{name}' is not a point or body")
    if scene.contact is not None:
        points = [p.name for p in scene.points] + [f"{r.name}_{j}" for r in scene.ropes for j in range(r.n_masses)]
        problems += contact_problems(scene.contact, points, [b.name for b in scene.bodies], scene.anchor_names(),
                                     ropes=scene.ropes, springs=scene.springs)
    problems += quadrotor_problems(scene)
    return problems


def check_size(scene) -> None:
    """Refuse scenes too large to build or to save (ValueError)."""
    n_cameras = sum(len(q.cameras) for q in scene.quadrotors)
    n_objects = (len(scene.points) + sum(r.n_masses for r in scene.ropes) + len(scene.bodies) + n_cameras)
    if n_objects > MAX_OBJECTS:
        raise ValueError(f"the scene has {n_objects:,} point masses and bodies (rope masses and cameras "
                         f"included): more than {MAX_OBJECTS:,}")
    rows, columns = scene.output_size()
    values = rows * columns
    if values > MAX_OUTPUT_VALUES:
        raise ValueError(
            f"sim: the run would save {rows:,} rows of {columns:,} columns ({values:.3g} "
            f"values, more than {MAX_OUTPUT_VALUES:.3g}); raise sim.output_dt or shorten sim.t_end")


def name_problems(scene) -> list[str]:
    """Names used twice (points, bodies, anchors, ropes and their masses, springs,
    joints share one namespace; markers are unique per body)."""
    problems: list[str] = []
    owners: dict[str, str] = {}

    def claim(name: str, where: str):
        if name in owners:
            problems.append(f"{where}: name '{name}' is already used by {owners[name]}")
        else:
            owners[name] = where

    for i, p in enumerate(scene.points):
        claim(p.name, f"points.{i}")
    for i, b in enumerate(scene.bodies):
        claim(b.name, f"bodies.{i}")
        seen = set()
        for j, m in enumerate(b.markers):
            if m.name in seen:
                problems.append(f"bodies.{i}.markers.{j}: duplicate marker name '{m.name}'")
            seen.add(m.name)
    for i, a in enumerate(scene.anchors):
        claim(a.name, f"anchors.{i}")
    for i, r in enumerate(scene.ropes):
        claim(r.name, f"ropes.{i}")
        for j in range(r.n_masses):
            claim(f"{r.name}_{j}", f"ropes.{i} (its mass {j})")
    for i, s in enumerate(scene.springs):
        claim(s.name, f"springs.{i}")
    for i, j in enumerate(scene.joints):
        claim(j.name, f"joints.{i}")
    return problems


def attachment_problems(scene) -> list[str]:
    """Rope and spring ends that name nothing attachable."""
    problems: list[str] = []
    attachable = scene.attachment_names()
    for kind, items in (("ropes", scene.ropes), ("springs", scene.springs)):
        for i, x in enumerate(items):
            for end in ("start", "end"):
                ref = getattr(x, end)
                if ref not in attachable:
                    problems.append(f"{kind}.{i}.{end}: '{ref}' {unknown_reference(scene, ref)}")
                elif kind == "ropes" and ref.startswith(f"{x.name}_"):
                    problems.append(f"ropes.{i}.{end}: a rope cannot attach to its own masses")
            if x.start == x.end:
                problems.append(f"{kind}.{i}: start and end are the same ('{x.start}')")
    return problems


def joint_problems(scene) -> list[str]:
    """Joints whose markers name no marker or anchor, or that could constrain nothing."""
    problems: list[str] = []
    frames = scene.frame_names()
    for i, j in enumerate(scene.joints):
        for side in ("marker_i", "marker_j"):
            ref = getattr(j, side)
            if ref not in frames:
                problems.append(
                    f"joints.{i}.{side}: '{ref}' is not a marker ('body.marker') or anchor"
                    f" {unknown_reference(scene, ref)}"
                )
        if j.marker_i == j.marker_j:
            problems.append(f"joints.{i}: marker_i and marker_j are the same")
        bi, bj = j.marker_i.split(".")[0], j.marker_j.split(".")[0]
        if bi == bj and "." in j.marker_i:
            problems.append(f"joints.{i}: both markers are on body '{bi}'")
        if j.marker_i in scene.anchor_names() and j.marker_j in scene.anchor_names():
            problems.append(f"joints.{i}: a joint between two anchors constrains nothing")
    return problems


def unknown_reference(scene, ref: str) -> str:
    """Why ``ref`` names nothing in ``scene`` (for a message)."""
    if "." in ref:
        body = ref.split(".")[0]
        if body not in {b.name for b in scene.bodies}:
            return f"(no body named '{body}')"
        return f"(body '{body}' has no marker '{ref.split('.', 1)[1]}')"
    return "(no point, rope mass, body or anchor has that name)"
