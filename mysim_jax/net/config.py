"""The ``net:`` block of a scene file: a square net of rope modules tethered to quadrotors.

A net of ``knots`` x ``knots`` knots (G x G, G >= 2) is a square of side ``size`` [m]
(at rest length). It starts flat and horizontal at ``center`` with its knots ``spread``
times the mesh spacing apart (default 0.8: the lines start slack and the net sags into
a bowl about a quarter of its side deep; a flat net at full size could only carry its
own weight by stretching its lines). Every mesh edge (between
neighbouring knots) is a rope module (:mod:`mysim_jax.net.rope`, paper Fig. rope_model)
with ``masses_per_edge`` lumped masses (0: one segment from knot to knot, the line's
mass lumped on the knots); every tether is a rope module from a knot to a
marker on a UAV body, ``attach`` below the UAV's centre (UAV body frame). By default the
four corner knots are tethered to the quadrotors in the order they are listed.

Mass. A line of ``mass_per_length`` μ [kg/m] is lumped so that every line's whole mass is
in the scene: an edge (or tether) of length ℓ with N interior masses puts μ ℓ / (N + 1)
on each of them and half of that on each of its two ends (a tether's UAV end adds its
half to nothing: it is part of the UAV). A knot carries the halves of the edges and
tethers that meet there plus ``knot_mass`` (the knot itself).

Generated names (usable in ``contact:`` groups and ``output.plot``), with ``P`` the net's
``name``::

    P_k{i}_{j}     knot in row i, column j (i along y, j along x, from the (-x, -y) corner)
    P_h{i}_{j}     rope from knot (i, j) to (i, j + 1); its masses P_h{i}_{j}_0, _1, ...
    P_v{i}_{j}     rope from knot (i, j) to (i + 1, j)
    P_t{n}         tether n (knot -> UAV); the UAV marker is ``<uav>.P_tether``

Line defaults (:data:`NYLON_TWINE`): knotted nylon (PA6) netting twine of 1 mm diameter,
the line of small catch and sports nets. Mass per metre: nylon's 1140 kg/m³ on a 1 mm
twisted cross-section at a packing of about 0.9 gives 0.8 g/m. Axial stiffness: the
low-strain modulus of twisted nylon twine is about 1.5 GPa (the twist lowers the
fibre's 2.5–3 GPa), times 0.785 mm² gives EA ≈ 1200 N. Damping: nylon's loss factor
(tan δ ≈ 0.02–0.1 at low frequency) is modelled as the rope module's tensile damping d;
d = 0.02 N s gives each 12.5 cm segment of the default net about 10 % of critical damping
on its own masses (12.5 cm segments of a 25 cm mesh; the default 20 cm mesh has 10 cm
segments). Tension-only (a line never pushes).

Air drag on the lines (:mod:`mysim_jax.net.drag`): every lumped mass carries the drag of
the line it stands for, ``F = −½ ρ C_d d ℓ |v| v`` (d the diameter, ℓ the lumped
length, C_d = 1.2 for a cylinder in cross-flow). For a net it is not small: 1 mm nylon
line falls at about 3 m/s, and without it a dropped net rings for seconds.

Everything here is NumPy and pydantic: validating a net never imports JAX. The net is
expanded into ordinary points, ropes and markers (:func:`net_elements`), so the builder,
the stability check and the contact lists treat it as any other rope network.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator

from mysim_jax.core.config_base import Name, NonNegFloat, PosFloat, StrictModel, Vec3
from mysim_jax.core.npgeom import rotate

MAX_KNOTS = 64          # per side: 4096 knots, ~8000 edges, far beyond a carried net


class LineConfig(StrictModel):
    """A line (net twine or tether): mass per metre, axial stiffness, tensile damping."""

    mass_per_length: PosFloat = 8.0e-4     # kg/m
    EA: PosFloat = 1200.0                  # N
    damping: NonNegFloat = 0.02            # N s (rope-module d: segment damping d / s̄)
    model: Literal["tension_only", "linear"] = "tension_only"
    diameter: PosFloat = 1.0e-3            # m (air drag)
    drag_coefficient: NonNegFloat = 1.2    # a cylinder in cross-flow (0 turns line drag off)


NYLON_TWINE = LineConfig()


class TetherConfig(StrictModel):
    """Tethers from knots to UAV markers.

    ``uavs`` are quadrotor bodies; ``knots`` the ``[i, j]`` knot of each (default: the
    corners (0, 0), (0, G−1), (G−1, G−1), (G−1, 0), counter-clockwise seen from above).
    """

    uavs: Annotated[list[Name], Field(min_length=1)]
    knots: list[tuple[int, int]] | None = None
    length: PosFloat = 1.0                 # m
    n_masses: Annotated[int, Field(ge=0, le=1000)] = 3
    # m, UAV body frame: 1 cm below the centre. The pull of a tether hung further below
    # the centre of mass tilts the UAV (a 3 cm arm gave the default attitude loop more
    # torque than it could hold while the net swung)
    attach: Vec3 = (0.0, 0.0, -0.01)
    line: LineConfig = NYLON_TWINE


class NetConfig(StrictModel):
    """A square net (module docstring). ``center`` is the net's centre at the start."""

    name: Name = "net"
    knots: Annotated[int, Field(le=MAX_KNOTS)] = 11
    size: PosFloat = 2.0                    # m, side of the square
    center: Vec3
    spread: Annotated[float, Field(gt=0.2, le=1.0)] = 0.8   # start knot spacing / mesh spacing
    masses_per_edge: Annotated[int, Field(ge=0, le=100)] = 1
    knot_mass: NonNegFloat = 0.0            # kg, added to every knot
    line: LineConfig = NYLON_TWINE
    tethers: TetherConfig | None = None
    air_density: NonNegFloat = 1.225        # kg/m^3 (line drag; 0 turns it off)

    @field_validator("knots")
    @classmethod
    def _at_least_two(cls, value):
        if value < 2:
            raise ValueError(f"a net needs at least 2 x 2 knots, got {value}")
        return value

    def knot_name(self, i: int, j: int) -> str:
        return f"{self.name}_k{i}_{j}"

    def edge_chains(self) -> list[list[str]]:
        """Point names along every edge of the net, knot to knot through its lumped masses:
        ``[knot (i, j), masses..., knot (i, j + 1) or (i + 1, j)]``, row edges (``h``) and
        column edges (``v``) in row-major order of their first knot."""
        g = self.knots
        chains = []
        for i in range(g):
            for j in range(g):
                for kind, end in (("h", (i, j + 1)), ("v", (i + 1, j))):
                    if end[0] >= g or end[1] >= g:
                        continue
                    rope = f"{self.name}_{kind}{i}_{j}"
                    chains.append([self.knot_name(i, j)] + [f"{rope}_{m}" for m in range(self.masses_per_edge)]
                                  + [self.knot_name(*end)])
        return chains

    def corner_knots(self) -> list[tuple[int, int]]:
        g = self.knots - 1
        return [(0, 0), (0, g), (g, g), (g, 0)]

    def tether_knots(self) -> list[tuple[int, int]]:
        t = self.tethers
        if t is None:
            return []
        if t.knots is not None:
            return [tuple(k) for k in t.knots]
        return self.corner_knots()[: len(t.uavs)]

    @property
    def spacing(self) -> float:
        """Mesh spacing [m] (edge length)."""
        return self.size / (self.knots - 1)


@dataclass
class NetElements:
    """A net expanded into plain scene entries (dicts in the scene file's schema)."""

    points: list[dict] = field(default_factory=list)
    ropes: list[dict] = field(default_factory=list)
    markers: dict[str, dict] = field(default_factory=dict)     # UAV body name -> marker entry
    drag_area: dict[str, float] = field(default_factory=dict)  # point name -> C_d x diameter x line length [m^2]
    problems: list[str] = field(default_factory=list)


def knot_positions(net: NetConfig) -> np.ndarray:
    """Initial knot positions ``(G, G, 3)``: row i along y, column j along x, ``spread``
    times the mesh spacing apart (flat; ``spread < 1`` leaves the lines slack, so the net
    sags into a bowl instead of starting as a drum)."""
    g = net.knots
    offsets = (np.arange(g) - 0.5 * (g - 1)) * net.spacing * net.spread
    pos = np.zeros((g, g, 3))
    pos[..., 0] = offsets[None, :]
    pos[..., 1] = offsets[:, None]
    return pos + np.asarray(net.center, float)


def net_elements(net: NetConfig, bodies: dict, quadrotor_bodies: set[str]) -> NetElements:
    """Expand ``net`` into points, ropes and UAV markers; ``problems`` lists what is wrong
    (field-named strings). ``bodies`` maps body names to their configs (for the start
    positions of the tethered UAVs)."""
    out = NetElements()
    g, a = net.knots, net.spacing
    n = net.masses_per_edge
    pos = knot_positions(net)
    knot_mass = np.full((g, g), net.knot_mass)
    line = net.line
    edge_share = line.mass_per_length * a / (n + 1)          # each interior mass; half on each end
    edge_area = line.drag_coefficient * line.diameter * a / (n + 1)
    knot_area = np.zeros((g, g))
    for i in range(g):
        for j in range(g):
            if j + 1 < g:
                out.ropes.append(dict(name=f"{net.name}_h{i}_{j}", start=net.knot_name(i, j),
                                      end=net.knot_name(i, j + 1), length=a, n_masses=n, mass=edge_share,
                                      EA=line.EA, damping=line.damping, model=line.model))
                knot_mass[i, j] += 0.5 * edge_share
                knot_mass[i, j + 1] += 0.5 * edge_share
                knot_area[i, j] += 0.5 * edge_area
                knot_area[i, j + 1] += 0.5 * edge_area
                out.drag_area.update({f"{net.name}_h{i}_{j}_{m}": edge_area for m in range(n)})
            if i + 1 < g:
                out.ropes.append(dict(name=f"{net.name}_v{i}_{j}", start=net.knot_name(i, j),
                                      end=net.knot_name(i + 1, j), length=a, n_masses=n, mass=edge_share,
                                      EA=line.EA, damping=line.damping, model=line.model))
                knot_mass[i, j] += 0.5 * edge_share
                knot_mass[i + 1, j] += 0.5 * edge_share
                knot_area[i, j] += 0.5 * edge_area
                knot_area[i + 1, j] += 0.5 * edge_area
                out.drag_area.update({f"{net.name}_v{i}_{j}_{m}": edge_area for m in range(n)})

    t = net.tethers
    if t is not None:
        knots = net.tether_knots()
        if t.knots is not None and len(t.knots) != len(t.uavs):
            out.problems.append(f"net.tethers.knots: {len(t.knots)} knots for {len(t.uavs)} uavs "
                                "(one knot per tethered UAV)")
        elif t.knots is None and len(t.uavs) > 4:
            out.problems.append(f"net.tethers.knots: {len(t.uavs)} uavs but only 4 corners; list the knots")
        seen: dict[str, int] = {}
        share = t.line.mass_per_length * t.length / (t.n_masses + 1)
        for k, (uav, (i, j)) in enumerate(zip(t.uavs, knots)):
            where = f"net.tethers.uavs.{k}"
            if uav not in quadrotor_bodies:
                known = ", ".join(sorted(quadrotor_bodies)) or "none"
                out.problems.append(f"{where}: '{uav}' is not a quadrotor body (quadrotor bodies: {known})")
                continue
            if uav in seen:
                out.problems.append(f"{where}: '{uav}' already has tether {seen[uav]}")
                continue
            seen[uav] = k
            if not (0 <= i < g and 0 <= j < g):
                out.problems.append(f"net.tethers.knots.{k}: knot [{i}, {j}] is outside the {g} x {g} net")
                continue
            marker = f"{net.name}_tether"
            out.markers[uav] = dict(name=marker, pos=tuple(t.attach))
            body = bodies[uav]
            end = np.asarray(body.pos, float) + rotate(body.quat, t.attach)
            span = float(np.linalg.norm(end - pos[i, j]))
            if span > t.length * (1.0 + 1e-3):
                out.problems.append(
                    f"{where}: tether {k} would start stretched: its UAV's marker is {span:.4g} m from knot "
                    f"[{i}, {j}], the tether is {t.length:g} m long (move the UAV closer or lengthen "
                    "net.tethers.length)")
            out.ropes.append(dict(name=f"{net.name}_t{k}", start=net.knot_name(i, j), end=f"{uav}.{marker}",
                                  length=t.length, n_masses=t.n_masses, mass=share, EA=t.line.EA,
                                  damping=t.line.damping, model=t.line.model))
            knot_mass[i, j] += 0.5 * share
            area = t.line.drag_coefficient * t.line.diameter * t.length / (t.n_masses + 1)
            knot_area[i, j] += 0.5 * area
            out.drag_area.update({f"{net.name}_t{k}_{m}": area for m in range(t.n_masses)})
    for i in range(g):
        for j in range(g):
            out.points.append(dict(name=net.knot_name(i, j), mass=float(knot_mass[i, j]), pos=tuple(pos[i, j])))
            out.drag_area[net.knot_name(i, j)] = float(knot_area[i, j])
    return out


