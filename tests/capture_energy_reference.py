"""Independent NumPy energy book-keeping of a capture scene (net + tethers + quadrotors + target).

Used by ``tests/test_capture_energy.py``. Nothing here calls the package's force, energy,
marker, contact or quadrotor functions: every law is re-implemented from the documented
physics, and the constants that are the package's own derivations (the lumping of the
net's mass and line drag, the target's drag constant, the rotor layout) are recomputed
from the scene file's values. From the built scene only the static topology is read
(names, spring end nodes, which body a marker sits on) and from the Params the spring
constants and marker offsets (the lumped point masses are recomputed and compared with the
Params by the test; body masses and inertias come from the scene file).

For a stack of states (leaves with a leading time axis) :meth:`EnergyModel.evaluate`
returns, per state:

* ``kinetic``: Σ ½ m |v|² of points and bodies + Σ ½ ωᵀ I ω (body frame);
* ``potential``: −Σ m g·x;
* ``spring``: Σ ½ k (s − s̄)² over taut tension-only springs (all linear springs);
* ``contact``: Σ k δⁿ⁺¹/(n + 1) over touching sphere–capsule and sphere–sphere pairs;
* dissipated powers (≥ 0): ``spring_damping``, ``contact_damping`` (normal damper and
  friction), ``line_drag`` Σ c_i |v_i|³, ``target_drag`` ½ ρ C_d π r² |v|³;
* input powers: ``thrust`` (F·v of the rotor thrust at the CoM) and ``rotor_torque``
  (τ·ω of the arm torques and reaction torques, body frame).

Dissipation of an element with elastic energy E_el and force power P (the power its forces
do on the objects it joins) is ``D = −P − dE_el/dt``, evaluated pointwise:

* tension-only spring, taut (s > s̄): applied tension f = max(k(s − s̄) + c ṡ, 0), power
  −f ṡ, so D = (f − k(s − s̄)) ṡ: c ṡ² while f > 0, and −k(s − s̄) ṡ > 0 while the clip is
  active (which needs ṡ < −k(s − s̄)/c < 0); slack: D = 0.
* contact, δ > 0: normal force f = max(k δⁿ + STEP(δ; 0, 0, p, c) δ̇, 0) and friction
  F_t = −μ(|u|) f u/|u| (u the tangential slip of the sphere's contact point relative to the
  other object's contact point): power −f δ̇ + F_t·u, D = (f − k δⁿ) δ̇ + f μ(|u|) |u|.
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass

import numpy as np

# --- small NumPy kinematics -------------------------------------------------------------


def rotate(q, v):
    """Rotate ``v`` (..., 3) by unit quaternions ``q`` (..., 4) wxyz (body -> world)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def hermite_step(x, x0, h0, x1, h1):
    s = np.clip((x - x0) / (x1 - x0), 0.0, 1.0)
    return h0 + (h1 - h0) * s * s * (3.0 - 2.0 * s)


def friction_mu(speed, mu_s, mu_d, v_s, v_d):
    """|μ| at slip speed ``speed`` (C¹ Stribeck-like curve of the contact docs)."""
    x = speed / v_s
    return np.where(speed < v_s, 0.5 * mu_s * x * (3.0 - x * x), hermite_step(speed, v_s, mu_s, v_d, mu_d))


# --- lumped masses and line drag of a net, from the config --------------------------------


def net_lumping(net, point_names):
    """``(mass, drag_constant)`` ``(n_points,)`` of every point, recomputed from the
    ``net:`` config by the documented lumping: a line of length ℓ with N interior masses
    gives each of them μ ℓ/(N + 1) and line length ℓ/(N + 1), and half of that to each
    end knot (a tether's UAV end: to nothing); drag constant ½ ρ C_d d ℓ_lumped.
    Points that are not the net's get zeros."""
    g = net.knots
    a = net.size / (g - 1)
    p = re.escape(net.name)
    edge_n = net.masses_per_edge
    tet = net.tethers
    tether_knots = {}
    if tet is not None:
        knots = tet.knots if tet.knots is not None else [(0, 0), (0, g - 1), (g - 1, g - 1), (g - 1, 0)]
        tether_knots = {k: tuple(knots[k]) for k in range(len(tet.uavs))}
    mass = np.zeros(len(point_names))
    drag = np.zeros(len(point_names))

    def edge_share(line, length, n):
        piece = length / (n + 1)
        return line.mass_per_length * piece, 0.5 * net.air_density * line.drag_coefficient * line.diameter * piece

    for idx, name in enumerate(point_names):
        if re.fullmatch(rf"{p}_[hv](\d+)_(\d+)_(\d+)", name):
            mass[idx], drag[idx] = edge_share(net.line, a, edge_n)
        elif re.fullmatch(rf"{p}_t(\d+)_(\d+)", name):
            mass[idx], drag[idx] = edge_share(tet.line, tet.length, tet.n_masses)
        elif m := re.fullmatch(rf"{p}_k(\d+)_(\d+)", name):
            i, j = int(m.group(1)), int(m.group(2))
            degree = (i > 0) + (i < g - 1) + (j > 0) + (j < g - 1)
            em, ed = edge_share(net.line, a, edge_n)
            mass[idx], drag[idx] = net.knot_mass + 0.5 * degree * em, 0.5 * degree * ed
            for knot in tether_knots.values():
                if knot == (i, j):
                    tm, td = edge_share(tet.line, tet.length, tet.n_masses)
                    mass[idx] += 0.5 * tm
                    drag[idx] += 0.5 * td
    return mass, drag


# --- the model --------------------------------------------------------------------------


@dataclass
class Contact:
    """Sphere–capsule and sphere–sphere pairs of one sphere (the target body) and its law."""

    body: int                 # the sphere's body index
    radius: float
    capsule_a: np.ndarray     # (n_caps,) node index of end a
    capsule_b: np.ndarray
    capsule_radius: float
    sphere_points: np.ndarray  # (n_sph,) point indices of the other spheres
    sphere_radius: float
    k: float
    n: float
    c: float
    p: float
    mu_s: float
    mu_d: float
    v_s: float
    v_d: float


class EnergyModel:
    """Energies and powers of a capture scene built from ``config`` (a SceneConfig).

    ``motor_speed`` ``(n_quads, 4)`` rad/s: the constant motor commands (no motor lag, not
    clipped: the test checks they lie inside [ω_min, ω_max]).

    Contact is counted for the target only: against the capsules of the ``segments``
    group paired with it and, if ``sphere_pair_group`` names a ``members`` group of point
    masses paired with it, against those spheres. Other pairs (ground, UAVs) are not
    modelled: the test checks that they never touch.
    """

    def __init__(self, config, scene, params, motor_speed, sphere_pair_group=None):
        self.scene = scene
        pn, bn = list(scene.point_names), list(scene.body_names)
        self.n_points, self.n_markers = len(pn), len(scene.marker_names)
        self.gravity = np.asarray(config.gravity, float)

        # masses: net lumping from the config; bodies from the config
        self.point_mass, self.line_drag = net_lumping(config.net, pn)
        tgt = config.target
        bodies = {b.name: b for b in config.bodies}
        self.body_mass = np.array([tgt.mass if n == tgt.name else bodies[n].mass for n in bn])
        inertia = [tgt.inertia if n == tgt.name else bodies[n].inertia for n in bn]
        self.body_inertia = np.array([np.diag(i) if np.ndim(i) == 1 else np.asarray(i, float) for i in inertia])
        self.target = bn.index(tgt.name)
        self.target_drag = 0.5 * tgt.air_density * tgt.drag_coefficient * np.pi * tgt.radius ** 2

        # markers and springs
        self.marker_body = np.asarray(scene.marker_body, int)
        self.marker_pos = np.asarray(params.marker_pos, float)
        self.spring_a = np.asarray(scene.spring_node_a, int)
        self.spring_b = np.asarray(scene.spring_node_b, int)
        self.spring_k = np.asarray(params.spring_stiffness, float)
        self.spring_c = np.asarray(params.spring_damping, float)
        self.spring_rest = np.asarray(params.spring_rest_length, float)
        self.tension_only = np.asarray(scene.spring_tension_only, bool)
        if scene.anchor_names:
            raise ValueError("this reference covers scenes without anchors (the capture scene has none); "
                             f"got anchors {list(scene.anchor_names)}")

        # rotors (body frame, from the config's rotor values)
        self.quad_body = np.array([bn.index(q.body) for q in config.quadrotors])
        self.rotor_pos, self.lift, self.torque_coef, self.spin = [], [], [], []
        for q in config.quadrotors:
            r = q.rotors
            arm, ang = np.asarray(r.arm_length, float), np.asarray(r.angle, float)
            self.rotor_pos.append(np.stack([arm * np.sin(ang), arm * np.cos(ang), 0.0 * arm], -1))
            self.lift.append(np.asarray(r.lift_coefficient, float))
            self.torque_coef.append(np.asarray(r.torque_coefficient, float))
            self.spin.append(np.asarray(r.spin, float))
        self.rotor_pos, self.lift = np.asarray(self.rotor_pos), np.asarray(self.lift)
        self.torque_coef, self.spin = np.asarray(self.torque_coef), np.asarray(self.spin)
        w2 = np.asarray(motor_speed, float) ** 2
        thrust = self.lift * w2                                     # (q, 4) N along body z
        self.thrust = thrust.sum(-1)                                # (q,)
        fz = np.zeros(thrust.shape + (3,))
        fz[..., 2] = thrust
        self.rotor_torque = np.cross(self.rotor_pos, fz).sum(-2)    # arm torques
        self.rotor_torque[:, 2] += (self.spin * self.torque_coef * w2).sum(-1)

        self.contact = self._contact(config, pn, sphere_pair_group) if config.contact is not None else None

    def _contact(self, config, pn, sphere_pair_group):
        cc = config.contact
        groups = {g.name: g for g in cc.groups}
        tgt = config.target.name
        tgroup = next(g for g in cc.groups if g.members == [tgt])
        seg_groups = [g for g in cc.groups if g.segments is not None]
        assert len(seg_groups) == 1
        seg = seg_groups[0]
        names = self.scene.spring_names
        caps = [i for i, s in enumerate(names)
                if any(fnmatch.fnmatchcase(s.split("[")[0], pat) for pat in seg.segments)]
        # a sphere never touches a segment attached to its own body's markers
        node_body = lambda nd: (self.marker_body[nd - self.n_points] if nd >= self.n_points else -1)
        caps = [i for i in caps if self.target not in (node_body(self.spring_a[i]), node_body(self.spring_b[i]))]
        pairs = [tuple(p) for p in cc.pairs]
        assert (tgroup.name, seg.name) in pairs or (seg.name, tgroup.name) in pairs
        sph_points, sph_radius = np.zeros(0, int), 0.0
        if sphere_pair_group is not None:
            assert (tgroup.name, sphere_pair_group) in pairs or (sphere_pair_group, tgroup.name) in pairs
            g = groups[sphere_pair_group]
            sph_points = np.array([i for i, n in enumerate(pn) if any(fnmatch.fnmatchcase(n, m) for m in g.members)])
            sph_radius = g.radius
        f = cc.friction          # None: frictionless (μ = 0)
        return Contact(body=self.target, radius=tgroup.radius, capsule_a=self.spring_a[caps],
                       capsule_b=self.spring_b[caps], capsule_radius=seg.radius, sphere_points=sph_points,
                       sphere_radius=sph_radius, k=cc.stiffness, n=cc.exponent, c=cc.damping, p=cc.damping_depth,
                       mu_s=f.mu_static if f else 0.0, mu_d=f.mu_dynamic if f else 0.0,
                       v_s=f.v_static if f else 1.0, v_d=f.v_dynamic if f else 2.0)

    # ------------------------------------------------------------------------------------

    def nodes(self, phys):
        """Node positions and velocities ``(T, n_nodes, 3)``: points, then markers."""
        bq, bx, bv = phys["body_quat"], phys["body_pos"], phys["body_vel"]
        omega_w = rotate(bq, phys["body_angvel"])                        # (T, nb, 3)
        mb = self.marker_body
        r = rotate(bq[:, mb], np.broadcast_to(self.marker_pos, bq[:, mb].shape[:-1] + (3,)))
        mpos = bx[:, mb] + r
        mvel = bv[:, mb] + np.cross(omega_w[:, mb], r)
        return (np.concatenate([phys["point_pos"], mpos], 1), np.concatenate([phys["point_vel"], mvel], 1),
                omega_w)

    def _contact_terms(self, phys, node_pos, node_vel, omega_w):
        """``(elastic energy (T,), dissipated power (T,), deepest penetration (T,))``."""
        c = self.contact
        n_t = node_pos.shape[0]
        x = phys["body_pos"][:, c.body][:, None]                 # (T, 1, 3) the sphere's centre
        # sphere–capsule: closest segment point p = a + s (b − a), s in [0, 1], moving at
        # (1 − s) v_a + s v_b; sphere–sphere: the other sphere's centre
        a, b = node_pos[:, c.capsule_a], node_pos[:, c.capsule_b]
        ab = b - a
        s = np.clip(np.einsum("tki,tki->tk", x - a, ab) / np.einsum("tki,tki->tk", ab, ab), 0.0, 1.0)
        families = [(a + s[..., None] * ab, c.capsule_radius, s)]
        if len(c.sphere_points):
            families.append((phys["point_pos"][:, c.sphere_points], c.sphere_radius, None))
        energy, diss, depth_max = np.zeros(n_t), np.zeros(n_t), np.full(n_t, -np.inf)
        for k, (other, r_other, s_k) in enumerate(families):
            depth = c.radius + r_other - np.linalg.norm(x - other, axis=-1)        # (T, K)
            depth_max = np.maximum(depth_max, depth.max(-1))
            t, j = np.nonzero(depth > 0.0)                                          # touching pairs only
            if not len(t):
                continue
            pen = depth[t, j]
            d = x[t, 0] - other[t, j]
            n = d / np.linalg.norm(d, axis=-1, keepdims=True)                       # from the other to the sphere
            if s_k is None:
                v_other = phys["point_vel"][t, c.sphere_points[j]]
            else:
                sj = s_k[t, j][:, None]
                v_other = (1.0 - sj) * node_vel[t, c.capsule_a[j]] + sj * node_vel[t, c.capsule_b[j]]
            lever = -(c.radius - 0.5 * pen)[:, None] * n                           # centre -> contact point
            v_rel = phys["body_vel"][t, c.body] + np.cross(omega_w[t, c.body], lever) - v_other
            rate = -np.einsum("ki,ki->k", v_rel, n)                                 # dδ/dt (ω × lever ⟂ n)
            elastic_force = c.k * pen ** c.n
            f = np.maximum(elastic_force + hermite_step(pen, 0.0, 0.0, c.p, c.c) * rate, 0.0)
            u = np.linalg.norm(v_rel + rate[:, None] * n, axis=-1)                  # tangential slip speed
            mu = friction_mu(u, c.mu_s, c.mu_d, c.v_s, c.v_d)
            energy += np.bincount(t, c.k * pen ** (c.n + 1.0) / (c.n + 1.0), minlength=n_t)
            diss += np.bincount(t, (f - elastic_force) * rate + f * mu * u, minlength=n_t)
        return energy, diss, depth_max

    def evaluate(self, phys):
        """Energies and powers (dict of ``(T,)`` arrays) of stacked states ``phys`` (a dict
        or object with ``point_pos``, ``point_vel``, ``body_pos``, ``body_quat``,
        ``body_vel``, ``body_angvel`` leaves ``(T, ...)``)."""
        if not isinstance(phys, dict):
            phys = {k: np.asarray(getattr(phys, k), float) for k in
                    ("point_pos", "point_vel", "body_pos", "body_quat", "body_vel", "body_angvel")}
        pv, bv, wb = phys["point_vel"], phys["body_vel"], phys["body_angvel"]
        out = {}
        out["kinetic"] = (0.5 * (self.point_mass * (pv ** 2).sum(-1)).sum(-1)
                          + 0.5 * (self.body_mass * (bv ** 2).sum(-1)).sum(-1)
                          + 0.5 * np.einsum("tbi,bij,tbj->t", wb, self.body_inertia, wb))
        out["potential"] = -((self.point_mass * (phys["point_pos"] @ self.gravity)).sum(-1)
                             + (self.body_mass * (phys["body_pos"] @ self.gravity)).sum(-1))

        node_pos, node_vel, omega_w = self.nodes(phys)
        dx = node_pos[:, self.spring_b] - node_pos[:, self.spring_a]
        dv = node_vel[:, self.spring_b] - node_vel[:, self.spring_a]
        s = np.linalg.norm(dx, axis=-1)
        rate = np.einsum("tki,tki->tk", dv, dx) / s
        stretch = s - self.spring_rest
        elastic_force = self.spring_k * stretch
        f_lin = elastic_force + self.spring_c * rate
        taut = stretch > 0.0
        f = np.where(self.tension_only, np.where(taut, np.maximum(f_lin, 0.0), 0.0), f_lin)
        counted = np.where(self.tension_only, taut, True)
        out["spring"] = (0.5 * self.spring_k * stretch ** 2 * counted).sum(-1)
        out["spring_damping"] = ((f - elastic_force * counted) * rate).sum(-1)
        out["spring_clipped"] = (self.tension_only & taut & (f_lin < 0.0)).sum(-1)

        out["line_drag"] = (self.line_drag * np.linalg.norm(pv, axis=-1) ** 3).sum(-1)
        out["target_drag"] = self.target_drag * np.linalg.norm(bv[:, self.target], axis=-1) ** 3

        qb = self.quad_body
        ez = np.zeros(phys["body_quat"][:, qb].shape[:-1] + (3,))
        ez[..., 2] = 1.0
        thrust_w = self.thrust[:, None] * rotate(phys["body_quat"][:, qb], ez)
        out["thrust"] = np.einsum("tqi,tqi->t", thrust_w, bv[:, qb])
        out["rotor_torque"] = np.einsum("qi,tqi->t", self.rotor_torque, wb[:, qb])

        if self.contact is not None:
            out["contact"], out["contact_damping"], out["contact_depth"] = self._contact_terms(
                phys, node_pos, node_vel, omega_w)
        else:
            zero = np.zeros(pv.shape[0])
            out["contact"], out["contact_damping"], out["contact_depth"] = zero, zero, zero - np.inf
        out["energy"] = out["kinetic"] + out["potential"] + out["spring"] + out["contact"]
        out["dissipation"] = out["spring_damping"] + out["contact_damping"] + out["line_drag"] + out["target_drag"]
        out["input"] = out["thrust"] + out["rotor_torque"]
        return out


def cumulative_trapezoid(y, h):
    """∫ y dt from the first sample, trapezoid rule on a uniform grid of spacing ``h``."""
    return np.concatenate([[0.0], np.cumsum(0.5 * h * (y[1:] + y[:-1]))])


def simpson_at_even(y, h):
    """Composite Simpson ∫ y dt at the even samples 0, 2, 4, ... (uniform spacing ``h``)."""
    pieces = h / 3.0 * (y[0:-2:2] + 4.0 * y[1:-1:2] + y[2::2])
    return np.concatenate([[0.0], np.cumsum(pieces)])
