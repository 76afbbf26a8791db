"""The team's own UAVs in a camera's image (mysim_jax/perception/detect/team.py): expected
boxes against the UAVs' rendered pixels, the fit and the gate by hand, the evaluation's
teammate hints, and region mode dropping what a teammate explains."""

from __future__ import annotations

import numpy as np
import pytest

from mysim_jax.perception.camera import CameraPoses, PerceptionError, intrinsics
from mysim_jax.perception.detect.dataset import (DatasetSpec, _Columns, _random_quat, camera_matrix, render_sample,
                                                 scene_config)
from mysim_jax.perception.detect.metrics import iou
from mysim_jax.perception.detect.team import expected_boxes, explained_by_teammates, fit, perturbed_positions
from mysim_jax.perception.ground import GroundTexture
from mysim_jax.perception.render import Renderer
from mysim_jax.perception.render_models import tip_radius


def test_expected_boxes_bound_the_rendered_uavs():
    """UAVs at random attitudes (tilt <= 20 deg) 1.5-20 m in front of a camera pitched 10-70 deg
    down: each one's rendered pixels (the renderer's object ids) have their centre within
    0.1 of the expected box's side of its centre, stick out of it by at most 0.05 side (a
    sphere off the optical axis projects a little wider than ``2 f r / z``), and the box's
    side is 0.9-1.5 x the pixels' longer side. Measured over 35 UAVs (seeds 0-3): centre
    0.079 side, out 0.033 side, ratio 0.95-1.35."""
    config = scene_config("drone")
    intr = intrinsics(width=640, height=360)
    uav = config.quadrotors[0]
    radius = tip_radius(uav.rotors.arm_length)
    renderer = Renderer(config=config, intr=intr, texture=GroundTexture(seed=0))
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(12):
        R = camera_matrix(rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10, 70)), np.radians(rng.uniform(-10, 10)))
        p = np.array([0.0, 0.0, 30.0])
        ray = R @ np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.2), 1.0])
        pos = p + ray / np.linalg.norm(ray) * np.exp(rng.uniform(np.log(1.5), np.log(20.0)))
        cols = _Columns(config)
        cols.body(uav.body, pos, _random_quat(rng, 20.0))
        frame = renderer.render(cols.cols, CameraPoses(name="observer", t=np.array([0.0]), R=R[None], p=p[None]), 0)
        v, u = np.nonzero(frame.mask(uav.body))
        (box,) = expected_boxes(intr, R, p, pos[None], radius)
        if u.size < 20 or box[0] < 0 or box[1] < 0 or box[2] > 639 or box[3] > 359:
            continue
        drawn = np.array([u.min() - 0.5, v.min() - 0.5, u.max() + 0.5, v.max() + 0.5])
        side = box[2] - box[0]
        drawn_centre = (drawn[:2] + drawn[2:]) / 2
        assert np.linalg.norm(drawn_centre - (box[:2] + box[2:]) / 2) <= 0.1 * side
        assert np.all(drawn[:2] >= box[:2] - 0.05 * side) and np.all(drawn[2:] <= box[2:] + 0.05 * side)
        assert 0.9 <= side / max(drawn[2] - drawn[0], drawn[3] - drawn[1]) <= 1.5
        checked += 1
    assert checked >= 8
    # behind the camera or nearer than the minimum depth: not expected in the image
    R = camera_matrix(0.0, 0.0, 0.0)
    behind = np.array([[-5.0, 0.0, 30.0], [0.05, 0.0, 30.0], [5.0, 0.0, 30.0]])
    assert expected_boxes(intr, R, np.array([0.0, 0.0, 30.0]), behind, radius).shape == (1, 4)
    with pytest.raises(PerceptionError, match="positive radii"):
        expected_boxes(intr, R, np.zeros(3), behind, 0.0)


def test_fit_and_gate_by_hand():
    """The fit is the centre offset over the expected side plus |ln size ratio|; a detection is
    a teammate's when it fits a teammate's box below the gate and the target's worse by more
    than the margin."""
    box = np.array([[10.0, 10.0, 30.0, 20.0]])       # centre (20, 15), longer side 20
    assert fit(box, (20.0, 15.0), 20.0)[0] == pytest.approx(0.0)
    assert fit(box, (26.0, 23.0), 20.0)[0] == pytest.approx(0.5)          # 10 px off / 20
    assert fit(box, (20.0, 15.0), 40.0)[0] == pytest.approx(np.log(2.0))
    dets = np.array([[0.0, 0.0, 10.0, 10.0],           # on the teammate
                     [50.0, 50.0, 60.0, 60.0],         # on the target
                     [4.0, 4.0, 14.0, 14.0]])          # on the teammate, the target not far off
    team = np.array([[0.0, 0.0, 10.0, 10.0]])
    out = explained_by_teammates(dets, (55.0, 55.0), 10.0, team, gate=0.8, margin=0.0)
    assert out.tolist() == [True, False, True]
    # the third (centre (9, 9)) fits the teammate (centre (5, 5)) at sqrt(32) / 10 = 0.57 and a
    # target expected at (11, 11) at sqrt(8) / 10 = 0.28: the target's
    assert fit(dets[2:], (11.0, 11.0), 10.0)[0] == pytest.approx(np.sqrt(8.0) / 10.0)
    assert explained_by_teammates(dets[2:], (11.0, 11.0), 10.0, team, gate=0.8).tolist() == [False]
    assert explained_by_teammates(dets[2:], (20.0, 20.0), 10.0, team, gate=0.8).tolist() == [True]
    assert explained_by_teammates(dets[2:], (20.0, 20.0), 10.0, team, gate=0.5).tolist() == [False]
    # a margin keeps a detection that fits both about as well
    assert explained_by_teammates(dets[:1], (2.0, 2.0), 10.0, team, gate=0.8, margin=0.5).tolist() == [False]
    assert explained_by_teammates(dets, (55.0, 55.0), 10.0, np.zeros((0, 4)), gate=0.8).tolist() == [False] * 3


def test_perturbed_positions_have_the_stated_errors():
    """Position errors of the stated sigma per axis; the camera turned by a rotation whose
    angle has the stated sigma per axis (chi with 3 degrees of freedom)."""
    rng = np.random.default_rng(0)
    R = camera_matrix(0.3, 0.5, 0.1)
    pos = np.zeros((2000, 3))
    noisy, _ = perturbed_positions(rng, pos, R, 0.05, 0.0)
    assert np.std(noisy, axis=0) == pytest.approx([0.05] * 3, rel=0.06)
    angles = []
    for _ in range(2000):
        _, R2 = perturbed_positions(rng, pos[:1], R, 0.0, 0.004)
        angles.append(np.arccos(np.clip((np.trace(R2 @ R.T) - 1) / 2, -1, 1)))
    assert np.sqrt(np.mean(np.square(angles)) / 3) == pytest.approx(0.004, rel=0.06)


def test_teammate_hints_follow_the_drawn_uavs():
    """The evaluation's teammate hints: one box per UAV drawn in the frame, near its exact
    projection (the stated VIO-like errors), the same for the same seed; labels without the
    UAVs drawn are an error."""
    from mysim_jax.perception.detect.train import _label, teammate_hints

    spec = DatasetSpec(split="held_out", n_images=12, seed=4, p_empty=0.0, p_distractors=1.0, p_occluder=0.0)
    labels = [_label(render_sample(spec, i)) for i in range(12)]
    hints = teammate_hints(labels, 9, 640, 360)
    assert [len(h) for h in hints] == [
        len(expected_boxes(intrinsics(width=640, height=360), np.array(lab["meta"]["camera_R"]),
                           np.array(lab["meta"]["camera_p"]), [u["pos"] for u in lab["meta"]["uavs"]],
                           [u["radius"] for u in lab["meta"]["uavs"]])) if lab["meta"]["uavs"] else 0
        for lab in labels]
    assert sum(len(h) for h in hints) >= 6
    again = teammate_hints(labels, 9, 640, 360)
    assert all(np.array_equal(a, b) for a, b in zip(hints, again))
    labels[0]["meta"].pop("uavs")
    with pytest.raises(PerceptionError, match="render them again"):
        teammate_hints(labels, 9, 640, 360)


def test_region_mode_drops_a_detection_a_teammate_explains():
    """The committed detector in region mode: a target it finds is dropped when a teammate is
    expected exactly there and the hint's size is three times off (fit 0 against ln 3), and
    kept when the teammates are elsewhere or the hint fits it as well."""
    from mysim_jax.perception.detect.model import load_detector

    detector = load_detector()
    spec = DatasetSpec(split="held_out", n_images=30, seed=12345, p_empty=0.0, p_occluder=0.0, p_distractors=0.0)
    done = 0
    for i in range(30):
        s = render_sample(spec, i)
        if s.box is None or s.ignore:
            continue
        side = float(max(s.box[2] - s.box[0], s.box[3] - s.box[1]))
        centre = (s.box[:2] + s.box[2:]) / 2
        plain = detector.detect_region(s.image, centre, side)
        if not plain or iou(plain[0].box, s.box) < 0.5:
            continue
        on_it = plain[0].box[None]
        wide = [d for d in detector.detect_region(s.image, centre, 3 * side, teammates=on_it)
                if iou(d.box, plain[0].box) > 0.9]
        assert wide == []
        elsewhere = detector.detect_region(s.image, centre, side, teammates=on_it + 200.0)
        assert [d.box.tolist() for d in elsewhere] == [d.box.tolist() for d in plain]
        kept = detector.detect_region(s.image, centre, side, teammates=on_it)
        assert kept and iou(kept[0].box, s.box) >= 0.5
        done += 1
        if done == 3:
            break
    assert done == 3
    from mysim_jax.perception.detect.model import RegionSettings
    with pytest.raises(PerceptionError, match="teammate_gate and teammate_margin"):
        RegionSettings(teammate_margin=-0.1)


def test_region_detector_passes_the_teammates_to_a_detector_that_takes_them():
    """RegionDetector hands a hint's teammates to ``detect_region`` when it has a
    ``teammates`` parameter, and calls one without it as before."""
    from types import SimpleNamespace

    from mysim_jax.perception.track_detectors import RegionDetector, RegionHint

    seen = []

    def takes(image, centre, side, region, teammates=None):
        seen.append(teammates)
        return []

    def plain(image, centre, side, region):
        seen.append("plain")
        return []

    frame = SimpleNamespace(image=np.zeros((8, 8, 3), np.uint8))
    boxes = np.array([[1.0, 2.0, 3.0, 4.0]])
    hint = RegionHint(centre=np.array([4.0, 4.0]), side=3.0, teammates=boxes)
    RegionDetector(SimpleNamespace(detect=lambda image: [], detect_region=takes))(frame, hint)
    RegionDetector(SimpleNamespace(detect=lambda image: [], detect_region=takes))(
        frame, RegionHint(centre=np.array([4.0, 4.0]), side=3.0))
    RegionDetector(SimpleNamespace(detect=lambda image: [], detect_region=plain))(frame, hint)
    assert seen[0] is boxes and seen[1] is None and seen[2] == "plain"
