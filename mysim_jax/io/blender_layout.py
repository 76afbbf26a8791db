"""What a trajectory CSV holds, for the Blender importer: its columns, its objects and
lines, and the rows to keyframe; no Blender needed.

This file imports nothing beyond Python's standard library and NumPy (Blender runs its
sibling :mod:`mysim_jax.io.blender_import` as a script and imports this file from beside it).

* :func:`read_columns` reads the CSV (:mod:`mysim_jax.io.trajectory` writes it).
* :func:`scene_layout` splits its objects into rigid bodies (``NAME_x/y/z`` and
  ``NAME_qw/qx/qy/qz`` columns) and free point masses, and guesses the lines (net, tethers,
  ropes) from the names mysim_jax gives the masses (:mod:`mysim_jax.net.config`): net knots
  ``P_k{i}_{j}`` are joined through the masses of ropes ``P_h{i}_{j}`` and ``P_v{i}_{j}``;
  other masses named ``R_0 .. R_{n-1}`` form a chain, whose ends join the nearest free
  point, knot or body beyond them (within 1.5 mass spacings, ``ATTACH_SPACINGS``, at the
  first row). A rope ending at a fixed anchor (anchors are not in the CSV) is drawn up to its
  last mass. Lines given by the caller replace the guess.
* :func:`keyed_rows` picks the row nearest to each frame's time, and
  :func:`continuous_quaternions` makes the quaternions' signs continuous from row to row.
"""

from __future__ import annotations

import csv
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["BlenderImportError", "Layout", "read_columns", "check_time", "scene_layout", "infer_lines",
           "keyed_rows", "continuous_quaternions", "default_kind", "point_positions", "ATTACH_SPACINGS"]

ATTACH_SPACINGS = 1.5       # a chain end joins a node within this many mass spacings


class BlenderImportError(ValueError):
    """The CSV or an option cannot be used; the message names it and says what to do."""


def read_columns(path) -> dict[str, np.ndarray]:
    """Read a trajectory CSV (header row, then one row per output time) into ``{name: (n,)}``."""
    path = Path(path)
    if not path.is_file():
        raise BlenderImportError(f"{path}: no such trajectory CSV (scripts/simulate.py writes OUT/trajectory.csv)")
    with open(path, newline="") as fh:
        header = next(csv.reader(fh), None)
    if not header or "time" not in header:
        raise BlenderImportError(f"{path}: the first row must be the header and name a 'time' column")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)      # "input contained no data": said below
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as err:
        raise BlenderImportError(f"{path}: not a numeric CSV below its header ({err})") from None
    if data.shape[0] == 0:
        raise BlenderImportError(f"{path}: the CSV has a header but no rows")
    if data.shape[1] != len(header):
        raise BlenderImportError(f"{path}: {data.shape[1]} values per row but {len(header)} header names")
    columns = {name: data[:, i] for i, name in enumerate(header)}
    check_time(columns["time"], str(path))
    return columns


def check_time(time, where="time") -> None:
    time = np.asarray(time, float)
    if len(time) == 0:
        raise BlenderImportError(f"{where}: no rows")
    if not np.all(np.isfinite(time)) or np.any(np.diff(time) <= 0):
        raise BlenderImportError(f"{where}: the time column must be finite and increasing")


@dataclass
class Layout:
    """What a trajectory holds: rigid bodies (position and quaternion columns), free point
    masses (drawn as spheres), and lines (polylines of point and body names)."""

    bodies: list[str] = field(default_factory=list)
    points: list[str] = field(default_factory=list)
    lines: list[list[str]] = field(default_factory=list)


def _objects(columns):
    """Names with ``_x/_y/_z`` columns, split into bodies (with a quaternion) and points.
    A controller reference (``NAME_ref_x/y/z`` beside ``NAME_ref_yaw``) is not an object."""
    bodies, points = [], []
    for key in columns:
        if not key.endswith("_x"):
            continue
        name = key[:-2]
        if not all(f"{name}_{a}" in columns for a in "yz"):
            continue
        if name.endswith("_ref") and f"{name}_yaw" in columns:
            continue
        (bodies if all(f"{name}_q{a}" in columns for a in "wxyz") else points).append(name)
    return bodies, points


KNOT = re.compile(r"^(?P<net>.+)_k(?P<i>\d+)_(?P<j>\d+)$")
CHAIN = re.compile(r"^(?P<rope>.+)_(?P<k>\d+)$")


def point_positions(columns, name, rows=slice(None)):
    """``(n_rows, 3)`` positions of object ``name`` (its ``NAME_x/y/z`` columns) at ``rows``."""
    return np.stack([np.asarray(columns[f"{name}_{a}"], float)[rows] for a in "xyz"], axis=-1)


def infer_lines(columns, bodies, points):
    """Polylines of names (see the module docstring) and the points they use."""
    objects = set(bodies) | set(points)
    start = {n: point_positions(columns, n, 0) for n in objects}
    lines, used = [], set()
    grids: dict[str, dict[tuple[int, int], str]] = {}
    for p in points:
        m = KNOT.match(p)
        if m:
            grids.setdefault(m["net"], {})[(int(m["i"]), int(m["j"]))] = p
    for net, grid in grids.items():
        used |= set(grid.values())
        for (i, j), knot in sorted(grid.items()):
            for kind, end in (("h", (i, j + 1)), ("v", (i + 1, j))):
                if end not in grid:
                    continue
                masses = []
                while f"{net}_{kind}{i}_{j}_{len(masses)}" in objects:
                    masses.append(f"{net}_{kind}{i}_{j}_{len(masses)}")
                used |= set(masses)
                lines.append([knot, *masses, grid[end]])
    groups: dict[str, dict[int, str]] = {}
    for p in points:
        m = CHAIN.match(p)
        if p not in used and m and m["rope"] not in objects:
            groups.setdefault(m["rope"], {})[int(m["k"])] = p
    chains = [[g[k] for k in range(len(g))] for g in groups.values() if set(g) == set(range(len(g)))]
    nodes = [n for n in objects if n not in used and not any(n in c for c in chains)]
    nodes += [n for grid in grids.values() for n in grid.values()]
    for chain in chains:
        used |= set(chain)
        line = list(chain)
        a = _attach(start, chain[0], chain[1] if len(chain) > 1 else None, nodes, chain)
        if a is not None:
            line.insert(0, a)
        inner = chain[-2] if len(chain) > 1 else None
        b = _attach(start, chain[-1], inner, nodes, chain, other=a if len(chain) == 1 else None)
        if b is not None:
            line.append(b)
        if len(line) > 1:
            lines.append(line)
        else:
            used.discard(chain[0])      # a lone mass that joins nothing is a free point
    return lines, used


def _attach(start, end, inner, nodes, chain, other=None):
    """The node a chain's ``end`` mass joins: the nearest node beyond it (away from the
    ``inner`` neighbour; for a one-mass chain, on the other side of ``other``), within
    ``ATTACH_SPACINGS`` mass spacings."""
    p = start[end]
    candidates = [n for n in nodes if n not in chain and np.all(np.isfinite(start[n]))]
    if not candidates:
        return None
    d = {n: float(np.linalg.norm(start[n] - p)) for n in candidates}
    if inner is not None:
        spacing = float(np.mean([np.linalg.norm(start[a] - start[b]) for a, b in zip(chain[:-1], chain[1:])]))
        outward = p - start[inner]
        candidates = [n for n in candidates if np.dot(start[n] - p, outward) > 0]
    elif other is not None:
        spacing = d[other]
        candidates = [n for n in candidates if n != other and np.dot(start[n] - p, start[other] - p) < 0]
    else:
        spacing = min(d.values())
    candidates = [n for n in candidates if d[n] <= ATTACH_SPACINGS * spacing]
    return min(candidates, key=d.get) if candidates else None


def scene_layout(columns, lines=None) -> Layout:
    """Bodies, free points and lines of a trajectory (``lines`` given: used as they are,
    after checking that every name in them is in the CSV)."""
    bodies, points = _objects(columns)
    if not bodies and not points:
        raise BlenderImportError("the CSV has no objects: no NAME_x, NAME_y, NAME_z columns")
    if lines is None:
        lines, used = infer_lines(columns, bodies, points)
    else:
        lines = [list(line) for line in lines]
        unknown = sorted({n for line in lines for n in line} - set(bodies) - set(points))
        if unknown:
            raise BlenderImportError(f"lines: {', '.join(unknown[:5])} not in the CSV (no NAME_x/y/z columns)")
        used = {n for line in lines for n in line if n in points}
    return Layout(bodies=bodies, points=[p for p in points if p not in used], lines=lines)


def keyed_rows(time, fps) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, frames)``: the rows to key (the row nearest to each whole frame's time,
    each row at most once) and their frames ``(t - t0) fps`` (fractional where a row's
    time falls between frames)."""
    time = np.asarray(time, float)
    check_time(time)
    if not (isinstance(fps, (int, np.integer)) and not isinstance(fps, bool) and fps > 0):
        raise BlenderImportError(f"fps must be a positive whole number of frames per second, got {fps!r}")
    rel = (time - time[0]) * fps
    wanted = np.arange(int(math.floor(rel[-1] + 1e-9)) + 1)
    after = np.clip(np.searchsorted(rel, wanted), 0, len(rel) - 1)      # first row at or after the frame
    before = np.clip(after - 1, 0, len(rel) - 1)
    nearest = np.where(np.abs(rel[before] - wanted) <= np.abs(rel[after] - wanted), before, after)
    rows = np.unique(np.append(nearest, len(rel) - 1))
    return rows, rel[rows]


def continuous_quaternions(q) -> np.ndarray:
    """Unit quaternions ``(n, 4)`` with each one's sign chosen nearest to the one before."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    out = q.copy()
    for k in range(1, len(q)):
        if np.dot(out[k], out[k - 1]) < 0:
            out[k] = -out[k]
    return out


def default_kind(name: str, body: bool) -> str:
    if not body:
        return "sphere"
    if name.startswith("uav"):
        return "quadrotor"
    if name.startswith("cam"):
        return "camera"
    return "sphere"

