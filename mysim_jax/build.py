"""Build ``(Scene, Params, State)`` from a validated :class:`~mysim_jax.config.scene.SceneConfig`.

Everything here is host-side NumPy; nothing is traced or compiled. The explicit stability
check of fixed-step integrators runs here (it needs the masses on both ends of each
spring) and raises :class:`~mysim_jax.config.scene.ConfigError` naming ``sim.dt``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.config.scene import FIXED_STEP_INTEGRATORS, ConfigError, SceneConfig, expand_capture
from mysim_jax.contact.broad_phase import broad_phase_start
from mysim_jax.contact.build import build_contact, contact_stable_step
from mysim_jax.contact.config import segment_table
from mysim_jax.control.build import build_quadrotors, expand_cameras
from mysim_jax.dynamics.joint_check import joint_groups, joint_problems
from mysim_jax.dynamics.implicit_springs import spring_ends_on_markers
from mysim_jax.dynamics.stability import NETWORK_STEP_SAFETY, scene_network_stable_step, stable_step
from mysim_jax.effects.registry import BuildContext, registered_effects, scene_effects
from mysim_jax.net.rope import build_rope
from mysim_jax.core.npgeom import rotate
from mysim_jax.core.types import JointBucket, Params, PhysState, Scene, State

# ``substeps: auto`` takes sub-steps of at most this fraction of the per-element explicit
# stability limits of contact pairs and Baumgarte terms: a per-element estimate ignores
# coupling between elements (which can raise the top frequency by up to ~√2) and the
# nonlinearity of contact forces. The spring network's limit needs no such factor: it is a
# bound over all configurations with its own measured margin (NETWORK_STEP_SAFETY), so
# ``auto`` uses it as the check does, and an auto step always passes the check.
AUTO_SUBSTEP_SAFETY = 0.5

# ``substeps: auto`` with ``implicit_euler``: sub-steps of at most this multiple of the
# accepted explicit step of its implicit springs (docs/scenes.md, "Stiff ropes at large steps":
# stable in randomised runs at this multiple with the default CG iterations). It is not a
# stability limit and explicit steps above it are accepted; beyond it the fixed number of
# CG iterations resolves less of the solve and the step is far less accurate.
IMPLICIT_AUTO_FACTOR = 10.0


@dataclass
class _Tables:
    """The scene's point and marker tables while they are assembled, and the lookups of
    names to indices that the later stages share."""

    config: SceneConfig
    body_index: dict
    anchor_index: dict
    point_names: list = dataclasses.field(default_factory=list)
    point_mass: list = dataclasses.field(default_factory=list)
    point_pos: list = dataclasses.field(default_factory=list)
    point_vel: list = dataclasses.field(default_factory=list)
    marker_names: list = dataclasses.field(default_factory=list)
    marker_body: list = dataclasses.field(default_factory=list)
    marker_pos: list = dataclasses.field(default_factory=list)
    marker_quat: list = dataclasses.field(default_factory=list)
    n_points: int = 0            # set by resolve_nodes: node numbers are final from then on
    n_markers: int = 0

    @classmethod
    def of(cls, config: SceneConfig) -> "_Tables":
        """The config's own points and its bodies' markers."""
        t = cls(config, {b.name: i for i, b in enumerate(config.bodies)},
                {a.name: i for i, a in enumerate(config.anchors)})
        for p in config.points:
            t.add_point(p.name, p.mass, np.asarray(p.pos, float), np.asarray(p.vel, float))
        for bi, b in enumerate(config.bodies):
            for m in b.markers:
                t.add_marker(f"{b.name}.{m.name}", bi, np.asarray(m.pos, float), np.asarray(m.quat, float))
        return t

    def add_point(self, name, mass, pos, vel):
        self.point_names.append(name)
        self.point_mass.append(mass)
        self.point_pos.append(pos)
        self.point_vel.append(vel)

    def add_marker(self, name, body, pos, quat):
        self.marker_names.append(name)
        self.marker_body.append(body)
        self.marker_pos.append(pos)
        self.marker_quat.append(quat)

    def marker_for(self, ref: str) -> int:
        """Index of marker ``body.marker``, or of an implicit centre marker for ``body``."""
        if ref not in self.marker_names:
            self.add_marker(ref, self.body_index[ref], np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
        return self.marker_names.index(ref)

    def world_pos(self, ref: str):
        """Initial world position of an attachment, or None if not placed yet."""
        if ref in self.anchor_index:
            return np.asarray(self.config.anchors[self.anchor_index[ref]].pos, float)
        if ref in self.point_names:
            return self.point_pos[self.point_names.index(ref)]
        body_name, _, marker_name = ref.partition(".")
        if body_name in self.body_index:
            b = self.config.bodies[self.body_index[body_name]]
            offset = np.zeros(3)
            if marker_name:
                offset = np.asarray(next(m.pos for m in b.markers if m.name == marker_name), float)
            return np.asarray(b.pos, float) + rotate(b.quat, offset)
        return None

    def resolve_nodes(self) -> None:
        """Give every referenced body (or body marker) its marker; node numbers are final
        after this: points, then markers, then anchors."""
        c = self.config
        refs = [r.start for r in c.ropes] + [r.end for r in c.ropes]
        refs += [s.start for s in c.springs] + [s.end for s in c.springs]
        refs += [ld.at for ld in c.loads]
        for ref in refs:
            if ref not in self.point_names and ref not in self.anchor_index:
                self.marker_for(ref)
        self.n_points, self.n_markers = len(self.point_names), len(self.marker_names)

    @property
    def n_nodes(self) -> int:
        return self.n_points + self.n_markers + len(self.config.anchors)

    def node(self, ref: str) -> int:
        if ref in self.point_names:
            return self.point_names.index(ref)
        if ref in self.anchor_index:
            return self.n_points + self.n_markers + self.anchor_index[ref]
        return self.n_points + self.marker_names.index(ref)


class _Spring(NamedTuple):
    name: str
    node_a: int
    node_b: int
    tension_only: bool
    stiffness: float
    damping: float
    rest: float


@dataclass
class _Springs:
    """Every spring of the scene, the ropes' segments first, and each rope's mass points."""

    rows: list = dataclasses.field(default_factory=list)              # a _Spring per spring
    rope_point_index: list = dataclasses.field(default_factory=list)  # per rope, its masses' point indices

    def column(self, field: str) -> tuple:
        return tuple(getattr(r, field) for r in self.rows)


def _inertia_matrix(inertia) -> np.ndarray:
    if len(inertia) == 3 and not isinstance(inertia[0], (tuple, list)):
        return np.diag(np.asarray(inertia, dtype=float))
    return np.asarray(inertia, dtype=float)


def _expanded(config: SceneConfig) -> SceneConfig:
    """The config with its net as knots, ropes and tether markers, its target as a body and
    its quadrotors' cameras as bodies, markers and joints (a new config; the input is not
    touched)."""
    if config.sim.precision == "float64" and not jax.config.jax_enable_x64:
        raise ConfigError(
            f"sim.precision: float64 requested by scene '{config.name}' but JAX runs in 32-bit "
            "mode; enable it first with jax.config.update('jax_enable_x64', True) or "
            "`with jax.enable_x64(True):` (scripts/simulate.py does this for you)"
        )
    config, problems = expand_capture(config)
    if problems:      # the config validator has reported these already; defensive only
        raise ConfigError("; ".join(problems))
    config = expand_cameras(config)
    problems = joint_problems(config)
    if problems:
        raise ConfigError("; ".join(problems))
    return config


def _place_ropes(t: _Tables) -> dict:
    """Add every rope's masses to the point table, a rope whose end hangs off another
    rope's mass after that rope. Returns ``{rope index: (first point index, rope segments)}``."""
    ropes = t.config.ropes
    placed: dict[int, object] = {}
    pending = list(range(len(ropes)))
    while pending:
        progress = False
        for ri in list(pending):
            r = ropes[ri]
            a, b = t.world_pos(r.start), t.world_pos(r.end)
            if a is None or b is None:
                continue
            seg = build_rope(r.length, r.n_masses, r.mass, r.EA, r.damping, a, b)
            placed[ri] = (len(t.point_names), seg)
            for j in range(r.n_masses):
                t.add_point(f"{r.name}_{j}", seg.point_mass[j], seg.point_pos[j], np.zeros(3))
            pending.remove(ri)
            progress = True
        if not progress:
            names = ", ".join(f"ropes.{i} ({ropes[i].name})" for i in pending)
            raise ConfigError(f"{names}: rope ends form a cycle; attach at least one end to a point, body or anchor")
    return placed


def _spring_table(t: _Tables, placed: dict) -> _Springs:
    """The ropes' segments (in rope order), then the config's springs."""
    sp = _Springs()
    for ri, r in enumerate(t.config.ropes):
        first, seg = placed[ri]
        chain = [t.node(r.start)] + list(range(first, first + r.n_masses)) + [t.node(r.end)]
        sp.rope_point_index.append(tuple(range(first, first + r.n_masses)))
        for j in range(r.n_masses + 1):
            sp.rows.append(_Spring(f"{r.name}[{j}]", chain[j], chain[j + 1], r.model == "tension_only",
                                   seg.stiffness[j], seg.damping[j], seg.rest_length[j]))
    for s in t.config.springs:
        rest = (float(np.linalg.norm(t.world_pos(s.end) - t.world_pos(s.start))) if s.rest_length is None
                else s.rest_length)
        sp.rows.append(_Spring(s.name, t.node(s.start), t.node(s.end), s.model == "tension_only", s.stiffness,
                               s.damping, rest))
    return sp


def _loads(t: _Tables) -> tuple[np.ndarray, np.ndarray]:
    """Constant loads: force per node ``(n_nodes, 3)``, torque per body ``(n_bodies, 3)``."""
    load_force = np.zeros((t.n_nodes, 3))
    load_torque = np.zeros((len(t.config.bodies), 3))
    for ld in t.config.loads:
        load_force[t.node(ld.at)] += ld.force
        if ld.at in t.body_index:
            load_torque[t.body_index[ld.at]] += ld.torque
    return load_force, load_torque


def _scene(t: _Tables, sp: _Springs, loads, contact_scene, quad_scene) -> Scene:
    """The static Scene (its effects and sub-steps are filled in later)."""
    config = t.config
    load_force, load_torque = loads
    return Scene(
        point_names=tuple(t.point_names),
        body_names=tuple(b.name for b in config.bodies),
        marker_names=tuple(t.marker_names),
        marker_body=tuple(t.marker_body),
        anchor_names=tuple(a.name for a in config.anchors),
        rope_names=tuple(r.name for r in config.ropes),
        rope_point_index=tuple(sp.rope_point_index),
        spring_names=sp.column("name"),
        spring_node_a=sp.column("node_a"),
        spring_node_b=sp.column("node_b"),
        spring_tension_only=sp.column("tension_only"),
        has_gravity=any(g != 0.0 for g in config.gravity),
        has_loads=bool(np.any(load_force) or np.any(load_torque)),
        joint_buckets=_joint_buckets(config, t.body_index, t.anchor_index, t.marker_names),
        integrator=config.sim.integrator,
        dt=config.sim.dt,
        substeps=1 if config.sim.substeps == "auto" else config.sim.substeps,
        precision=config.sim.precision,
        rtol=config.sim.rtol,
        atol=config.sim.atol,
        solver_max_steps=config.sim.max_steps,
        implicit_iterations=config.sim.cg_iterations,
        accumulate=config.sim.accumulate,
        gather=config.sim.gather,
        smooth_backward=(None if config.sim.smooth_backward is None
                         else (config.sim.smooth_backward.tension, config.sim.smooth_backward.slack)),
        contact=contact_scene,
        quadrotor=quad_scene,
    )


def _build_effects(effect_config: SceneConfig, scene: Scene) -> tuple[Scene, dict, dict]:
    """Ask every registered effect to build itself for this scene (from the config as the
    user wrote it). Returns the scene with its effects, their params and their memory."""
    quad_scene = scene.quadrotor
    ctx = BuildContext(body_names=scene.body_names, point_names=scene.point_names,
                       marker_names=scene.marker_names,
                       quadrotor_bodies=() if quad_scene is None else quad_scene.body, dtype=scene.dtype,
                       contact=scene.contact)
    effect_static, effect_params, effect_memory = [], {}, {}
    for effect in registered_effects():
        try:
            parts = effect.build(effect_config, ctx)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        if parts is not None:
            effect_static.append((effect.name, parts[0]))
            effect_params[effect.name], effect_memory[effect.name] = parts[1], parts[2]
    return dataclasses.replace(scene, effects=tuple(effect_static)), effect_params, effect_memory


def build(config: SceneConfig):
    """Assemble the scene. Returns ``(scene, params, state)``; what a run saves comes from
    ``config.run_settings()`` (:class:`~mysim_jax.config.scene.RunSettings`)."""
    effect_config = config
    config = _expanded(config)
    t = _Tables.of(config)
    placed = _place_ropes(t)
    t.resolve_nodes()           # markers are final before node numbers are handed out
    sp = _spring_table(t, placed)
    load_force, load_torque = _loads(t)
    dtype = jnp.float64 if config.sim.precision == "float64" else jnp.float32
    contact_scene = contact_params = None
    if config.contact is not None:
        contact_scene, contact_params = build_contact(
            config.contact, t.point_names, [b.name for b in config.bodies], dtype,
            segments=segment_table(config.ropes, config.springs))
    quad_scene, quad_params, control_params, control_state = build_quadrotors(
        config, [b.name for b in config.bodies], dtype)
    scene = _scene(t, sp, (load_force, load_torque), contact_scene, quad_scene)
    scene, effect_params, effect_memory = _build_effects(effect_config, scene)

    point_mass = np.asarray(t.point_mass, float).reshape(-1)
    body_mass = np.asarray([b.mass for b in config.bodies], float).reshape(-1)
    inertia = np.asarray([_inertia_matrix(b.inertia) for b in config.bodies], float).reshape(-1, 3, 3)
    substeps = _check_stability(config, scene, point_mass, body_mass, inertia, t.marker_pos,
                                np.asarray(sp.column("stiffness"), float), np.asarray(sp.column("damping"), float))
    scene = dataclasses.replace(scene, substeps=substeps)

    def arr(x, shape):
        return jnp.asarray(np.asarray(x, dtype=float).reshape(shape), dtype=scene.dtype)

    params = Params(
        point_mass=arr(point_mass, (-1,)),
        body_mass=arr(body_mass, (-1,)),
        body_inertia=arr(inertia, (-1, 3, 3)),
        marker_pos=arr(t.marker_pos, (-1, 3)),
        marker_quat=arr(t.marker_quat, (-1, 4)),
        anchor_pos=arr([a.pos for a in config.anchors], (-1, 3)),
        anchor_quat=arr([a.quat for a in config.anchors], (-1, 4)),
        spring_stiffness=arr(sp.column("stiffness"), (-1,)),
        spring_damping=arr(sp.column("damping"), (-1,)),
        spring_rest_length=arr(sp.column("rest"), (-1,)),
        gravity=arr(config.gravity, (3,)),
        load_node_force=arr(load_force, (t.n_nodes, 3)),
        load_body_torque=arr(load_torque, (-1, 3)),
        baumgarte_alpha=jnp.asarray(config.baumgarte.alpha, dtype=scene.dtype),
        baumgarte_beta=jnp.asarray(config.baumgarte.beta, dtype=scene.dtype),
        contact=contact_params,
        quadrotor=quad_params,
        controller=control_params,
        effects=effect_params,
    )
    phys = PhysState(
        point_pos=arr(t.point_pos, (-1, 3)),
        point_vel=arr(t.point_vel, (-1, 3)),
        body_pos=arr([b.pos for b in config.bodies], (-1, 3)),
        body_quat=arr([b.quat for b in config.bodies], (-1, 4)),
        body_vel=arr([b.vel for b in config.bodies], (-1, 3)),
        body_angvel=arr([b.angvel for b in config.bodies], (-1, 3)),
    )
    state = State(phys=phys, time=jnp.zeros((), dtype=scene.dtype), controller=control_state, effects=effect_memory)
    if scene.contact is not None and scene.contact.broad_phase is not None:
        state = state.replace(contact=broad_phase_start(scene, params, state))
    for effect, _ in scene_effects(scene):
        state = effect.init(scene, params, state)
    return scene, params, state


def _joint_buckets(config: SceneConfig, body_index, anchor_index, marker_names) -> tuple[JointBucket, ...]:
    """Split joints into connected groups of bodies and stack equal-structure groups."""
    if not config.joints:
        return ()

    def side(ref):
        if ref in anchor_index:
            return None, anchor_index[ref]
        return body_index[ref.split(".")[0]], marker_names.index(ref)

    sides = [(side(j.marker_i), side(j.marker_j)) for j in config.joints]
    groups = joint_groups(len(config.bodies), [[b for b, _ in pair if b is not None] for pair in sides])

    buckets: dict[tuple, list] = {}
    for root, joint_ids in groups.items():
        bodies = sorted({b for ji in joint_ids for b in (sides[ji][0][0], sides[ji][1][0]) if b is not None})
        local = {b: k for k, b in enumerate(bodies)}
        sig = (len(bodies),) + tuple(
            (config.joints[ji].type,
             sides[ji][0][0] is None, sides[ji][1][0] is None,
             -1 if sides[ji][0][0] is None else local[sides[ji][0][0]],
             -1 if sides[ji][1][0] is None else local[sides[ji][1][0]])
            for ji in joint_ids
        )
        frames_i = tuple(sides[ji][0][1] for ji in joint_ids)
        frames_j = tuple(sides[ji][1][1] for ji in joint_ids)
        buckets.setdefault(sig, []).append((tuple(bodies), frames_i, frames_j))

    out = []
    for sig, members in buckets.items():
        joints = sig[1:]
        out.append(JointBucket(
            joint_types=tuple(j[0] for j in joints),
            side_i_is_anchor=tuple(j[1] for j in joints),
            side_j_is_anchor=tuple(j[2] for j in joints),
            side_i_local_body=tuple(j[3] for j in joints),
            side_j_local_body=tuple(j[4] for j in joints),
            group_bodies=tuple(m[0] for m in members),
            group_frame_i=tuple(m[1] for m in members),
            group_frame_j=tuple(m[2] for m in members),
        ))
    return tuple(out)


def _check_stability(config, scene, point_mass, body_mass, inertia, marker_pos, stiffness, damping) -> int:
    """Reject a fixed step above the explicit limit of the stiffest spring, joint or
    contact; resolve ``substeps: auto``. Returns the number of sub-steps to take.

    With ``implicit_euler`` the springs between point masses (and to anchors) are implicit
    and set no limit; springs on body markers, contact and Baumgarte terms are explicit
    (stepped as semi-implicit Euler steps them) and keep theirs."""
    integrator = config.sim.integrator
    auto = config.sim.substeps == "auto"
    if integrator not in FIXED_STEP_INTEGRATORS:
        return 1 if auto else config.sim.substeps
    # compared with a relative tolerance that ``auto`` rounds within, so an auto step passes
    h = config.sim.dt / (1 if auto else config.sim.substeps) / (1.0 + 1e-9)
    n_points, n_markers = scene.n_points, scene.n_markers
    marker_pos = np.asarray(marker_pos, float).reshape(-1, 3)

    def node_name(node):
        if node < n_points:
            return scene.point_names[node]
        if node < n_points + n_markers:
            return scene.marker_names[node - n_points]
        return scene.anchor_names[node - n_points - n_markers]

    problems, limits, auto_steps = [], [], []
    explicit_springs = np.arange(scene.n_springs)
    what_network = "the spring network"
    if integrator == "implicit_euler" and scene.n_springs:
        # springs between point masses (and to anchors) are implicit: no step limit of their
        # own; auto takes IMPLICIT_AUTO_FACTOR times their explicit limit (measured stable)
        explicit_springs = spring_ends_on_markers(scene)
        implicit = np.setdiff1d(np.arange(scene.n_springs), explicit_springs)
        if implicit.shape[0]:
            bound, _ = _network_bound("semi_implicit_euler", scene, implicit, point_mass, body_mass, inertia,
                                      marker_pos, stiffness, damping)
            auto_steps.append(IMPLICIT_AUTO_FACTOR * NETWORK_STEP_SAFETY * bound)
        what_network = "the springs on body markers (explicit with implicit_euler)"
    if explicit_springs.shape[0]:
        bound, worst = _network_bound(integrator, scene, explicit_springs, point_mass, body_mass, inertia,
                                      marker_pos, stiffness, damping)
        limit = NETWORK_STEP_SAFETY * bound
        limits.append(limit)
        auto_steps.append(limit)
        if h > limit:
            problems.append(
                f"{what_network} (its top mode strains spring '{scene.spring_names[worst]}' most: "
                f"k = {stiffness[worst]:.4g} N/m, c = {damping[worst]:.4g} N s/m, joining "
                f"'{node_name(scene.spring_node_a[worst])}' and '{node_name(scene.spring_node_b[worst])}') "
                f"is stable only below "
                f"{limit:.3g} s ({NETWORK_STEP_SAFETY:g} x {bound:.3g} s, its bound over all configurations)"
            )
    if config.joints:
        beta, alpha = config.baumgarte.beta, config.baumgarte.alpha
        limits.append(stable_step(integrator, beta, 2.0 * alpha))
        auto_steps.append(AUTO_SUBSTEP_SAFETY * limits[-1])
        if h > limits[-1]:
            problems.append(
                f"Baumgarte constants (alpha = {alpha:g}, beta = {beta:g} 1/s) are stable only "
                f"below {limits[-1]:.3g} s"
            )
    if scene.contact is not None:
        limit, what = contact_stable_step(integrator, config.contact, scene.contact, point_mass, body_mass)
        limits.append(limit)
        auto_steps.append(AUTO_SUBSTEP_SAFETY * limit)
        if h > limit:
            problems.append(f"{what} is stable only below {limit:.3g} s")
    if auto:
        finite = [x for x in auto_steps if math.isfinite(x)]
        return max(1, math.ceil(config.sim.dt / min(finite) - 1e-9)) if finite else 1
    if problems:
        substeps = math.ceil(config.sim.dt / min(limits))
        which = ("" if integrator != "implicit_euler" else
                 " (implicit_euler takes only the springs between point masses and anchors implicitly; contact, "
                 "joints and springs on body markers stay explicit and keep their limits)")
        raise ConfigError(
            f"sim.dt: step {h:.3g} s (dt = {config.sim.dt:g} / substeps = {config.sim.substeps}) "
            f"exceeds the explicit stability limit of {integrator}{which}: " + "; ".join(problems)
            + f". Use sim.substeps >= {substeps} (or sim.substeps: auto), a smaller dt, or an adaptive "
            "integrator (tsit5, kvaerno5)"
        )
    return config.sim.substeps


def _network_bound(integrator, scene, springs, point_mass, body_mass, inertia, marker_pos, stiffness, damping):
    """:func:`scene_network_stable_step` of the springs with indices ``springs`` only:
    ``(bound, worst)`` with ``worst`` an index into all the scene's springs."""
    springs = np.asarray(springs, dtype=np.int64)
    sub = dataclasses.replace(
        scene, spring_node_a=tuple(scene.spring_node_a[s] for s in springs),
        spring_node_b=tuple(scene.spring_node_b[s] for s in springs),
        spring_names=tuple(scene.spring_names[s] for s in springs),
        spring_tension_only=tuple(scene.spring_tension_only[s] for s in springs))
    bound, worst = scene_network_stable_step(integrator, sub, point_mass, body_mass, inertia, marker_pos,
                                             stiffness[springs], damping[springs])
    return bound, int(springs[worst]) if springs.shape[0] else 0
