"""Target detection speed: the learned detector on the whole image and in region mode.

Frames: held-out frames of the detector's dataset (:mod:`mysim_jax.perception.detect.dataset`,
640 x 360, seed ``FRAME_SEED``, the first ``N_FRAMES`` with a counted target: spheres and
drones, near and far, some behind an occluder). Detector: the committed weights
(``docs/detector/detector.msgpack``) as gimbal tracking loads them. Variants, timed
round-robin on the same frames (:func:`mysim_jax.bench.timing.time_round_robin`), one call
= every frame once, reported per frame:

* ``whole image`` — :meth:`CNNDetector.detect <mysim_jax.perception.detect.model.CNNDetector.detect>`:
  the pyramid with the flip test, then the second stage;
* ``region`` — :meth:`CNNDetector.detect_region <mysim_jax.perception.detect.model.CNNDetector.detect_region>`
  around a hint ``HINT_OFFSET_PX`` off the target's true centre, with its true size (the
  mode gimbal tracking runs, :class:`~mysim_jax.perception.track_detectors.RegionDetector`);
* ``region, the hint as a candidate`` — the same with ``RegionSettings.hint_candidate``
  (the second stage also looks at the hint's box);
* ``region, first stage only`` — the same window without the second stage (what the
  second stage costs there).

:func:`section_k` writes BENCHMARKS.md (k).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from mysim_jax.bench.timing import contention_note, median, spread, time_round_robin, wait_for_quiet
from mysim_jax.perception.detect.dataset import DatasetSpec, counted_samples
from mysim_jax.perception.detect.model import load_detector

FRAME_SEED = 2024           # held-out frames no evaluation of the detector draws (its seeds are small)
N_FRAMES = 24
HINT_OFFSET_PX = (6.0, -4.0)


def frames(n: int = N_FRAMES, seed: int = FRAME_SEED) -> list:
    """The first ``n`` held-out samples with a counted target."""
    return counted_samples(DatasetSpec(split="held_out", n_images=4 * n, seed=seed, p_empty=0.0), n)


def hint_of(sample) -> tuple[np.ndarray, float]:
    """(centre (2,) px, side px): the hint the region variants get for ``sample``."""
    b = np.asarray(sample.box, float)
    centre = np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2]) + np.asarray(HINT_OFFSET_PX)
    return centre, float(max(b[2] - b[0], b[3] - b[1]))


def measure(samples, repeats: int, section: str = "k") -> dict[str, list[float]]:
    """Seconds per frame of each variant (the counted rounds)."""
    detector = load_detector()
    stage1 = replace(detector, refiner=None)
    hinted = replace(detector, region=replace(detector.region, hint_candidate=True))
    hints = [hint_of(s) for s in samples]

    def whole():
        for s in samples:
            detector.detect(s.image)

    def region(d):
        def run():
            for s, (c, side) in zip(samples, hints):
                d.detect_region(s.image, c, side)
        return run

    calls = {"whole image": whole, "region": region(detector), "region, the hint as a candidate": region(hinted),
             "region, first stage only": region(stage1)}
    times = time_round_robin(calls, repeats, section=section)
    return {k: [t / len(samples) for t in v] for k, v in times.items()}


def section_k(cfg, results) -> list[str]:
    """(k) Target detection speed (:func:`measure`)."""
    t0 = time.perf_counter()
    samples = frames(8 if cfg.quick else N_FRAMES)
    render_s = time.perf_counter() - t0
    repeats = 3 if cfg.quick else 5
    wait_for_quiet(cfg.max_wait_s, "k")
    times = measure(samples, repeats)
    fps = {k: 1.0 / median(v) for k, v in times.items()}
    results["k"] = fps
    drones = sum(s.kind == "drone" for s in samples)
    lines = [
        "## (k) Target detection",
        "",
        f"The learned detector (`docs/detector/detector.msgpack`, mysim_jax/perception/detect/) on {len(samples)} "
        f"held-out 640 × 360 frames with a target ({drones} drones, {len(samples) - drones} spheres; rendered in "
        f"{render_s:.0f} s), one image per call, no batching: **whole image** (`detect`: the image pyramid with the "
        f"flip test, then the second stage), **region** (`detect_region` around a hint "
        f"{np.hypot(*HINT_OFFSET_PX):.0f} px off the target's centre: the mode gimbal tracking runs, "
        "docs/detector.md), the same with the hint's box as one more candidate of the second stage "
        "(`RegionSettings.hint_candidate`) and the region's first stage alone. Median per frame of the counted rounds, timed "
        f"round-robin (mysim_jax/bench/detect.py). {contention_note('k', repeats)}",
        "",
        "| variant | ms per frame | frames/s | spread |",
        "|---|---:|---:|---:|",
    ]
    for k, v in times.items():
        lines.append(f"| {k} | {1e3 * median(v):.1f} | {fps[k]:.1f} | {spread(v)} |")
    lines += ["", f"Region mode runs {fps['region'] / fps['whole image']:.1f}× the whole image's frame rate; "
              f"the second stage is {1 - fps['region'] / fps['region, first stage only']:.0%} of a region call.", ""]
    return lines
