"""What both stages of the detector's training share (:mod:`~mysim_jax.perception.detect.train`
trains the first, :mod:`~mysim_jax.perception.detect.refine_train` the second): ground truth
from the labels, the photometric augmentation, batches made ahead by a background thread and
the step loop with its progress bar."""

from __future__ import annotations

import queue
import threading

import numpy as np
from tqdm.auto import tqdm

from mysim_jax.perception.detect.config import DetectorConfig
from mysim_jax.perception.detect.dataset import is_ignored


def truths(labels: list[dict], count_truncated: bool = False, cfg: DetectorConfig | None = None) -> list[list]:
    """Ground truth per frame as the metrics take it: [(box, ignore)] or [].

    ``count_truncated``: count targets however much of them the image border cuts off (the
    share of the silhouette within the image decides, not of the whole; ``cfg.data`` gives the
    thresholds), instead of the labels' ``ignore``."""
    if not count_truncated:
        return [[] if lab["box"] is None else [(np.asarray(lab["box"]), lab["ignore"])] for lab in labels]
    d = cfg.data
    return [[] if lab["box"] is None else
            [(np.asarray(lab["box"]), is_ignored(lab["visible_px"], lab["visible_fraction"], 0.0, d.min_visible_px,
                                                 d.min_visible_fraction))]
            for lab in labels]


def photometric(crop: np.ndarray, t, rng: np.random.Generator) -> np.ndarray:
    """``crop`` (uint8 RGB) with the photometric augmentation of the train settings ``t``: a
    random gamma, contrast (about the mean) and saturation (about each pixel's grey), a
    brightness gain and offset and per-channel (white balance) gains."""
    if not (t.photometric > 0 or t.colour_jitter > 0 or t.gamma > 0 or t.contrast > 0 or t.saturation > 0):
        return crop
    x = crop.astype(np.float32) * (1.0 / 255.0)
    x = x ** np.float32(np.exp(rng.uniform(-t.gamma, t.gamma)))
    if t.contrast > 0:          # about the crop's mean
        mean = x.mean()
        x = mean + (x - mean) * np.float32(np.exp(rng.uniform(np.log(1 - t.contrast), np.log(1 + t.contrast))))
    if t.saturation > 0:        # about each pixel's grey (Rec. 601 luma); 0 is a grey image
        grey = x @ np.array([0.299, 0.587, 0.114], np.float32)
        x = grey[..., None] + (x - grey[..., None]) * np.float32(rng.uniform(1 - t.saturation, 1 + t.saturation))
    gain = np.exp(rng.uniform(np.log(1 - t.photometric), np.log(1 + t.photometric)))
    gain = gain * (1 + rng.uniform(-t.colour_jitter, t.colour_jitter, 3))
    x = x * gain.astype(np.float32) + np.float32(rng.uniform(-0.05, 0.05) if t.photometric > 0 else 0.0)
    return np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)


def prefetch(make, n: int, depth: int = 2):
    """The results of ``n`` calls of ``make()``, made in order by a background thread up to
    ``depth`` ahead (the crops are cut while the network trains on the previous batch)."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def work():
        try:
            for _ in range(n):
                item = make()
                while not stop.is_set():
                    try:
                        q.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
        except BaseException as exc:      # re-raised in the consumer
            q.put((None, exc))

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    try:
        for _ in range(n):
            item, exc = q.get()
            if exc is not None:
                raise exc
            yield item
    finally:
        stop.set()


def run_steps(step, params, opt_state, batches, steps: int, desc: str, rate_key: str, shown: tuple[str, ...],
              progress: bool = True, log=None):
    """The training loop of both stages: ``params, opt_state, loss, parts = step(params,
    opt_state, *batch)`` for each of ``steps`` batches (an iterator of tuples), a progress bar
    showing the running loss and the ``shown`` parts, ``log(step, loss, parts)`` every 20
    steps. A non-finite loss stops it with an error naming ``rate_key``. Returns (params,
    [(step, loss)])."""
    history, running = [], None
    bar = tqdm(range(steps), desc=desc, unit="step", disable=not progress)
    for k in bar:
        params, opt_state, loss, parts = step(params, opt_state, *next(batches))
        loss = float(loss)
        if not np.isfinite(loss):
            raise FloatingPointError(f"{desc}: the loss became {loss} at step {k}; lower {rate_key}")
        running = loss if running is None else 0.95 * running + 0.05 * loss
        history.append((k, loss))
        if k % 20 == 0:
            bar.set_postfix(loss=f"{running:.3f}", **{key: f"{float(parts[key]):.4f}" for key in shown})
            if log is not None:
                log(k, loss, {key: float(v) for key, v in parts.items()})
    return params, history
