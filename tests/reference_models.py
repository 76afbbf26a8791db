"""Independent reference models for the tests: plain NumPy right-hand sides built straight
from a scene config (not from mysim_jax.build), integrated with SciPy.

They re-derive the rope discretisation of paper Sec. 2.1 from the config fields on their
own, so a mistake in the library's topology, constants or force law shows up as a
mismatch rather than being reproduced.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp


class RopeNetReference:
    """Point masses, anchors and lumped-mass ropes (linear or tension-only segments)."""

    def __init__(self, config):
        self.names, masses, pos = [], [], []
        where = {}
        for p in config.points:
            where[p.name] = ("dof", len(self.names))
            self.names.append(p.name)
            masses.append(p.mass)
            pos.append(p.pos)
        anchors = {a.name: np.asarray(a.pos, float) for a in config.anchors}
        segs = []  # (end_a, end_b, rest, k, c, tension_only) with ends ("dof", i) | ("fix", xyz)
        for r in config.ropes:
            n = r.n_masses
            s_bar = r.length / n
            rest = [s_bar / 2] + [s_bar] * (n - 1) + [s_bar / 2]
            start = self._pos(r.start, where, pos, anchors)
            end = self._pos(r.end, where, pos, anchors)
            chain = [self._end(r.start, where, anchors)]
            travelled = 0.0
            for j in range(n):
                travelled += rest[j]
                where[f"{r.name}_{j}"] = ("dof", len(self.names))
                chain.append(("dof", len(self.names)))
                self.names.append(f"{r.name}_{j}")
                masses.append(r.mass)
                pos.append(start + (end - start) * travelled / r.length)
            chain.append(self._end(r.end, where, anchors))
            for j in range(n + 1):
                segs.append((chain[j], chain[j + 1], rest[j], r.EA / rest[j], r.damping / rest[j],
                             r.model == "tension_only"))
        self.mass = np.asarray(masses, float)
        self.x0 = np.asarray(pos, float)
        self.segs = segs
        self.g = np.asarray(config.gravity, float)

    @staticmethod
    def _pos(ref, where, pos, anchors):
        if ref in anchors:
            return anchors[ref]
        return np.asarray(pos[where[ref][1]], float)

    @staticmethod
    def _end(ref, where, anchors):
        return ("fix", anchors[ref]) if ref in anchors else where[ref]

    def _segment_arrays(self):
        """Vectorised form of the segment list: ends as rows of the DOF positions padded
        with one zero row (fixed ends add their point), and the incidence matrix that sums
        segment forces onto the DOFs (+ at end a, - at end b)."""
        if not hasattr(self, "_arrays"):
            n = len(self.mass)
            idx_a = np.array([a[1] if a[0] == "dof" else n for a, *_ in self.segs])
            idx_b = np.array([b[1] if b[0] == "dof" else n for _, b, *_ in self.segs])
            fix_a = np.array([np.zeros(3) if a[0] == "dof" else a[1] for a, *_ in self.segs])
            fix_b = np.array([np.zeros(3) if b[0] == "dof" else b[1] for _, b, *_ in self.segs])
            rest, k, c, tonly = (np.array([s[i] for s in self.segs]) for i in (2, 3, 4, 5))
            incidence = np.zeros((n + 1, len(self.segs)))
            incidence[idx_a, np.arange(len(self.segs))] += 1.0
            incidence[idx_b, np.arange(len(self.segs))] -= 1.0
            self._arrays = (idx_a, idx_b, fix_a, fix_b, rest, k, c, tonly.astype(bool), incidence[:n])
        return self._arrays

    def accelerations(self, x, v):
        n = len(self.mass)
        idx_a, idx_b, fix_a, fix_b, rest, k, c, tonly, incidence = self._segment_arrays()
        # row n is a sink for fixed ends: position zero plus the fixed point, velocity zero
        xp = np.zeros((n + 1, 3))
        vp = np.zeros((n + 1, 3))
        xp[:n], vp[:n] = x, v
        d = (xp[idx_b] + fix_b) - (xp[idx_a] + fix_a)
        s = np.sqrt(np.einsum("ij,ij->i", d, d))
        u = d / s[:, None]
        t = k * (s - rest) + c * np.einsum("ij,ij->i", vp[idx_b] - vp[idx_a], u)
        t = np.where(tonly, np.where(s > rest, np.maximum(t, 0.0), 0.0), t)
        return (incidence @ (t[:, None] * u)) / self.mass[:, None] + self.g

    def solve(self, t_end, t_eval, rtol=1e-10, atol=1e-12):
        n = len(self.mass)

        def rhs(_, y):
            x, v = y[: 3 * n].reshape(n, 3), y[3 * n:].reshape(n, 3)
            return np.concatenate([v.ravel(), self.accelerations(x, v).ravel()])

        y0 = np.concatenate([self.x0.ravel(), np.zeros(3 * n)])
        sol = solve_ivp(rhs, (0.0, t_end), y0, method="DOP853", t_eval=t_eval, rtol=rtol, atol=atol)
        assert sol.success, sol.message
        return sol.y[: 3 * n].T.reshape(-1, n, 3)
