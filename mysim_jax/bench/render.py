"""Rendering speed: frames per second of :meth:`Renderer.render <mysim_jax.perception.render.Renderer.render>`.

The scene is ``configs/capture_falling.yaml`` with one fixed camera added on uav0 (``cam0``:
yawed towards the net's centre and pitched 35 deg down), simulated with its scripted team
for ``t_end`` seconds. Three views, each rendered at every image size of the same camera
(the paper's 50 mm lens on a 36 mm sensor):

* ``onboard`` — ``cam0`` at the output row where it sees the most of the target with all of
  the target inside the image (the net across the image, the target in it, the ground behind);
* ``observer`` — a free camera (:func:`~mysim_jax.perception.camera.look_at`) 8 m from the
  net, looking at it: all four UAVs, the net, the tethers and the target in view;
* ``ground`` — the same free camera turned away from the team: ground and sky only.

Frames per second are 1 / the median time of one ``render`` call (inputs checked, ground,
objects, compositing, target boxes), timed round-robin across views and sizes
(:func:`mysim_jax.bench.timing.time_round_robin`). :func:`section_h` writes them as
BENCHMARKS.md (h), with :func:`example_image` saved beside the report's plots.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from mysim_jax.bench.report import ROOT
from mysim_jax.bench.timing import contention_note, median, spread, time_round_robin, wait_for_quiet
from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.io.trajectory import trajectory_columns
from mysim_jax.perception.camera import intrinsics
from mysim_jax.perception.camera import look_at
from mysim_jax.perception.render import Renderer
from mysim_jax.driver import simulate
from mysim_jax.tasks.scripted import team_policy

CAPTURE_FALLING = Path(__file__).resolve().parents[2] / "configs" / "capture_falling.yaml"
CAMERA_QUAT = (0.88112, -0.115075, 0.277816, 0.364972)   # yaw 45 deg, then pitch 35 deg down
OBSERVER_EYE = (-6.0, -5.0, 5.5)                          # m
NET_CENTRE = (0.0, 0.0, 3.0)                              # m
AWAY = (-30.0, -25.0, 0.0)                                # m, a point on the ground behind the observer
SIZES = ((1920, 1080), (640, 360))


def capture_run(t_end: float = 1.6, progress: bool = False):
    """(config, columns) of the capture scene with ``cam0`` on uav0, simulated for ``t_end`` s."""
    raw = yaml.safe_load(CAPTURE_FALLING.read_text())
    raw["sim"]["t_end"] = t_end
    raw["quadrotors"][0]["cameras"] = [{"name": "cam0", "mount": "fixed", "quat": list(CAMERA_QUAT)}]
    config = config_from_dict(raw, str(CAPTURE_FALLING))
    scene, params, state = build(config)
    traj = simulate(scene, params, state, config.run_settings(), progress=progress, policy=team_policy(config, scene))
    if not traj.ok:
        raise RuntimeError(f"the benchmark's capture run failed: {traj.failure}")
    return config, trajectory_columns(scene, traj)


def views(config, columns) -> dict[str, tuple[object, int]]:
    """view name -> (camera, row), as in the module doc."""
    t = columns["time"]
    probe = Renderer(config, intrinsics(width=160, height=90))
    seen, whole = [], []
    for f in probe.render_many(columns, "cam0", progress=False):
        box = f.target.full_box
        seen.append(f.target.visible_px)
        whole.append(box is not None and box[0] > 0 and box[1] > 0 and box[2] < 159 and box[3] < 89)
    seen = np.asarray(seen)
    row = int(np.argmax(np.where(whole, seen, -1))) if any(whole) else int(np.argmax(seen))
    return {"onboard": ("cam0", row),
            "observer": (look_at(OBSERVER_EYE, NET_CENTRE, t), row),
            "ground": (look_at(OBSERVER_EYE, AWAY, t), row)}


@dataclass
class RenderRow:
    view: str
    width: int
    height: int
    times: list[float]          # s per frame, counted rounds
    target_px: int              # target pixels visible in the frame
    object_px: int              # pixels showing an object (not ground or sky)

    @property
    def fps(self) -> float:
        return 1.0 / median(self.times)


def measure(config, columns, sizes=SIZES, repeats: int = 5, section: str = "h") -> tuple[list[RenderRow], dict]:
    """Time every view at every size; also returns the 640 x 360 frames (view -> Frame) for a picture."""
    chosen = views(config, columns)
    renderers = {(w, h): Renderer(config, intrinsics(width=w, height=h)) for w, h in sizes}
    calls, meta, frames = {}, {}, {}
    for (w, h), renderer in renderers.items():
        for name, (camera, row) in chosen.items():
            frame = renderer.render(columns, camera, row)
            key = f"{name} {w}x{h}"
            meta[key] = (name, w, h, frame.target.visible_px, int((frame.ids > 1).sum()))
            if (w, h) == (640, 360):
                frames[name] = frame
            calls[key] = (lambda r=renderer, c=camera, k=row: r.render(columns, c, k) and None)
    times = time_round_robin(calls, repeats, section=section)
    rows = [RenderRow(view=m[0], width=m[1], height=m[2], times=times[key], target_px=m[3], object_px=m[4])
            for key, m in meta.items()]
    return rows, frames


def example_image(frames: dict) -> np.ndarray:
    """(360, 1280, 3) uint8 RGB: the onboard and observer frames side by side, target boxes drawn."""
    tiles = []
    for name in ("onboard", "observer"):
        image = frames[name].image.copy()
        box = frames[name].target.box
        if box is not None:
            u0, v0, u1, v1 = (int(round(x)) for x in box)
            cv2.rectangle(image, (u0 - 1, v0 - 1), (u1, v1), (255, 40, 40), 1)
        cv2.putText(image, name, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(image)
    return np.concatenate(tiles, axis=1)


def section_h(cfg, results) -> list[str]:
    """(h) Rendering speed (:func:`measure`): a capture run seen by an onboard and an
    observer camera, and ground only, at 1920 x 1080 and 640 x 360."""
    t0 = time.perf_counter()
    config, columns = capture_run(t_end=1.6)
    sim_s = time.perf_counter() - t0
    wait_for_quiet(cfg.max_wait_s, "h")
    rows, frames = measure(config, columns, repeats=3 if cfg.quick else 7, section="h")
    results["h"] = {f"{r.view} {r.width}x{r.height}": r.fps for r in rows}
    picture = cfg.plots_dir / "render_example.png"
    cv2.imwrite(str(picture), cv2.cvtColor(example_image(frames), cv2.COLOR_RGB2BGR))
    onboard = frames["onboard"]
    lines = [
        "## (h) Rendering (camera images)",
        "",
        f"`Renderer.render` (mysim_jax/perception/render.py) on `{CAPTURE_FALLING.relative_to(ROOT)}` with a "
        f"camera `cam0` on uav0 (yawed to the net, pitched 35° down), simulated 1.6 s ({sim_s:.0f} s, compile "
        f"included). Views at t = {onboard.t:.2f} s (the row where cam0 sees the most of the target, all of it in the image): "
        "**onboard** (cam0), **observer** (a free camera 8 m from the net: four UAVs, net, tethers, target) and "
        "**ground** (the observer turned away: ground and sky only). One call = inputs checked, ground, objects, "
        f"compositing, target boxes; median of the counted rounds, timed round-robin "
        f"(mysim_jax/bench/render.py). {contention_note('h', 3 if cfg.quick else 7)}",
        "",
        "| view | image | ms per frame | frames/s | object pixels | target pixels | spread |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r.view} | {r.width} × {r.height} | {1e3 * median(r.times):.0f} | {r.fps:.1f} | "
                     f"{r.object_px:,} | {r.target_px:,} | {spread(r.times)} |")
    small = [r for r in rows if (r.width, r.height) == (640, 360)]
    slowest = min(small, key=lambda r: r.fps)
    lines += ["", f"A 30 s flight at 20 Hz (600 frames) at 640 × 360 takes ~{600 / slowest.fps / 60:.1f} min "
              f"at the slowest view's rate ({slowest.view}).", "",
              f"![rendered frames](docs/bench/{picture.name})", ""]
    return lines
