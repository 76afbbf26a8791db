"""Interactive 3D replay of a run: one self-contained HTML file (plotly).

:func:`write_replay_html` turns the trajectory columns of a run
(:func:`mysim_jax.io.trajectory.read_trajectory_csv` or ``trajectory_columns``) and its
scene config into one HTML file with a 3D view, a time slider and play / pause buttons.
plotly.js is embedded in the file, so it opens offline in any browser.

What is drawn is read from the config, so every kind of scene replays:

* quadrotors: the rotor cross (arms at the config's arm lengths and angles, a dot per
  rotor) and a heading line along the body +x axis, so attitude shows; the reference
  path (dashed) when the columns carry ``NAME_ref_x/y/z``. A vehicle that would be a
  speck in a large scene is drawn enlarged (its legend entry says by how much), so that
  its cross spans at least ``GLYPH_FRACTION`` of the scene; its position is exact;
* cameras on quadrotors: a diamond and a line along the camera's optical axis (the
  camera body's +x axis), enlarged the same way;
* the net as the polylines of its rows and columns through every knot and line mass;
  tethers, ropes and springs as polylines between their end nodes (a point, a body, a
  marker on a body, or an anchor) through their masses;
* the target as a sphere of its radius;
* free point masses (the rope net's payload, the collision ball) and other rigid bodies
  (with their body axes); anchors as fixed crosses;
* a trail behind every quadrotor, the target, free points and other bodies: their path
  over the last ``trail`` seconds;
* the ground plane z = 0, in scenes that have one: scenes with quadrotors, a target, or a
  contact pair with ``ground``. Other scenes (the rope net hangs below its anchors at
  z = 0) are drawn without it.

The run is downsampled to at most ``max_frames`` evenly spaced output rows (the last
row always included). Every frame stores the moving geometry once, as float32 binary
(base64): the embedded plotly.js is a few megabytes, and the frames of a capture scene
with its whole net at the default ``max_frames`` add a few more. The axis ranges are fixed
over the whole run and the three axes have the same scale (1 m is 1 m in every
direction), so the view never jumps; an axis along which little moves is widened to at
least ``MIN_SPAN_FRACTION`` of the largest span, so a flat scene is still seen at an
angle. Positions are in metres, time in seconds.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mysim_jax.config.scene import expand_capture
from mysim_jax.core.extras import require
from mysim_jax.core.npgeom import rotate

COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf",
          "#bcbd22", "#7f7f7f")
NET_COLOR = "#555555"
ROPE_COLOR = "#8a6d3b"
TARGET_COLOR = "#202020"
GROUND_COLOR = "#c9dcc0"
CAMERA_AXIS = 0.12        # m, length of a camera's optical-axis line (at least)
HEADING_FACTOR = 1.6      # a quadrotor's heading line, in (drawn) arm lengths
BODY_AXIS = 0.15          # m, axis lines of other rigid bodies (at least)
GLYPH_FRACTION = 0.08     # quadrotors, camera and body axes are drawn at least this fraction of the scene
MIN_SPAN_FRACTION = 0.25  # every axis range spans at least this fraction of the largest one
PAD_FRACTION = 0.05       # margin around everything drawn, as a fraction of the largest span
MIN_PAD = 0.1             # m
TRAIL_POINTS = 40         # positions per trail and frame


class ReplayError(ValueError):
    """The columns cannot be replayed with this config. The message names what is missing."""


# --- geometry from the columns ---------------------------------------------------------


def _xyz(columns, name, rows):
    return np.stack([columns[f"{name}_{a}"][rows] for a in "xyz"], axis=-1)


def _quat(columns, name, rows):
    q = np.stack([columns[f"{name}_q{a}"][rows] for a in "wxyz"], axis=-1)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    return q / np.where(norm > 0, norm, 1.0)


def _polyline_array(lines):
    """Join polylines ``[(n_frames, n_i, 3), ...]`` into one ``(n_frames, Σ(n_i + 1), 3)``
    array with a NaN row between them (plotly breaks a line at a NaN)."""
    n = lines[0].shape[0]
    gap = np.full((n, 1, 3), np.nan)
    parts = []
    for line in lines:
        parts += [line, gap]
    return np.concatenate(parts[:-1], axis=1)


def _sphere(radius, n_lat=8, n_lon=14):
    """Vertices ``(n, 3)`` and triangles ``(m, 3)`` of a UV sphere of ``radius`` at the origin."""
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                     np.cos(theta)[:, None] * np.ones_like(phi)], axis=-1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]]) * radius
    tris = []
    top, bottom = 0, len(verts) - 1
    idx = lambda r, c: 1 + r * n_lon + c % n_lon  # noqa: E731
    for c in range(n_lon):
        tris.append((top, idx(0, c), idx(0, c + 1)))
        tris.append((bottom, idx(len(theta) - 1, c + 1), idx(len(theta) - 1, c)))
        for r in range(len(theta) - 1):
            tris.append((idx(r, c), idx(r + 1, c), idx(r + 1, c + 1)))
            tris.append((idx(r, c), idx(r + 1, c + 1), idx(r, c + 1)))
    return verts, np.asarray(tris)


# --- the scene description -------------------------------------------------------------


@dataclass
class _Layer:
    """One plotly trace whose geometry changes every frame: ``xyz`` ``(n_frames, n, 3)``."""

    name: str
    xyz: np.ndarray
    style: dict
    kind: str = "scatter3d"          # or "mesh3d"
    mesh: tuple | None = None        # (vertices relative to the centre, triangles) for mesh3d


@dataclass
class _Scene:
    layers: list[_Layer] = field(default_factory=list)
    static: list[dict] = field(default_factory=list)     # plotly trace dicts drawn once
    extent: list[np.ndarray] = field(default_factory=list)   # arrays (..., 3) the view must contain
    ground: bool = False


class _Nodes:
    """World positions over the selected rows of anything a line may end at: a point or
    rope mass, a body, a marker on a body (``body.marker``), or an anchor."""

    def __init__(self, columns, config, rows):
        self.columns, self.rows = columns, rows
        self.anchors = {a.name: np.asarray(a.pos, float) for a in config.anchors}
        self.markers = {f"{b.name}.{m.name}": (b.name, np.asarray(m.pos, float))
                        for b in config.bodies for m in b.markers}
        self._cache: dict[str, np.ndarray] = {}

    def __call__(self, name):
        if name not in self._cache:
            if name in self.anchors:
                xyz = np.broadcast_to(self.anchors[name], (len(self.rows), 3))
            elif name in self.markers:
                body, offset = self.markers[name]
                xyz = _xyz(self.columns, body, self.rows) + rotate(_quat(self.columns, body, self.rows), offset)
            else:
                xyz = _xyz(self.columns, name, self.rows)
            self._cache[name] = xyz
        return self._cache[name]


def _net_polylines(net, nodes):
    """The net's rows (along x, through the ``h`` ropes) and columns (along y, through
    the ``v`` ropes), each one polyline through its knots and line masses."""
    g, m = net.knots, net.masses_per_edge
    lines = []
    for kind, knot in (("h", lambda a, b: (a, b)), ("v", lambda a, b: (b, a))):
        for a in range(g):
            names = []
            for b in range(g):
                names.append(net.knot_name(*knot(a, b)))
                if b < g - 1:
                    i, j = knot(a, b)
                    names += [f"{net.name}_{kind}{i}_{j}_{k}" for k in range(m)]
            lines.append(np.stack([nodes(n) for n in names], axis=1))
    return lines


def _rope_polylines(ropes, nodes):
    return [np.stack([nodes(r.start)] + [nodes(f"{r.name}_{k}") for k in range(r.n_masses)] + [nodes(r.end)], axis=1)
            for r in ropes]


def required_names(config) -> dict[str, str]:
    """Every name the replay of ``config`` reads from the columns, mapped to ``"point"``
    (needs ``NAME_x/y/z``) or ``"body"`` (also ``NAME_qw/qx/qy/qz``)."""
    full, _ = expand_capture(config)
    names = {p.name: "point" for p in full.points}
    names.update({f"{r.name}_{k}": "point" for r in full.ropes for k in range(r.n_masses)})
    names.update({b.name: "body" for b in full.bodies})
    names.update({c.name: "body" for q in config.quadrotors for c in q.cameras})
    return names


def check_columns(columns, config) -> int:
    """Raise :class:`ReplayError` if ``columns`` lack anything the config names; returns
    the number of rows."""
    if "time" not in columns:
        raise ReplayError("the columns have no 'time' column; pass what read_trajectory_csv returns")
    n = len(columns["time"])
    if n == 0:
        raise ReplayError("the trajectory has no rows: there is nothing to replay")
    missing = []
    for name, kind in required_names(config).items():
        axes = ("x", "y", "z") + (("qw", "qx", "qy", "qz") if kind == "body" else ())
        lacking = [f"{name}_{a}" for a in axes if f"{name}_{a}" not in columns]
        if lacking:
            missing.append(name if len(lacking) == len(axes) else f"{name} ({', '.join(lacking)})")
    if missing:
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        raise ReplayError(f"the trajectory has no columns for {shown}, which scene '{config.name}' names: "
                          "replay a trajectory with the config it was simulated with (the run folder's "
                          "config.yaml)")
    short = [k for k, v in columns.items() if len(v) != n]
    if short:
        raise ReplayError(f"columns {', '.join(short[:5])} have a different length than 'time' ({n} rows)")
    return n


def frame_rows(n_rows: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` evenly spaced row indices from 0 to ``n_rows - 1`` (both kept)."""
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1:
        raise ReplayError(f"max_frames must be a positive whole number, got {max_frames!r}")
    if n_rows <= max_frames:
        return np.arange(n_rows)
    return np.unique(np.linspace(0, n_rows - 1, max_frames).round().astype(int))


def _trail(xyz, time, trail, max_points=TRAIL_POINTS):
    """``(n_frames, w, 3)`` trails: frame k shows the path over the ``trail`` seconds
    before it, through at most ``max_points`` of the frames' positions (every s-th frame
    when the window holds more; before the first frame the trail stays at the start)."""
    n = len(time)
    dt = float(np.median(np.diff(time))) if n > 1 else 1.0
    window = int(np.ceil(trail / dt)) if dt > 0 else 0
    stride = max(1, int(np.ceil(window / max_points)))
    back = np.arange(0, window + 1, stride)                       # frames behind the current one
    index = np.clip(np.arange(n)[:, None] - back[None, :], 0, n - 1)
    return xyz[index]


@dataclass
class _Draw:
    """What the drawing steps of :func:`_describe` share: the columns, the frames' rows,
    the trail length, the glyph size and the scene being filled."""

    columns: dict
    rows: np.ndarray
    trail: int
    glyph: float
    scene: _Scene

    @property
    def time(self):
        return self.columns["time"][self.rows]

    def pose(self, name):
        return _xyz(self.columns, name, self.rows), _quat(self.columns, name, self.rows)

    def trail_layer(self, name, xyz, color):
        self.scene.layers.append(_Layer(f"{name} trail", _trail(xyz, self.time, self.trail),
                                        dict(mode="lines", line=dict(color=color, width=2), opacity=0.5,
                                             showlegend=False, hoverinfo="skip")))


def _describe(columns, config, rows, trail) -> _Scene:
    """Everything to draw, per frame and static, from what the config contains."""
    full, _ = expand_capture(config)
    nodes = _Nodes(columns, full, rows)
    everything = np.concatenate([nodes(n) for n in required_names(config)] + [np.zeros((0, 3))], axis=0)
    everything = everything[np.all(np.isfinite(everything), axis=1)]
    view = float(np.ptp(everything, axis=0).max()) if len(everything) else 1.0
    # GLYPH_FRACTION * view m: the size small glyphs are drawn at, at least
    d = _Draw(columns=columns, rows=rows, trail=trail, glyph=GLYPH_FRACTION * view, scene=_Scene())
    _draw_lines(d, config, full, nodes)
    for k, q in enumerate(config.quadrotors):
        _draw_quadrotor(d, q, COLORS[k % len(COLORS)])
    _draw_cameras(d, sorted({c.name for q in config.quadrotors for c in q.cameras}))
    if config.target is not None:
        _draw_target(d, config.target)
    _draw_points_and_bodies(d, config, nodes)
    if config.anchors:
        a = np.array([x.pos for x in config.anchors], float)
        d.scene.static.append(dict(type="scatter3d", name="anchors", x=a[:, 0].tolist(), y=a[:, 1].tolist(),
                                   z=a[:, 2].tolist(),
                                   mode="markers", marker=dict(size=6, symbol="cross", color="black")))
        d.scene.extent.append(a)
    contact_ground = config.contact is not None and any("ground" in pair for pair in config.contact.pairs)
    d.scene.ground = bool(config.quadrotors) or config.target is not None or contact_ground
    return d.scene


def _draw_lines(d: _Draw, config, full, nodes) -> None:
    """The net, and every other rope and spring."""
    scene = d.scene
    if config.net is not None:
        net = _polyline_array(_net_polylines(config.net, nodes))
        scene.layers.append(_Layer("net", net, dict(mode="lines", line=dict(color=NET_COLOR, width=2))))
        scene.extent.append(net)
    net_edges = set()
    if config.net is not None:
        g, name = config.net.knots, config.net.name
        net_edges = {f"{name}_{kind}{i}_{j}" for kind in "hv" for i in range(g) for j in range(g)}
    lines = _rope_polylines([r for r in full.ropes if r.name not in net_edges], nodes)
    lines += [np.stack([nodes(s.start), nodes(s.end)], axis=1) for s in full.springs]
    if lines:
        label = "tethers" if config.net is not None and not config.ropes and not config.springs else "ropes"
        xyz = _polyline_array(lines)
        scene.layers.append(_Layer(label, xyz, dict(mode="lines+markers", line=dict(color=ROPE_COLOR, width=3),
                                                    marker=dict(size=2, color=ROPE_COLOR))))
        scene.extent.append(xyz)


def _draw_quadrotor(d: _Draw, q, color) -> None:
    """A quadrotor's rotor cross and heading, its trail and its reference path."""
    scene, columns = d.scene, d.columns
    pos, quat = d.pose(q.body)
    arm = np.asarray(q.rotors.arm_length, float)
    angle = np.asarray(q.rotors.angle, float)
    scale = max(1.0, d.glyph / (2.0 * arm.max()))
    tips = scale * np.stack([arm * np.cos(angle), arm * np.sin(angle), np.zeros(4)], axis=-1)  # (4, 3) body frame
    nose = np.array([HEADING_FACTOR * scale * arm.max(), 0.0, 0.0])
    local = np.array([tips[0], tips[2], [np.nan] * 3, tips[1], tips[3], [np.nan] * 3, [0.0, 0.0, 0.0], nose])
    world = pos[:, None, :] + rotate(quat[:, None, :], local[None, :, :])
    label = q.body if scale == 1.0 else f"{q.body} (drawn {scale:.2g}x)"
    scene.layers.append(_Layer(label, world, dict(mode="lines+markers", line=dict(color=color, width=6),
                                                   marker=dict(size=3, color=color))))
    d.trail_layer(q.body, pos, color)
    scene.extent.append(pos)
    if all(f"{q.body}_ref_{a}" in columns for a in "xyz"):
        ref = np.stack([columns[f"{q.body}_ref_{a}"] for a in "xyz"], axis=-1)
        scene.static.append(dict(type="scatter3d", name=f"{q.body} reference", x=_typed(ref[:, 0]),
                                 y=_typed(ref[:, 1]), z=_typed(ref[:, 2]), mode="lines",
                                 line=dict(color=color, width=2, dash="dash"), opacity=0.6, hoverinfo="skip"))
        scene.extent.append(ref)


def _draw_cameras(d: _Draw, names) -> None:
    """Cameras: a diamond and the optical axis."""
    if not names:
        return
    segs = []
    for name in names:
        pos, quat = d.pose(name)
        segs.append(np.stack([pos, pos + rotate(quat, [max(CAMERA_AXIS, d.glyph), 0.0, 0.0])], axis=1))
    d.scene.layers.append(_Layer("cameras", _polyline_array(segs),
                                 dict(mode="lines+markers", line=dict(color="#e377c2", width=4),
                                      marker=dict(size=3, symbol="diamond", color="#e377c2"))))


def _draw_target(d: _Draw, target) -> None:
    """The target: a sphere of its radius, and its trail."""
    pos = _xyz(d.columns, target.name, d.rows)
    verts, tris = _sphere(target.radius)
    d.scene.layers.append(_Layer(target.name, pos[:, None, :] + verts[None],
                                 dict(color=TARGET_COLOR, opacity=1.0, flatshading=True),
                                 kind="mesh3d", mesh=(verts, tris)))
    d.trail_layer(target.name, pos, TARGET_COLOR)
    d.scene.extent.append(pos[:, None, :] + verts[None])


def _draw_points_and_bodies(d: _Draw, config, nodes) -> None:
    """Free point masses, and the bodies that are not quadrotors (as axes)."""
    scene = d.scene
    free = [p.name for p in config.points]
    if free:
        xyz = np.stack([nodes(n) for n in free], axis=1)
        scene.layers.append(_Layer("points", xyz, dict(mode="markers+text", text=free, textposition="top center",
                                                        marker=dict(size=6, color="#d62728"))))
        for n in free:
            d.trail_layer(n, nodes(n), "#d62728")
        scene.extent.append(xyz)
    quad_bodies = {q.body for q in config.quadrotors}
    others = [b.name for b in config.bodies if b.name not in quad_bodies]
    for k, name in enumerate(others):
        color = COLORS[(len(config.quadrotors) + k) % len(COLORS)]
        pos, quat = d.pose(name)
        size = max(BODY_AXIS, d.glyph)
        local = np.array([[0, 0, 0], [size, 0, 0], [np.nan] * 3, [0, 0, 0], [0, size, 0], [np.nan] * 3,
                          [0, 0, 0], [0, 0, size]], float)
        world = pos[:, None, :] + rotate(quat[:, None, :], local[None])
        scene.layers.append(_Layer(name, world, dict(mode="lines+markers", line=dict(color=color, width=5),
                                                     marker=dict(size=3, color=color))))
        d.trail_layer(name, pos, color)
        scene.extent.append(pos)


def _axis_ranges(scene: _Scene) -> np.ndarray:
    """Fixed ``(3, 2)`` axis ranges holding everything drawn (and the ground when there is
    one), with equal scale on the three axes."""
    pts = np.concatenate([np.asarray(e, float).reshape(-1, 3) for e in scene.extent], axis=0)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        pts = np.zeros((1, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if scene.ground:
        lo[2] = min(lo[2], 0.0)
    span = hi - lo
    pad = max(PAD_FRACTION * span.max(), MIN_PAD)
    lo, hi = lo - pad, hi + pad
    span = hi - lo
    widen = np.maximum(MIN_SPAN_FRACTION * span.max() - span, 0.0)
    lo, hi = lo - widen / 2, hi + widen / 2
    if scene.ground and pts[:, 2].min() >= 0.0 and lo[2] < -pad:
        # widening put empty space under the ground: move it above the scene instead
        shift = -pad - lo[2]
        lo[2], hi[2] = lo[2] + shift, hi[2] + shift
    return np.stack([lo, hi], axis=1)


def _typed(values, dtype="f4") -> dict:
    """An array as plotly.js's typed-array spec (little-endian binary, base64): a quarter
    of the size of its decimal text. NaN stays NaN (a gap in a line)."""
    array = np.ascontiguousarray(values, dtype=np.dtype(dtype).newbyteorder("<"))
    return dict(dtype=dtype, bdata=base64.b64encode(array.tobytes()).decode("ascii"))


def _layer_data(layer: _Layer, k: int) -> dict:
    xyz = layer.xyz[k]
    return dict(type=layer.kind, x=_typed(xyz[:, 0]), y=_typed(xyz[:, 1]), z=_typed(xyz[:, 2]))


def replay_figure(columns, config, title: str | None = None, max_frames: int = 200, trail: float = 2.0):
    """The replay as a plotly figure dict (``data``, ``layout``, ``frames``: one per
    selected row, with a slider and play / pause buttons). ``trail``: seconds of path drawn
    behind moving objects."""
    n_rows = check_columns(columns, config)
    rows = frame_rows(n_rows, max_frames)
    if not np.isfinite(trail) or trail < 0:
        raise ReplayError(f"trail must be a non-negative number of seconds, got {trail!r}")
    scene = _describe(columns, config, rows, trail)
    time = np.asarray(columns["time"], float)[rows]
    ranges = _axis_ranges(scene)

    data = []
    for layer in scene.layers:
        if layer.kind == "mesh3d":
            verts, tris = layer.mesh
            data.append(dict(name=layer.name, showlegend=True, i=_typed(tris[:, 0], "i4"), j=_typed(tris[:, 1], "i4"),
                             k=_typed(tris[:, 2], "i4"),
                             **_layer_data(layer, 0), **layer.style))
        else:
            data.append(dict(name=layer.name, **_layer_data(layer, 0), **layer.style))
    dynamic = list(range(len(data)))
    data += scene.static
    if scene.ground:
        (x0, x1), (y0, y1) = ranges[0], ranges[1]
        data.append(dict(type="surface", name="ground (z = 0)", x=[float(x0), float(x1)], y=[float(y0), float(y1)],
                         z=[[0.0, 0.0], [0.0, 0.0]], colorscale=[[0, GROUND_COLOR], [1, GROUND_COLOR]],
                         showscale=False, opacity=0.8, hoverinfo="skip", showlegend=True))

    frames = [dict(name=str(k), data=[_layer_data(layer, k) for layer in scene.layers], traces=dynamic)
              for k in range(len(rows))]
    step_ms = float(np.median(np.diff(time))) * 1000.0 if len(time) > 1 else 100.0
    play = dict(frame=dict(duration=max(step_ms, 40.0), redraw=True), fromcurrent=True,
                transition=dict(duration=0), mode="immediate")
    pause = dict(frame=dict(duration=0, redraw=False), transition=dict(duration=0), mode="immediate")
    slider = dict(active=0, x=0.05, len=0.9, y=0.02, pad=dict(t=30),
                  currentvalue=dict(prefix="t = ", suffix=" s", visible=True),
                  steps=[dict(label=f"{t:.3g}", method="animate",
                              args=[[str(k)], dict(frame=dict(duration=0, redraw=True), mode="immediate",
                                                   transition=dict(duration=0))])
                         for k, t in enumerate(time)])
    spans = ranges[:, 1] - ranges[:, 0]
    axis = lambda a, r: dict(title=f"{a} [m]", range=[float(v) for v in r], autorange=False,  # noqa: E731
                            zeroline=False)
    layout = dict(
        title=dict(text=title or _default_title(config, time), x=0.5),
        scene=dict(xaxis=axis("x", ranges[0]), yaxis=axis("y", ranges[1]), zaxis=axis("z", ranges[2]),
                   aspectmode="manual", aspectratio=dict(zip("xyz", (spans / spans.max()).tolist())),
                   camera=dict(eye=dict(x=1.15, y=-1.35, z=0.75))),
        uirevision="replay",
        margin=dict(l=0, r=0, t=50, b=0),
        legend=dict(x=0.0, y=0.95, bgcolor="rgba(255,255,255,0.7)"),
        updatemenus=[dict(type="buttons", direction="left", x=0.05, y=0.1, xanchor="left", yanchor="top",
                          showactive=False, pad=dict(r=10, t=10),
                          buttons=[dict(label="▶ play", method="animate", args=[None, play]),
                                   dict(label="❚❚ pause", method="animate", args=[[None], pause])])],
        sliders=[slider],
    )
    return dict(data=data, layout=layout, frames=frames)


def _default_title(config, time) -> str:
    text = config.name
    if config.description:
        text += f": {config.description}"
    return f"{text}<br><sub>{len(time)} frames, t = {time[0]:.3g} to {time[-1]:.3g} s; positions in m</sub>"


def write_replay_html(columns, config, path, title: str | None = None, max_frames: int = 200,
                      trail: float = 2.0) -> Path:
    """Write the replay of a run (see the module docstring) to ``path``, one self-contained
    HTML file with plotly.js inline. ``columns``: trajectory columns; ``config``: the scene
    config the run was simulated with. Raises :class:`ReplayError` naming what is missing
    when the columns do not fit the config."""
    # plotly is an optional extra ([plots]): imported only when a replay is written
    require("the HTML replay (replay.html)", "plotly")
    import plotly.io

    fig = replay_figure(columns, config, title=title, max_frames=max_frames, trail=trail)
    path = Path(path)
    plotly.io.write_html(fig, path, include_plotlyjs=True, full_html=True, auto_play=False, div_id="replay",
                         validate=False, config=dict(displaylogo=False, responsive=True))
    return path
