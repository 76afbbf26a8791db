"""The detector's second stage (mysim_jax/perception/detect/refine.py, refine_train.py):
windows against hand-placed pixels, labels by hand, learning on a few steps, the two-stage
detector's interface and files, and the training script on a tiny config (the refine: config errors are
in test_detector.py's test_config_errors)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from mysim_jax.perception.detect.refine import (IGNORE_IOU, POS_IOU, cut_windows, from_window, sample_labels,
                                                to_window, windows_of)


def test_windows_are_squares_around_the_box():
    """A 10 x 4 px box centred at edge coordinates (20, 30) gets a 25 px window (context 2.5)
    centred there; a 2 px box gets the minimum side."""
    box = np.array([[15.0 - 0.5, 28.0 - 0.5, 25.0 - 0.5, 32.0 - 0.5]])     # renderer px: edges 15..25, 28..32
    (x0, y0, side), = windows_of(box, context=2.5, min_px=16)
    assert side == 25 and abs(x0 + side / 2 - 20) <= 0.5 and abs(y0 + side / 2 - 30) <= 0.5
    (_, _, side), = windows_of(np.array([[10.0, 10.0, 12.0, 12.0]]), context=2.5, min_px=16)
    assert side == 16


def test_window_units_round_trip_and_point_at_the_pixels():
    """A white 6 x 6 px square on black: cut in a 24 px window at 3x (72 px), the square's
    box in window units covers the white pixels of the cut (to within the bilinear edge)."""
    image = np.zeros((50, 80, 3), np.uint8)
    image[20:26, 40:46] = 255
    box = np.array([[39.5, 19.5, 45.5, 25.5]])          # renderer px: pixels 40..45, 20..25
    window = windows_of(box, context=4.0, min_px=8)
    assert window[0, 2] == 24
    np.testing.assert_allclose(from_window(to_window(box, window), window), box, atol=1e-12)
    cut = cut_windows(image, window, 72)[0]
    u = to_window(box, window)[0] * 72                 # edges in the cut's px
    white = np.argwhere(cut[..., 0] > 127)
    assert np.all(white[:, 1] >= u[0] - 1) and np.all(white[:, 1] <= u[2] + 1)
    assert np.all(white[:, 0] >= u[1] - 1) and np.all(white[:, 0] <= u[3] + 1)
    assert cut[int((u[1] + u[3]) / 2), int((u[0] + u[2]) / 2), 0] == 255


def test_windows_beyond_the_image_repeat_its_edge():
    image = np.zeros((40, 40, 3), np.uint8)
    image[:, 0] = (10, 20, 30)                         # left column
    cut = cut_windows(image, np.array([[-30, 5, 20]]), 20)[0]          # wholly left of the image
    assert np.all(cut == (10, 20, 30))
    cut = cut_windows(image, np.array([[-10, 5, 20]]), 20)[0]          # half outside: the left column repeats
    assert np.all(cut[:, :10] == (10, 20, 30)) and np.all(cut[:, 11:] == 0)


def test_labels_by_hand():
    """Candidates against one target [0, 0, 10, 10]: IoU 1 is a positive with the target's box
    as its target; IoU 30 / 170 (between IGNORE_IOU and POS_IOU) has no label; IoU 16 / 184
    (below IGNORE_IOU) and far away are negatives. Over an ignored target no candidate above
    IGNORE_IOU has a label; with no target every candidate is a negative."""
    gt = np.array([0.0, 0.0, 10.0, 10.0])
    cands = np.array([[0.0, 0.0, 10.0, 10.0], [7.0, 0.0, 17.0, 10.0], [6.0, 6.0, 16.0, 16.0],
                      [50.0, 50.0, 60.0, 60.0]])
    assert IGNORE_IOU < 30 / 170 < POS_IOU and 16 / 184 < IGNORE_IOU
    label, weight, target = sample_labels(cands, [(gt, False)])
    np.testing.assert_array_equal(label, [1, 0, 0, 0])
    np.testing.assert_array_equal(weight, [1, 0, 1, 1])
    np.testing.assert_array_equal(target[0], gt)
    np.testing.assert_array_equal(target[1:], cands[1:])
    label, weight, _ = sample_labels(cands, [(gt, True)])
    np.testing.assert_array_equal(label, [0, 0, 0, 0])
    np.testing.assert_array_equal(weight, [0, 0, 1, 1])
    label, weight, _ = sample_labels(cands, [])
    np.testing.assert_array_equal(label, [0, 0, 0, 0])
    np.testing.assert_array_equal(weight, [1, 1, 1, 1])


def _tiny_refiner(seed: int = 0, flip: bool = True, score: str = "geometric", members: int = 1):
    import jax

    from mysim_jax.perception.detect.refine import RefineNet, Refiner, RefineSettings

    settings = RefineSettings(widths=(4, 8, 8), hidden=8, size=32, flip_test=flip, score=score, members=members)
    net = RefineNet(widths=settings.widths, hidden=settings.hidden)
    return Refiner([net.init(jax.random.PRNGKey(seed + k), np.zeros((1, 32, 32, 3), np.float32))["params"]
                    for k in range(members)], settings)


def test_refiner_flip_test_is_mirror_symmetric():
    """With its flip test the second stage gives a window and its mirror the same probability
    and mirrored boxes (any parameters: here random ones)."""
    import jax

    from mysim_jax.perception.detect.refine import apply, mirror_window_boxes

    refiner = _tiny_refiner(seed=3)
    rng = np.random.default_rng(0)
    windows = rng.integers(0, 255, (5, 32, 32, 3)).astype(np.uint8)
    prior = np.tile(np.array([[0.3, 0.35, 0.7, 0.6]], np.float32), (5, 1))
    p, box = apply(refiner.model, refiner.members[0], windows, prior, flip=True)
    pm, boxm = apply(refiner.model, refiner.members[0], windows[:, :, ::-1], np.asarray(mirror_window_boxes(prior)),
                     flip=True)
    np.testing.assert_allclose(p, pm, atol=1e-6)
    np.testing.assert_allclose(box, mirror_window_boxes(boxm), atol=1e-6)
    p1, _ = apply(refiner.model, refiner.members[0], windows, prior, flip=False)
    assert not np.allclose(p1, p)       # the flip test does change the answer of an asymmetric network
    assert jax.numpy.all((p >= 0) & (p <= 1))


def test_a_few_refiner_steps_lower_the_loss():
    """Twenty steps on one fixed batch of 8 windows (an orange square, or none) lower the loss
    by more than half."""
    import jax
    import optax

    from mysim_jax.perception.detect.refine import RefineNet, loss_fn

    model = RefineNet(widths=(4, 8, 8), hidden=16)
    rng = np.random.default_rng(0)
    cut = rng.integers(60, 120, (8, 32, 32, 3)).astype(np.uint8)
    label = np.array([1, 0] * 4, np.float32)
    target = np.tile(np.array([[0.3, 0.3, 0.7, 0.7]], np.float32), (8, 1))
    for k in range(0, 8, 2):
        cut[k, 10:22, 10:22] = (240, 110, 15)
    prior = target + rng.normal(0, 0.05, target.shape).astype(np.float32)
    params = model.init(jax.random.PRNGKey(0), np.zeros((1, 32, 32, 3), np.float32))["params"]
    opt = optax.adam(3e-3)
    state = opt.init(params)
    weight = np.ones(8, np.float32)

    @jax.jit
    def step(params, state):
        (loss, _), g = jax.value_and_grad(loss_fn, has_aux=True)(params, model, cut, prior, label, weight, target, 5.0)
        updates, state = opt.update(g, state, params)
        return optax.apply_updates(params, updates), state, loss

    losses = []
    for _ in range(20):
        params, state, loss = step(params, state)
        losses.append(float(loss))
    assert np.all(np.isfinite(losses))
    assert losses[-1] < 0.5 * losses[0], losses


def test_two_stage_detector_saves_loads_and_scores_by_the_second_stage(tmp_path):
    """A detector with a second stage (of two networks): its detections are the second stage's
    (scores and boxes of :meth:`Refiner.refine` on the first stage's candidates, suppressed,
    above the floor); saved and loaded it gives the same detections; a file without one loads
    without one."""
    import jax

    from mysim_jax.perception.detect.model import CenterNet, CNNDetector, _suppress

    params = CenterNet(widths=(4, 4, 4, 4, 4)).init(jax.random.PRNGKey(0), np.zeros((1, 64, 64, 3), np.float32))["params"]
    first = CNNDetector(params=params, widths=(4, 4, 4, 4, 4), input_width=128, min_score=0.0)
    refiner = _tiny_refiner(members=2)
    two = CNNDetector(params=params, widths=(4, 4, 4, 4, 4), input_width=128, min_score=0.0, refiner=refiner)
    image = np.random.default_rng(1).integers(0, 255, (72, 128, 3)).astype(np.uint8)
    floor = refiner.settings.candidate_min_score
    candidates = first.detect(image, min_score=floor)
    assert candidates
    expected = [d for d in _suppress(refiner.refine([image], [candidates])[0]) if d.score >= 0.1]
    got = two.detect(image, min_score=0.1)
    assert len(got) == len(expected)
    assert all(np.allclose(a.box, b.box) and a.score == pytest.approx(b.score) for a, b in zip(got, expected))
    loaded = CNNDetector.load(two.save(tmp_path / "two.msgpack"))
    assert loaded.refiner is not None and loaded.refiner.settings == refiner.settings
    assert len(loaded.refiner.members) == 2
    again = loaded.detect(image, min_score=0.1)
    assert all(np.allclose(a.box, b.box, atol=1e-4) and a.score == pytest.approx(b.score, abs=1e-5)
               for a, b in zip(again, got)) and len(again) == len(got)
    assert CNNDetector.load(first.save(tmp_path / "one.msgpack")).refiner is None


def test_geometric_score_is_the_mean_of_both_stages():
    """The same candidates refined with ``score="refined"`` and ``"geometric"``: the same boxes,
    and the geometric score is sqrt(first-stage score x refined probability) of each."""
    from mysim_jax.perception.detect import Detection

    rng = np.random.default_rng(2)
    image = rng.integers(0, 255, (60, 90, 3)).astype(np.uint8)
    candidates = [Detection(box=np.array([10.0, 12.0, 30.0, 28.0]), score=0.64),
                  Detection(box=np.array([50.0, 5.0, 58.0, 14.0]), score=0.09)]
    refined = _tiny_refiner(score="refined").refine([image], [candidates])[0]
    geometric = _tiny_refiner(score="geometric").refine([image], [candidates])[0]
    assert len(refined) == len(geometric) == 2
    for cand in candidates:            # pair each output with its candidate by the box's centre
        r = min(refined, key=lambda d: np.abs(d.box - cand.box).sum())
        g = min(geometric, key=lambda d: np.abs(d.box - cand.box).sum())
        np.testing.assert_allclose(g.box, r.box)
        assert g.score == pytest.approx(np.sqrt(r.score * cand.score), rel=1e-6)
        assert g.score != pytest.approx(r.score, rel=1e-3)


def test_an_ensemble_averages_its_networks():
    """A second stage of two networks gives each candidate the mean of the probabilities and
    boxes the two networks give alone; a list of the wrong length is refused."""
    from dataclasses import replace

    from mysim_jax.perception.camera import PerceptionError
    from mysim_jax.perception.detect import Detection
    from mysim_jax.perception.detect.refine import Refiner

    rng = np.random.default_rng(4)
    image = rng.integers(0, 255, (60, 90, 3)).astype(np.uint8)
    candidates = [Detection(box=np.array([10.0, 12.0, 30.0, 28.0]), score=0.64),
                  Detection(box=np.array([50.0, 5.0, 58.0, 14.0]), score=0.09)]
    both = _tiny_refiner(seed=5, score="refined", members=2)
    alone = [Refiner([m], replace(both.settings, members=1)) for m in both.members]
    mean = both.refine([image], [candidates])[0]
    each = [r.refine([image], [candidates])[0] for r in alone]
    assert len(mean) == len(each[0]) == len(each[1]) == 2
    for cand in candidates:            # pair each output with its candidate by the box's centre
        pick = lambda dets: min(dets, key=lambda d: np.abs(d.box - cand.box).sum())
        m, a, b = pick(mean), pick(each[0]), pick(each[1])
        assert m.score == pytest.approx(0.5 * (a.score + b.score), rel=1e-5) and a.score != pytest.approx(b.score)
        np.testing.assert_allclose(m.box, 0.5 * (a.box + b.box), atol=1e-4)
    with pytest.raises(PerceptionError, match="2 network"):
        Refiner(both.members[:1], both.settings)
    with pytest.raises(PerceptionError, match="one parameter tree"):
        Refiner(both.members[0], alone[0].settings)


def test_p_occluded_draws_positives_from_hidden_targets_at_its_rate():
    """With ``p_occluded``, positive and synthetic windows come from frames whose target is
    behind the net or a UAV at that rate (here 1 frame of 4 is such a frame); unset, at the
    rate the frames give (each frame here has one positive candidate)."""
    from mysim_jax.perception.detect.config import DetectorConfig
    from mysim_jax.perception.detect.refine_train import SamplePool, make_sample

    scenes = ["net", "none", "distractors", "onboard"]
    labels = [dict(box=[10.0, 10.0, 20.0, 20.0], ignore=False, meta=dict(scene=s)) for s in scenes]
    candidates = [[([10.0, 10.0, 20.0, 20.0], 0.9), ([40.0, 5.0, 50.0, 15.0], 0.1)] for _ in scenes]
    images = np.full((4, 32, 64, 3), 100, np.uint8)
    pool = SamplePool(labels, candidates)
    assert len(pool.positives_by[0]) == 1 and len(pool.counted_by[0]) == 1 and "1 hidden" in repr(pool)

    def hidden_share(p_occluded, n=800):
        cfg = DetectorConfig.model_validate({"refine": {"size": 32, "p_positive": 0.6, "p_synthetic": 0.4,
                                                        "p_occluded": p_occluded, "p_low_res": 0.0}})
        rng = np.random.default_rng(0)
        # every sample is positive or synthetic; the hidden target's frame is the black one
        return np.mean([make_sample(images, pool, cfg, rng)[0].max() < 40 for _ in range(n)])   # others: >= 50

    images[0] = 0
    assert abs(hidden_share(None) - 0.25) < 0.05       # binomial std 0.015 at n = 800
    assert abs(hidden_share(0.6) - 0.6) < 0.06
    assert hidden_share(1.0) == 1.0


TINY_REFINE = ("data: {width: 160, height: 90, train_images: 4, eval_images: 3, workers: 1}\n"
               "model: {widths: [4, 4, 4, 4, 4], input_width: 128}\n"
               "train: {steps: 2, batch_size: 2, crop: 64, warmup_steps: 1}\n"
               "refine: {steps: 3, batch_size: 4, widths: [4, 4, 4], hidden: 8, size: 32, candidate_min_score: 0.01,"
               " warmup_steps: 1, members: 2}\n"
               "eval: {n_examples: 0}\n")
TINY_ONE = TINY_REFINE.replace("members: 2}", "members: 1}")    # one second-stage network


def fine_tune_tiny(tmp_path, refine_options: str, between=None):
    """``TINY_ONE`` trained by scripts/train_detector.py into ``tmp_path/start``, then (after
    ``between(start)``, if given) its second stage fine-tuned with the extra ``refine:``
    options ``refine_options`` (e.g. ``"teammate_channel: true"``; the first stage not trained
    again) from start's weights and cached frames into ``tmp_path/tuned``. Returns (start, tuned)."""
    from test_detector import _train_script

    module = _train_script()
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY_ONE)
    start, tuned = tmp_path / "start", tmp_path / "tuned"
    assert module.main([str(cfg), "--out", str(start), "--no-progress"]) == 0
    if between is not None:
        between(start)
    cfg.write_text(TINY_ONE.replace("steps: 2,", "steps: 0,")
                   .replace("members: 1}", f"members: 1, fine_tune: true, {refine_options}}}"))
    assert module.main([str(cfg), "--out", str(tuned), "--init", str(start / "detector.msgpack"), "--cache",
                        str(start / "cache"), "--no-progress"]) == 0
    return start, tuned


def test_script_trains_and_evaluates_both_stages_on_a_tiny_config(tmp_path, capsys):
    """scripts/train_detector.py with a ``refine:`` section: both stages trained (second-stage
    steps in the log and metrics), the file carries the second stage, and evaluating it with
    ``--weights`` takes the config's inference settings; ``train.steps: 0`` without ``--init``
    is refused before any work."""
    import json

    import jax

    from mysim_jax.perception.detect.model import load_detector
    from test_detector import _train_script

    module = _train_script()
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY_REFINE)
    out = tmp_path / "run"
    assert module.main([str(cfg), "--out", str(out), "--no-progress"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["refine_steps"] == 3 and np.isfinite(metrics["refine_final_loss"])
    log = json.loads((out / "train_log.json").read_text())
    assert {r["member"] for r in log if r.get("stage") == "refine"} == {0, 1}      # both networks trained
    det = load_detector(out / "detector.msgpack")
    assert det.refiner is not None and det.refiner.settings.size == 32 and det.refiner.settings.score == "geometric"
    a, b = (np.concatenate([np.ravel(x) for x in jax.tree.leaves(m)]) for m in det.refiner.members)
    assert a.shape == b.shape and not np.allclose(a, b)         # from seeds refine.seed and refine.seed + 1
    assert isinstance(det.detect(np.zeros((90, 160, 3), np.uint8), min_score=0.0), list)

    cfg.write_text(TINY_REFINE.replace("candidate_min_score: 0.01,", "candidate_min_score: 0.5, score: refined,")
                   .replace("members: 2}", "members: 2, fine_tune: true}"))     # fine_tune: training only
    again = tmp_path / "eval"
    assert module.main([str(cfg), "--out", str(again), "--weights", str(out / "detector.msgpack"), "--no-progress",
                        "--cache", str(out / "cache"), "--eval-images", "2"]) == 0
    evaluated = json.loads((again / "metrics.json").read_text())
    assert evaluated["refine"] is True and evaluated["cnn/held_out"]["n_images"] == 2

    # refine.fine_tune: the second stage starts from the --init file's, which must match the config's
    from mysim_jax.perception.camera import PerceptionError
    from mysim_jax.perception.detect.config import config_from_dict
    from mysim_jax.perception.detect.train import refine_init_from

    tuned = config_from_dict(yaml.safe_load(TINY_REFINE.replace("members: 2}", "members: 2, fine_tune: true}")))
    start = refine_init_from(tuned, out / "detector.msgpack")
    for mine, theirs in zip(start, det.refiner.members):
        assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(mine), jax.tree.leaves(theirs)))
    assert refine_init_from(config_from_dict(yaml.safe_load(TINY_REFINE)), out / "detector.msgpack") is None
    with pytest.raises(PerceptionError, match="members"):
        refine_init_from(config_from_dict(yaml.safe_load(TINY_REFINE.replace("members: 2}", "fine_tune: true}"))),
                         out / "detector.msgpack")
    first_only = tmp_path / "first_only.msgpack"
    det.refiner = None
    det.save(first_only)
    cfg.write_text(TINY_REFINE.replace("members: 2}", "members: 2, fine_tune: true}"))
    capsys.readouterr()
    assert module.main([str(cfg), "--out", str(tmp_path / "none"), "--init", str(first_only)]) == 2
    assert "has none" in capsys.readouterr().err and not (tmp_path / "none").exists()
    assert module.main([str(cfg), "--out", str(tmp_path / "none")]) == 2
    assert "refine.fine_tune" in capsys.readouterr().err and not (tmp_path / "none").exists()

    cfg.write_text(TINY_REFINE.replace("steps: 2,", "steps: 0,"))
    capsys.readouterr()
    assert module.main([str(cfg), "--out", str(tmp_path / "none"), "--no-progress"]) == 2
    assert "train.steps is 0" in capsys.readouterr().err and not (tmp_path / "none").exists()
    assert module.main([str(cfg), "--out", str(tmp_path / "none"), "--weights", str(out / "detector.msgpack"),
                        "--eval-images", "0"]) == 2
    assert "--eval-images 0" in capsys.readouterr().err and not (tmp_path / "none").exists()
