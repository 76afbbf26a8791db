"""The second stage's visible-pixel head (mysim_jax/perception/detect/refine.py,
refine_train.py, ``refine.mask_weight``): the rendered mask is the renderer's visible target
pixels, the masks' file round-trips and a set rendered before them gets the same masks again,
windows cut from a hand-placed mask keep its area and position, training windows carry it
mirrored with them, the head leaves the logit and box as they were, and the script fine-tunes
a second stage without a head into one trained with it."""

from __future__ import annotations

import json

import numpy as np

from mysim_jax.perception.detect.refine import window_masks


def test_a_sample_mask_is_the_visible_target_pixels_over_its_box():
    from mysim_jax.perception.detect.dataset import DatasetSpec, render_sample

    spec = DatasetSpec(split="train", n_images=8, seed=21, p_occluder=1.0)
    seen = 0
    for i in range(8):
        s = render_sample(spec, i)
        if s.box is None:
            assert s.mask is None
            continue
        e = s.box + 0.5
        assert s.mask.shape == (round(e[3] - e[1]), round(e[2] - e[0]))
        assert int(s.mask.sum()) == s.visible_px
        # the box is the visible pixels' box: every edge row and column holds one
        assert s.mask[0].any() and s.mask[-1].any() and s.mask[:, 0].any() and s.mask[:, -1].any()
        seen += s.visible_fraction < 0.95          # some partly hidden behind the occluder
    assert seen >= 2


def test_windows_of_a_mask_keep_its_area_and_place():
    mask = np.zeros((10, 20), bool)
    mask[2:8, 5:15] = True                         # 60 px, image columns 105..114, rows 52..57
    box = np.array([99.5, 49.5, 119.5, 59.5])      # the mask's box: columns 100..119, rows 50..59
    big = window_masks(mask, box, np.array([[90, 30, 64]]), 32)[0]    # shrunk 2x
    assert np.isclose(big.sum() * 4, 60) and big.max() == 1.0
    rows, cols = np.nonzero(big > 0)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (11, 13, 7, 12)   # (52-30)/2 .. (57-30)/2, ...
    # a window away from the target, or past the image's corner, shows nothing; a window over part of it, that part
    edge = window_masks(mask, box, np.array([[-20, -20, 32], [110, 40, 32]]), 32)
    assert edge[0].sum() == 0 and np.isclose(edge[1].sum(), 30)       # columns 110..114 of the mask
    assert window_masks(None, None, np.array([[0, 0, 16]]), 8).sum() == 0


def test_the_masks_file_round_trips_and_an_older_set_gets_the_same_masks(tmp_path):
    from mysim_jax.perception.detect.dataset import DatasetSpec, render_sample
    from mysim_jax.perception.detect.train import _read_masks, build_set, load_masks, set_key

    spec = DatasetSpec(split="train", n_images=5, seed=3, width=160, height=90, p_occluder=0.5, p_empty=0.3)
    images, labels = build_set(spec, tmp_path, "train", workers=1, progress=False)
    path = tmp_path / f"train_{set_key(spec)}_masks.npz"
    written = _read_masks(path)
    direct = [render_sample(spec, i).mask for i in range(5)]
    assert len(written) == 5 and any(m is None for m in direct + [None])
    for a, b, lab in zip(written, direct, labels):
        assert (a is None) == (b is None) == (lab["box"] is None)
        assert a is None or np.array_equal(a, b)
    path.unlink()                                  # as a set cached before the masks were kept
    again = load_masks(spec, tmp_path, "train", workers=1, progress=False)
    assert path.is_file() and all((a is None and b is None) or np.array_equal(a, b) for a, b in zip(again, direct))


def test_training_windows_carry_the_visible_mask_mirrored_with_them():
    from mysim_jax.perception.detect.config import DetectorConfig
    from mysim_jax.perception.detect.refine_train import SamplePool, make_sample

    mask = np.zeros((8, 8), bool)
    mask[:, :3] = True                             # the target shows only its left part
    labels = [dict(box=[27.5, 11.5, 35.5, 19.5], ignore=False, meta=dict(scene="uav"))]
    candidates = [[([27.5, 11.5, 35.5, 19.5], 0.9)]]
    images = np.full((1, 32, 64, 3), 100, np.uint8)
    cfg = DetectorConfig.model_validate({"refine": {"size": 32, "p_positive": 1.0, "p_synthetic": 0.0,
                                                    "p_low_res": 0.0, "jitter": 0.0, "mask_weight": 1.0}})
    pool = SamplePool(labels, candidates, [mask])
    rng = np.random.default_rng(0)
    sides = []
    for _ in range(40):
        cut, prior, target, label, weight, visible, on = make_sample(images, pool, cfg, rng)
        assert visible.shape == (16, 16) and on == 1.0 and label == 1.0
        cols = np.nonzero(visible.any(0))[0]
        centre = (target[0] + target[2]) / 2 * 16  # the box's centre, in mask cells
        sides.append("left" if cols.mean() < centre else "right")
    assert {"left", "right"} == set(sides) and 10 <= sides.count("left") <= 30
    labels[0]["ignore"] = True                     # an ignored target's pixels are not a label
    *_, visible, on = make_sample(images, pool, cfg, np.random.default_rng(1))
    assert on == 0.0 and visible.sum() == 0


def test_the_head_leaves_the_logit_and_box_as_they_were():
    import jax

    from mysim_jax.perception.detect.refine import RefineNet, apply

    net = RefineNet(widths=(4, 8, 8), hidden=8)
    x = np.zeros((3, 32, 32, 3), np.float32)
    with_head = net.init(jax.random.PRNGKey(0), x, with_mask=True)["params"]
    without = {k: v for k, v in with_head.items() if not k.startswith("mask")}
    assert set(with_head) - set(without) and not any(k.startswith("mask") for k in
                                                     net.init(jax.random.PRNGKey(0), x)["params"])
    windows = np.random.default_rng(0).integers(0, 255, (3, 32, 32, 3)).astype(np.uint8)
    prior = np.tile(np.float32([[0.3, 0.3, 0.7, 0.7]]), (3, 1))
    a, b = apply(net, with_head, windows, prior, flip=True), apply(net, without, windows, prior, flip=True)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))
    out, mask = net.apply({"params": with_head}, x, with_mask=True)
    assert out.shape == (3, 5) and mask.shape == (3, 16, 16)


def test_the_script_fine_tunes_a_second_stage_with_the_head(tmp_path):
    from mysim_jax.perception.detect.model import load_detector
    from test_detector_refine import fine_tune_tiny

    def as_before_masks(start):                    # the training frames as cached before the masks were kept
        for mask in (start / "cache").glob("train_*_masks.npz"):
            mask.unlink()

    start, out = fine_tune_tiny(tmp_path, "mask_weight: 1.0", between=as_before_masks)
    before = load_detector(start / "detector.msgpack").refiner.members[0]
    after = load_detector(out / "detector.msgpack").refiner.members[0]
    assert not any(k.startswith("mask") for k in before) and {k for k in after if k.startswith("mask")}
    assert not np.array_equal(before["fc"]["kernel"], after["fc"]["kernel"])
    log = [r for r in json.loads((out / "train_log.json").read_text()) if r.get("stage") == "refine"]
    assert log and all(np.isfinite(r["mask"]) for r in log)
    assert list((start / "cache").glob("train_*_masks.npz"))          # rendered again and kept
