"""The renderer's files and results: the run folder it reads, the frames it returns and
the files it writes them to.

:func:`load_run` reads a run folder of ``scripts/simulate.py`` (its ``trajectory.csv`` and
``config.yaml``). A :class:`Frame` is one rendered image with its depth, object ids and the
target's :class:`TargetView` (boxes: see :mod:`mysim_jax.perception.render` for the pixel
convention). :func:`write_video` writes frames to an ``.mp4`` or ``.avi`` file,
:func:`write_images` to PNG files with the target's boxes in ``targets.csv``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from mysim_jax.config.scene import ConfigError, load_config
from mysim_jax.io.trajectory import read_trajectory_csv
from mysim_jax.perception.camera import PerceptionError

__all__ = ["TargetView", "Frame", "Run", "load_run", "write_video", "write_images"]


@dataclass(frozen=True)
class TargetView:
    """Where the target is in one frame (boxes: see the module doc for the pixel convention)."""

    box: np.ndarray | None        # (4,) px (u_min, v_min, u_max, v_max) of the visible pixels; None: none visible
    full_box: np.ndarray | None   # (4,) px, the same for the silhouette with no occluders; None: out of view
    visible_fraction: float       # visible pixels / silhouette pixels (0 when out of view)
    visible_px: int               # pixels showing the target
    full_px: int                  # pixels of its unoccluded silhouette within the image
    centre: np.ndarray            # (2,) px, projection of the target's centre (meaningless when depth <= 0)
    depth: float                  # m, depth of the target's centre along the optical axis


@dataclass(frozen=True)
class Frame:
    """One rendered camera image and its ground truth."""

    image: np.ndarray            # (H, W, 3) uint8 RGB
    depth: np.ndarray            # (H, W) float32 m along the optical axis of the surface seen; inf on sky
    ids: np.ndarray              # (H, W) int16 object id, an index into ``names`` (0 sky, 1 ground)
    names: tuple[str, ...]       # object name of every id
    target: TargetView | None    # None when the scene has no target
    row: int                     # output row of the run
    t: float                     # s
    camera: str
    R: np.ndarray                # (3, 3) OpenCV camera frame -> world
    p: np.ndarray                # (3,) m, optical centre in the world

    def mask(self, name: str) -> np.ndarray:
        """(H, W) bool: pixels showing object ``name`` ('sky', 'ground', a body, 'net', 'tether0', ...)."""
        if name not in self.names:
            raise PerceptionError(f"no object '{name}' in this frame; objects: {', '.join(self.names)}")
        return self.ids == self.names.index(name)


@dataclass(frozen=True)
class Run:
    """A saved run: its resolved scene config and trajectory columns."""

    folder: Path
    config: object                    # SceneConfig
    columns: dict[str, np.ndarray]    # column name -> (N,) values

    @property
    def fps(self) -> float:
        """Output rows per second of simulated time."""
        t = self.columns["time"]
        return float((len(t) - 1) / (t[-1] - t[0])) if len(t) > 1 and t[-1] > t[0] else 1.0


def load_run(folder: str | Path) -> Run:
    """Read ``trajectory.csv`` and ``config.yaml`` of a run folder written by ``scripts/simulate.py``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PerceptionError(f"run folder {folder} does not exist; write one with "
                              f"scripts/simulate.py CONFIG --out {folder}")
    missing = [n for n in ("trajectory.csv", "config.yaml") if not (folder / n).is_file()]
    if missing:
        raise PerceptionError(f"run folder {folder} has no {' or '.join(missing)}; it must be the --out folder of "
                              f"scripts/simulate.py (which writes both)")
    try:
        config = load_config(folder / "config.yaml")
    except ConfigError as err:
        raise PerceptionError(f"run folder {folder}: {err}") from None
    try:
        columns = read_trajectory_csv(folder / "trajectory.csv")
    except (ValueError, OSError) as err:
        raise PerceptionError(f"run folder {folder}: trajectory.csv cannot be read ({err})") from None
    return Run(folder=folder, config=config, columns=columns)


def _rgb(frame) -> np.ndarray:
    image = frame.image if isinstance(frame, Frame) else np.asarray(frame)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise PerceptionError(f"a frame must be a Frame or an (H, W, 3) uint8 RGB image, got "
                              f"{image.dtype} {image.shape}")
    return image


def write_video(frames: Iterable, path: str | Path, fps: float = 20.0) -> int:
    """Write frames (:class:`Frame` or (H, W, 3) uint8 RGB) to a video file; returns the frame count.

    The codec follows the suffix: ``.mp4`` (MPEG-4 part 2), ``.avi`` (Motion JPEG).
    """
    path = Path(path)
    codecs = {".mp4": "mp4v", ".avi": "MJPG"}
    if path.suffix.lower() not in codecs:
        raise PerceptionError(f"video file {path} must end in .mp4 or .avi (or write images with write_images)")
    if not fps > 0:
        raise PerceptionError(f"fps must be positive, got {fps}")
    if not path.parent.is_dir():
        raise PerceptionError(f"folder {path.parent} does not exist; create it first")
    writer = None
    count = 0
    try:
        for frame in frames:
            image = _rgb(frame)
            if writer is None:
                size = (image.shape[1], image.shape[0])
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codecs[path.suffix.lower()]), float(fps), size)
                if not writer.isOpened():
                    raise PerceptionError(f"OpenCV cannot write {path} with codec {codecs[path.suffix.lower()]}; "
                                          f"try .avi or write_images")
            elif (image.shape[1], image.shape[0]) != size:
                raise PerceptionError(f"frame {count} is {image.shape[1]} x {image.shape[0]} px but the video is "
                                      f"{size[0]} x {size[1]}; all frames must have one size")
            writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            count += 1
    finally:
        if writer is not None:
            writer.release()
    if count == 0:
        raise PerceptionError(f"no frames to write to {path}")
    return count


def write_images(frames: Iterable[Frame], folder: str | Path, prefix: str = "frame") -> int:
    """Write every frame as ``PREFIX_ROW.png`` into ``folder`` (created) and the target's boxes as
    ``targets.csv`` (row, t, box, full box, visible fraction; empty cells when absent); returns the count."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    count = 0
    with open(folder / "targets.csv", "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["row", "t", "u_min", "v_min", "u_max", "v_max",
                      "full_u_min", "full_v_min", "full_u_max", "full_v_max", "visible_fraction"])
        for frame in frames:
            if not isinstance(frame, Frame):
                raise PerceptionError(f"write_images takes Frames (Renderer.render_many), got {type(frame).__name__}")
            if not cv2.imwrite(str(folder / f"{prefix}_{frame.row:05d}.png"), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)):
                raise PerceptionError(f"OpenCV could not write {folder / f'{prefix}_{frame.row:05d}.png'}")
            tv = frame.target
            box = [] if tv is None or tv.box is None else [f"{x:g}" for x in tv.box]
            full = [] if tv is None or tv.full_box is None else [f"{x:g}" for x in tv.full_box]
            out.writerow([frame.row, f"{frame.t:.6g}", *(box or [""] * 4), *(full or [""] * 4),
                          "" if tv is None else f"{tv.visible_fraction:.4f}"])
            count += 1
    return count
