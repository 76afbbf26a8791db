"""Region mode's hint as a candidate (``RegionSettings.hint_candidate``,
mysim_jax/perception/detect/model.py): with the committed detector, where the first stage
proposes nothing the hint's box alone finds the target; where the first stage already has
the target the hint adds no duplicate (the same detections as without it); on frames
without a target it adds no detection; bad settings are refused."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.detect.dataset import DatasetSpec, counted_samples, render_sample
from mysim_jax.perception.detect.metrics import iou


@pytest.fixture(scope="module")
def detector():
    from mysim_jax.perception.detect.model import load_detector

    return load_detector()


def _hinted(detector, **kw):
    return replace(detector, region=replace(detector.region, hint_candidate=True, **kw))


def _targets(n: int):
    return counted_samples(DatasetSpec(split="held_out", n_images=40, seed=4242, p_empty=0.0, p_occluder=0.0,
                                       p_distractors=0.0), n)


def test_the_hint_alone_finds_the_target_and_adds_no_duplicate(detector):
    from mysim_jax.perception.detect.refine import Refiner

    blind = replace(detector, refiner=Refiner(detector.refiner.members,
                                              replace(detector.refiner.settings, candidate_min_score=0.999)))
    found = same = 0
    for s in _targets(6):
        side = float(max(s.box[2] - s.box[0], s.box[3] - s.box[1]))
        centre = (s.box[:2] + s.box[2:]) / 2 + np.array([2.0, -1.0])
        assert blind.detect_region(s.image, centre, side) == []         # the first stage proposes nothing
        alone = _hinted(blind).detect_region(s.image, centre, side)
        found += bool(alone) and iou(alone[0].box, s.box) >= 0.5
        plain = detector.detect_region(s.image, centre, side)
        if plain and iou(plain[0].box, s.box) >= 0.5 and plain[0].score > 0.6:    # above any hint's score
            hinted = _hinted(detector).detect_region(s.image, centre, side)
            assert [d.box.tolist() for d in hinted] == [d.box.tolist() for d in plain]
            same += 1
    assert found >= 5 and same >= 4, (found, same)


def test_no_target_no_detection_from_the_hint(detector):
    spec = DatasetSpec(split="held_out", n_images=6, seed=4243, p_empty=1.0, p_occluder=0.0, p_distractors=0.0)
    for i in range(6):
        s = render_sample(spec, i)
        dets = _hinted(detector).detect_region(s.image, np.asarray(s.meta["pixel"]), 20.0)
        assert not [d for d in dets if d.score >= 0.3]


def test_bad_hint_settings_are_refused():
    from mysim_jax.perception.detect.model import RegionSettings

    with pytest.raises(PerceptionError, match="hint_score"):
        RegionSettings(hint_candidate=True, hint_score=0.0)
    with pytest.raises(PerceptionError, match="hint_overlap"):
        RegionSettings(hint_overlap=1.5)
