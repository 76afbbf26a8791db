"""Independent reference for the contact scenes: plain NumPy, built from the config
fields (not from mysim_jax.build or mysim_jax.contact), integrated by SciPy.

It extends the rope-net reference of tests/reference_models.py with the paper's normal
contact law between point-mass spheres, re-derived here from Eq. compact_force:
penetration ``δ = r_i + r_j − |x_j − x_i|``, force ``max(0, k δⁿ + STEP(δ; 0, 0, p, c) dδ/dt)``
for δ > 0 along the line of centres; optionally the C¹ friction law (point masses only).
Groups and patterns are resolved with ``fnmatch`` on the reference's own name list.
"""

from __future__ import annotations

import fnmatch

import numpy as np
from scipy.integrate import solve_ivp

from reference_models import RopeNetReference


def _step(x, x0, h0, x1, h1):
    s = np.clip((x - x0) / (x1 - x0), 0.0, 1.0)
    return h0 + (h1 - h0) * s * s * (3.0 - 2.0 * s)


class CollisionNetReference(RopeNetReference):
    """Rope net + point-mass spheres in penalty contact (no rigid bodies, no ground)."""

    def __init__(self, config, friction: bool | None = None):
        super().__init__(config)
        c = config.contact
        assert not config.bodies, "the reference handles point-mass spheres only"
        members = {}
        radius = {}
        for g in c.groups:
            names = [n for n in self.names if any(fnmatch.fnmatchcase(n, pat) for pat in g.members)]
            members[g.name] = names
            for n in names:
                radius[n] = g.radius
        pairs = set()
        for ga, gb in c.pairs:
            assert "ground" not in (ga, gb)
            for a in members[ga]:
                for b in members[gb]:
                    if a != b:
                        ia, ib = self.names.index(a), self.names.index(b)
                        pairs.add((min(ia, ib), max(ia, ib)))
        pairs = sorted(pairs)
        self.pi = np.array([p[0] for p in pairs])
        self.pj = np.array([p[1] for p in pairs])
        self.rsum = np.array([radius[self.names[i]] + radius[self.names[j]] for i, j in pairs])
        self.k, self.n_exp, self.c, self.p = c.stiffness, c.exponent, c.damping, c.damping_depth
        use_friction = c.friction is not None if friction is None else friction
        self.friction = c.friction if use_friction else None

    def contact_forces(self, x, v):
        d = x[self.pj] - x[self.pi]
        dist = np.linalg.norm(d, axis=1)
        n = d / np.where(dist > 0, dist, 1.0)[:, None]
        depth = self.rsum - dist
        dv = v[self.pj] - v[self.pi]
        rate = -np.sum(dv * n, axis=1)
        pen = np.maximum(depth, 0.0)
        f = np.maximum(self.k * pen ** self.n_exp + _step(pen, 0.0, 0.0, self.p, self.c) * rate, 0.0)
        f = np.where(depth > 0, f, 0.0)
        force_j = f[:, None] * n
        if self.friction is not None:
            fr = self.friction
            slip = dv - np.sum(dv * n, axis=1)[:, None] * n
            speed = np.linalg.norm(slip, axis=1)
            x_s = speed / fr.v_static
            mu = np.where(speed < fr.v_static, 0.5 * fr.mu_static * x_s * (3 - x_s ** 2),
                          _step(speed, fr.v_static, fr.mu_static, fr.v_dynamic, fr.mu_dynamic))
            unit = slip / np.where(speed > 0, speed, 1.0)[:, None]
            force_j = force_j - (mu * f)[:, None] * unit
        out = np.zeros_like(x)
        np.add.at(out, self.pj, force_j)
        np.add.at(out, self.pi, -force_j)
        return out

    def accelerations(self, x, v):
        return super().accelerations(x, v) + self.contact_forces(x, v) / self.mass[:, None]

    def solve(self, t_end, t_eval, rtol=1e-10, atol=1e-12, x0=None, v0=None, with_velocity=False):
        n = len(self.mass)
        x0 = self.x0 if x0 is None else x0
        v0 = np.zeros_like(self.x0) if v0 is None else v0

        def rhs(_, y):
            x, v = y[: 3 * n].reshape(n, 3), y[3 * n:].reshape(n, 3)
            return np.concatenate([v.ravel(), self.accelerations(x, v).ravel()])

        y0 = np.concatenate([np.asarray(x0, float).ravel(), np.asarray(v0, float).ravel()])
        sol = solve_ivp(rhs, (0.0, t_end), y0, method="DOP853", t_eval=t_eval, rtol=rtol, atol=atol)
        assert sol.success, sol.message
        pos = sol.y[: 3 * n].T.reshape(-1, n, 3)
        if with_velocity:
            return pos, sol.y[3 * n:].T.reshape(-1, n, 3), sol
        return pos

    def jax_accelerations(self):
        """The same right-hand side written with ``jax.numpy`` (dense incidence matrices
        instead of ``np.add.at``), for fast tight-tolerance solves with diffrax."""
        import jax.numpy as jnp

        n = len(self.mass)
        idx_a, idx_b, fix_a, fix_b, rest, k, c, tonly, _ = self._segment_arrays()
        seg_in = np.zeros((n + 1, len(rest)))
        seg_in[idx_a, np.arange(len(rest))] += 1.0
        seg_in[idx_b, np.arange(len(rest))] -= 1.0
        pair_in = np.zeros((n, len(self.pi)))
        pair_in[self.pj, np.arange(len(self.pi))] += 1.0
        pair_in[self.pi, np.arange(len(self.pi))] -= 1.0
        fixed_a, fixed_b = (idx_a == n)[:, None], (idx_b == n)[:, None]
        kk, nn, cc, pp, rsum = self.k, self.n_exp, self.c, self.p, self.rsum
        assert self.friction is None, "the jax reference is frictionless"

        def acc(x, v):
            xp = jnp.concatenate([x, jnp.zeros((1, 3), x.dtype)])
            vp = jnp.concatenate([v, jnp.zeros((1, 3), v.dtype)])
            d = jnp.where(fixed_b, fix_b, xp[idx_b]) - jnp.where(fixed_a, fix_a, xp[idx_a])
            s = jnp.sqrt(jnp.sum(d * d, axis=1))
            u = d / s[:, None]
            t = k * (s - rest) + c * jnp.sum((vp[idx_b] - vp[idx_a]) * u, axis=1)
            t = jnp.where(tonly, jnp.where(s > rest, jnp.maximum(t, 0.0), 0.0), t)
            f = (seg_in @ (t[:, None] * u))[:n]
            dc = x[self.pj] - x[self.pi]
            dist = jnp.sqrt(jnp.sum(dc * dc, axis=1))
            nc = dc / dist[:, None]
            depth = rsum - dist
            rate = -jnp.sum((v[self.pj] - v[self.pi]) * nc, axis=1)
            pen = jnp.maximum(depth, 0.0)
            ramp = jnp.clip(pen / pp, 0.0, 1.0)
            fn = jnp.maximum(kk * pen ** nn + cc * ramp * ramp * (3.0 - 2.0 * ramp) * rate, 0.0)
            fn = jnp.where(depth > 0.0, fn, 0.0)
            f = f + pair_in @ (fn[:, None] * nc)
            return f / self.mass[:, None] + self.g

        return acc

    def solve_diffrax(self, t_eval, rtol=1e-12, atol=1e-14, max_steps=2_000_000):
        """Positions ``(n_out, n, 3)`` at ``t_eval`` from diffrax's 8th-order Dopri8 (a
        different method from the library's default tsit5), float64."""
        import diffrax
        import jax
        import jax.numpy as jnp

        acc = self.jax_accelerations()
        n = len(self.mass)

        def field(t, y, args):
            return (y[1], acc(y[0], y[1]))

        ts = jnp.asarray(t_eval, dtype=jnp.float64)
        y0 = (jnp.asarray(self.x0, jnp.float64), jnp.zeros((n, 3), jnp.float64))

        @jax.jit
        def run(y0):
            sol = diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Dopri8(), ts[0], ts[-1], 1e-4, y0,
                                      saveat=diffrax.SaveAt(ts=ts), max_steps=max_steps,
                                      stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol))
            return sol.ys[0]

        return np.asarray(run(y0))
