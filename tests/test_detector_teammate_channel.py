"""The second stage's teammate channel (mysim_jax/perception/detect/refine.py,
refine_train.py, ``refine.teammate_channel``): the mask against hand-placed pixels, a
widened three-channel network computes exactly what it did whatever the mask holds, the
mask reaches the network through ``detect_region``'s teammates, training windows carry it
(mirrored with them, untouched by the photometric changes), and the script fine-tunes a
three-channel second stage into a four-channel one."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import yaml

from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.detect.refine import input_channels, teammate_masks, widen_input


def _refiner(channels: int, seed: int = 0):
    import jax

    from mysim_jax.perception.detect.refine import RefineNet, Refiner, RefineSettings

    settings = RefineSettings(widths=(4, 8, 8), hidden=8, size=32)
    net = RefineNet(widths=settings.widths, hidden=settings.hidden)
    return Refiner([net.init(jax.random.PRNGKey(seed), np.zeros((1, 32, 32, channels), np.float32))["params"]],
                   settings)


def test_the_mask_covers_the_window_pixels_whose_centres_are_in_a_teammate_box():
    # a 10 x 6 px box (renderer coordinates: pixel centres 10..19 and 4..9) in a window of
    # side 32 px at (8, 2), resized to 16 px (each window pixel 2 image pixels)
    box = np.array([[9.5, 3.5, 19.5, 9.5]])
    mask = teammate_masks(box, np.array([[8, 2, 32]]), 16)[0]
    want = np.zeros((16, 16), np.uint8)
    # window pixel k spans image edges 8 + 2k .. 10 + 2k (x), its centre at 9 + 2k: inside
    # [10, 20) for k = 1..5; y: centres 3 + 2k inside [4, 10) for k = 1..3
    want[1:4, 1:6] = 255
    np.testing.assert_array_equal(mask, want)
    assert not teammate_masks(None, np.array([[0, 0, 16]]), 8).any()
    assert not teammate_masks(np.zeros((0, 4)), np.array([[0, 0, 16]]), 8).any()
    far = teammate_masks(np.array([[100.0, 100.0, 110.0, 110.0]]), np.array([[0, 0, 16]]), 8)
    assert not far.any()


def test_a_widened_network_computes_what_it_did_whatever_the_mask():
    from mysim_jax.perception.detect.refine import Refiner, apply

    three = _refiner(3, seed=2)
    four = Refiner([widen_input(three.members[0])], three.settings)
    assert input_channels(three.members[0]) == 3 and four.channels == 4 and four.uses_teammates
    rng = np.random.default_rng(0)
    windows = rng.integers(0, 255, (6, 32, 32, 3)).astype(np.uint8)
    masks = rng.integers(0, 2, (6, 32, 32, 1)).astype(np.uint8) * 255
    prior = np.tile(np.array([[0.3, 0.3, 0.7, 0.7]], np.float32), (6, 1))
    p3, b3 = apply(three.model, three.members[0], windows, prior, flip=True)
    p4, b4 = apply(four.model, four.members[0], np.concatenate([windows, masks], -1), prior, flip=True)
    np.testing.assert_allclose(p4, p3, atol=1e-6)
    np.testing.assert_allclose(b4, b3, atol=1e-6)
    with pytest.raises(PerceptionError, match="more than"):
        widen_input(four.members[0], 3)
    with pytest.raises(PerceptionError, match="input channels"):
        Refiner([three.members[0], four.members[0]], three.settings.__class__(widths=(4, 8, 8), hidden=8, size=32,
                                                                              members=2))


def test_the_teammates_reach_a_four_channel_second_stage_through_detect_region():
    """A four-channel second stage (random weights) scores the same candidates differently
    with a teammate box over them than without; without teammates it is the empty mask; a
    three-channel one ignores them."""
    import jax

    from mysim_jax.perception.detect.model import CenterNet, CNNDetector

    params = CenterNet(widths=(4, 4, 4, 4, 4)).init(jax.random.PRNGKey(0), np.zeros((1, 64, 64, 3), np.float32))["params"]
    image = np.random.default_rng(1).integers(0, 255, (72, 128, 3)).astype(np.uint8)
    team = np.array([[40.0, 20.0, 90.0, 60.0]])
    found = {}
    for channels in (3, 4):
        det = CNNDetector(params=params, widths=(4, 4, 4, 4, 4), input_width=128, min_score=0.0,
                          refiner=_refiner(channels, seed=5))
        kw = dict(centre=(64.0, 36.0), side_px=20.0, min_score=0.0)
        # the gate on the team's boxes is a separate step: off, so that only the scores can change
        det.region = dataclasses.replace(det.region, teammate_gate=0.0)
        found[channels] = [[(tuple(np.round(d.box, 4)), round(d.score, 6))
                            for d in det.detect_region(image, **kw, teammates=t)] for t in (None, np.zeros((0, 4)), team)]
    none3, empty3, team3 = found[3]
    none4, empty4, team4 = found[4]
    assert none3 and none3 == empty3 == team3          # three channels: the boxes change nothing
    assert none4 and none4 == empty4                   # no teammates: the empty mask
    assert team4 != none4                              # a teammate over the window: another answer


def test_training_windows_carry_the_mask_mirrored_with_them_and_untouched_by_the_colours():
    from mysim_jax.perception.camera import intrinsics, project
    from mysim_jax.perception.detect.config import DetectorConfig
    from mysim_jax.perception.detect.refine_train import SamplePool, make_sample

    intr = intrinsics(width=64, height=32)
    R, p = np.eye(3), np.zeros(3)                       # OpenCV camera at the origin looking along +z
    uav = [-0.3, 0.0, 3.0]                              # a teammate left of the image centre
    u = project(intr, R, p, np.array([uav]))[0][0, 0]
    meta = dict(scene="uav", uavs=[dict(pos=uav, radius=0.2)], camera_R=R.tolist(), camera_p=p.tolist())
    labels = [dict(box=[28.0, 12.0, 36.0, 20.0], ignore=False, meta=meta)]
    candidates = [[([28.0, 12.0, 36.0, 20.0], 0.9)]]
    images = np.full((1, 32, 64, 3), 100, np.uint8)
    cfg = DetectorConfig.model_validate({"refine": {"size": 32, "p_positive": 1.0, "p_synthetic": 0.0,
                                                    "p_low_res": 0.0, "jitter": 0.0, "teammate_channel": True},
                                         "train": {"photometric": 0.3, "gamma": 0.3}})
    rng = np.random.default_rng(0)
    sides = []
    for _ in range(40):
        cut, *_ = make_sample(images, SamplePool(labels, candidates), cfg, rng)
        assert cut.shape == (32, 32, 4) and set(np.unique(cut[..., 3])) <= {0, 255} and cut[..., 3].any()
        cols = np.nonzero(cut[..., 3].any(0))[0]
        sides.append("left" if cols.mean() < 16 else "right")
    assert u < 32 and {"left", "right"} == set(sides)   # mirrored about half the time, the mask with the window
    assert 10 <= sides.count("left") <= 30
    labels[0]["meta"] = dict(scene="uav")                # frames rendered before the UAVs were listed
    with pytest.raises(PerceptionError, match="render them again"):
        make_sample(images, SamplePool(labels, candidates), cfg, np.random.default_rng(0))


def test_the_script_fine_tunes_a_three_channel_second_stage_into_a_four_channel_one(tmp_path, capsys):
    import jax

    from mysim_jax.perception.detect.config import config_from_dict
    from mysim_jax.perception.detect.model import load_detector
    from mysim_jax.perception.detect.train import refine_init_from
    from test_detector_refine import TINY_ONE, fine_tune_tiny

    start, out = fine_tune_tiny(tmp_path, "teammate_channel: true")
    three = load_detector(start / "detector.msgpack")
    assert three.refiner.channels == 3
    four = load_detector(out / "detector.msgpack")
    assert four.refiner.uses_teammates and input_channels(four.refiner.members[0]) == 4
    k3, k4 = three.refiner.members[0]["down0"]["kernel"], four.refiner.members[0]["down0"]["kernel"]
    assert k4.shape == k3.shape[:2] + (4,) + k3.shape[3:] and np.any(k4[:, :, 3] != 0)     # the new channel learned
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(three.params), jax.tree.leaves(four.params)))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["refine_steps"] == 3 and np.isfinite(metrics["refine_final_loss"])
    # the reverse: a four-channel start with a config without the channel is refused
    plain = config_from_dict(yaml.safe_load(TINY_ONE.replace("members: 1}", "members: 1, fine_tune: true}")))
    with pytest.raises(PerceptionError, match="teammate_channel: true"):
        refine_init_from(plain, out / "detector.msgpack")
