#!/usr/bin/env python
"""Train the learned target detector and compare it with the classical baseline.

    python scripts/train_detector.py configs/detector.yaml --out runs/detector

Renders training frames and two evaluation sets (in-distribution, held-out) of the capture
scenes' targets (mysim_jax/perception/detect/dataset.py), trains the CNN
(mysim_jax/perception/detect/model.py), evaluates it and the OpenCV colour-blob baseline
(mysim_jax/perception/detect/classical.py), and writes into OUT: ``detector.msgpack`` (the
weights; ``load_detector(OUT/detector.msgpack)`` loads them), ``metrics.json`` (precision,
recall, mean IoU, AP@0.5 and frames/s of both detectors on both sets), ``pr_curve.png``,
``examples/*/frame_*.png`` (annotated frames), ``train_log.json`` and ``config.yaml``.
Rendered frames are kept in ``OUT/cache`` (or ``--cache``) and reused by a rerun with the
same data settings. ``--weights FILE`` evaluates FILE instead of training (the evaluation
frames only are rendered):

    python scripts/train_detector.py configs/detector.yaml --weights docs/detector/detector.msgpack --out runs/det_eval

``--init FILE`` fine-tunes: training starts from FILE's weights instead of a random init
(the same ``model.widths``). A config with a ``refine:`` section also trains the second stage
(mysim_jax/perception/detect/refine.py) on the trained first stage's candidates in the
training frames; with ``train.steps: 0`` the first stage is FILE's as it is, and only the
second stage is trained (from FILE's second stage with ``refine.fine_tune: true``):

    python scripts/train_detector.py configs/detector_refine.yaml --init docs/detector/detector.msgpack \
        --out runs/detector_refine

``--modes full region`` also evaluates the CNN in region mode, as gimbal tracking runs it:
around a hint of where the target is, drawn near the truth with the tracker's prediction
errors (``mysim_jax.perception.detect.train.region_hints``); ``cnn_region/...`` in
``metrics.json``. ``region_team`` does the same with the detector also told where the team's
own UAVs appear (``teammate_hints``: from their drawn positions with VIO-like errors), so it
drops detections a teammate explains; ``cnn_region_team/...``. ``region_team_hint``: that, with
the second stage also looking at the hint's box itself (``RegionSettings.hint_candidate``);
``cnn_region_team_hint/...``.

``--eval-seed N`` draws the evaluation frames with seed N instead of ``data.seed`` (fresh frames
of the same splits; the training frames keep ``data.seed``); ``--eval-images N`` makes each
evaluation set N frames instead of ``data.eval_images`` (a larger draw, a tighter estimate).

A bad config (unknown keys, negative sizes, zero images, ...) or an unusable OUT is a
one-line-per-problem error and exit code 2 before anything is rendered or compiled.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="detector config (YAML), e.g. configs/detector.yaml")
    parser.add_argument("--out", default="runs/detector", help="output folder (default runs/detector)")
    parser.add_argument("--cache", help="folder of rendered frames (default OUT/cache)")
    parser.add_argument("--weights", help="evaluate these weights (a detector.msgpack) instead of training, e.g. "
                        "docs/detector/detector.msgpack")
    parser.add_argument("--init", help="fine-tune: start training from these weights (a detector.msgpack of the "
                        "config's model.widths) instead of a random init")
    parser.add_argument("--eval-seed", type=int, help="seed of the evaluation frames (default: the config's "
                        "data.eval_seed, else data.seed)")
    parser.add_argument("--eval-images", type=int, help="frames per evaluation set (default: the config's "
                        "data.eval_images)")
    parser.add_argument("--modes", nargs="+", choices=("full", "region", "region_team", "region_team_hint"),
                        default=["full"],
                        help="how the CNN is evaluated: on the whole image (full, default) and / or around a "
                        "tracker's hint drawn near the truth (region: the mode gimbal tracking uses), and told where the "
                        "team's UAVs are (region_team), and with the hint's box looked at as a candidate (region_team_hint)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)

    from mysim_jax.core.config_base import ConfigError
    from mysim_jax.io.output import OutputError, check_output_dir
    from mysim_jax.perception.detect.config import load_config

    try:
        cfg = load_config(args.config)
        if args.eval_seed is not None:
            if args.eval_seed < 0:
                raise ConfigError(f"--eval-seed {args.eval_seed}: a seed is a whole number >= 0")
            cfg = cfg.model_copy(update={"data": cfg.data.model_copy(update={"eval_seed": args.eval_seed})})
        if args.eval_images is not None:
            if args.eval_images < 1:
                raise ConfigError(f"--eval-images {args.eval_images}: give at least 1 frame per evaluation set")
            cfg = cfg.model_copy(update={"data": cfg.data.model_copy(update={"eval_images": args.eval_images})})
        out = check_output_dir(args.out)
        cache = None if args.cache is None else check_output_dir(args.cache, flag="--cache")
        if args.weights is not None:
            if not Path(args.weights).is_file():
                raise OutputError(f"--weights {args.weights}: no such file (a detector.msgpack)")
            if args.init is not None:
                raise ConfigError("--init fine-tunes a training run; --weights evaluates without training: "
                                  "give one of them")
        if cfg.refine is not None and cfg.refine.fine_tune and args.init is None and args.weights is None:
            raise ConfigError("refine.fine_tune starts the second stage from the --init weights: give them with --init "
                              "(e.g. docs/detector/detector.msgpack)")
        if cfg.train.steps == 0 and args.init is None and args.weights is None:
            raise ConfigError("train.steps is 0, so no first stage is trained: give the weights it starts from "
                              "with --init (e.g. docs/detector/detector.msgpack)")
        if args.init is not None:
            from mysim_jax.perception.camera import PerceptionError
            from mysim_jax.perception.detect.train import init_from, refine_init_from

            try:
                init_from(cfg, args.init)
                refine_init_from(cfg, args.init)
            except PerceptionError as err:
                raise OutputError(f"--init: {err}") from None
    except (ConfigError, OutputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from mysim_jax.perception.detect.train import run

    t0 = time.perf_counter()
    metrics = run(cfg, out, progress=not args.no_progress, cache=cache, weights=args.weights, init=args.init,
                  modes=tuple(args.modes))
    done = (f"evaluated {args.weights}" if args.weights else
            f"trained {cfg.train.steps} steps{f' from {args.init}' if args.init else ''} in "
            f"{metrics['train_seconds']:.0f} s" +
            (f", the second stage {cfg.refine.steps} steps in {metrics['refine_seconds']:.0f} s" if cfg.refine else ""))
    print(f"{done}; wrote {out}/ ({time.perf_counter() - t0:.0f} s in all)")
    names = [n for n in ("cnn", "cnn_region", "cnn_region_team", "cnn_region_team_hint", "baseline") if f"{n}/held_out" in metrics]
    for key in [f"{n}/{set_name}" for set_name in ("held_out", "in_distribution") for n in names]:
        m = metrics[key]
        print(f"  {key:31s} precision {m['precision']:.3f}  recall {m['recall']:.3f}  mean IoU {m['mean_iou']:.3f}  "
              f"AP50 {m['ap50']:.3f}  {m['fps']:.1f} frames/s ({m['n_targets']} targets in {m['n_images']} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
