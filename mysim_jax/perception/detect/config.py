"""The detector training config (``configs/detector.yaml``), validated without importing JAX.

Unknown keys, booleans given for numbers, non-positive sizes or counts, probabilities outside
[0, 1] and crops that do not fit the image are errors naming the field
(:class:`~mysim_jax.core.config_base.ConfigError`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationError, model_validator

from mysim_jax.core.config_base import (ConfigError, PosFloat, StrictModel, format_validation_error, read_yaml_file)

PosInt = Annotated[int, Field(gt=0)]
Prob = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
Pixels = Annotated[int, Field(ge=32, le=4096)]


class DataConfig(StrictModel):
    """Rendered frames (:mod:`mysim_jax.perception.detect.dataset`)."""

    width: Pixels = 640                  # px
    height: Pixels = 360                 # px
    train_images: PosInt = 3000          # training frames (split 'train')
    eval_images: PosInt = 300            # frames of each evaluation set (held-out; in-distribution)
    seed: Annotated[int, Field(ge=0)] = 0
    eval_seed: Annotated[int, Field(ge=0)] | None = None   # evaluation frames' seed (default: seed)
    p_empty: Prob = 0.1
    p_occluder: Prob = 0.25
    # training frames' occluder probability, if not p_occluder (evaluation sets keep p_occluder)
    train_p_occluder: Prob | None = None
    p_distractors: Prob = 0.5
    p_drone: Prob = 0.5
    p_onboard: Prob = 0.0                # frames from a camera under a UAV of the capture formation
    p_random_palette: Prob = 0.0         # training frames with random sky and ground colours
    min_visible_px: Annotated[int, Field(ge=1)] = 6
    min_visible_fraction: Prob = 0.3
    workers: Annotated[int, Field(ge=1, le=64)] = 2     # rendering processes


class ModelConfig(StrictModel):
    widths: Annotated[list[PosInt], Field(min_length=5, max_length=5)] = [16, 32, 48, 64, 96]  # channels, strides 2..32
    input_width: Annotated[int, Field(ge=64, le=4096, multiple_of=32)] = 640    # px, images resized to this
    # inference image pyramid: scales of input_width the network runs at, and the box sides
    # (network px, lo, hi) each level keeps (mysim_jax/perception/detect/model.py)
    pyramid: Annotated[list[Annotated[float, Field(gt=0.0, le=4.0)]], Field(min_length=1, max_length=6)] = [1.0]
    pyramid_band_px: tuple[Annotated[float, Field(ge=0.0)], PosFloat] = (24.0, 96.0)
    flip_test: bool = False      # also run on the mirrored image and average (twice the work)

    @model_validator(mode="after")
    def _pyramid(self):
        if len(set(self.pyramid)) != len(self.pyramid):
            raise ValueError(f"model.pyramid: levels must differ, got {self.pyramid}")
        if self.pyramid_band_px[0] >= self.pyramid_band_px[1]:
            raise ValueError(f"model.pyramid_band_px: lo {self.pyramid_band_px[0]:g} is not below "
                             f"hi {self.pyramid_band_px[1]:g}")
        return self


class DetectorTrainConfig(StrictModel):
    steps: Annotated[int, Field(ge=0)] = 5000   # 0: the first stage is not trained (its weights: --init)
    batch_size: PosInt = 16
    crop: Annotated[int, Field(ge=64, le=4096, multiple_of=32)] = 160   # px, square training crops
    learning_rate: PosFloat = 3e-3
    warmup_steps: Annotated[int, Field(ge=0)] = 50
    weight_decay: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 1e-4
    p_target_crop: Prob = 0.7            # crops chosen to contain the target (else anywhere)
    # where in such a crop its centre falls (fraction of the crop's side, per axis): values
    # outside [0, 1] put the centre beyond the crop's edge, so the target is cut as by the image border
    crop_centre_range: tuple[Annotated[float, Field(ge=-1.0, le=2.0)], Annotated[float, Field(ge=-1.0, le=2.0)]] = (0.05, 0.95)
    scale_range: tuple[PosFloat, PosFloat] = (0.6, 1.6)   # random image rescale before cropping
    # random aspect change before cropping: the height is scaled by a further factor in this
    # range (log-uniform), so boxes of every aspect are seen and the size is read from the pixels
    aspect_range: tuple[PosFloat, PosFloat] = (1.0, 1.0)
    hflip: bool = True
    photometric: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.5    # brightness gain in [1 - x, 1 + x] (log-uniform)
    colour_jitter: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.1  # per-channel gain in [1 - x, 1 + x]
    gamma: Annotated[float, Field(ge=0.0, le=2.0)] = 0.3          # gamma exp(U(-x, x))
    contrast: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.0       # contrast gain in [1 - x, 1 + x] (log-uniform)
    saturation: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0     # saturation gain in [1 - x, 1 + x] (1: down to grey)
    size_weight: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 0.5   # of the L1 loss on log box size
    # a target's heatmap positive weighs 1 + hidden_weight * (share of its silhouette the crop
    # does not show: occluded, or cut by the image border or the crop's edge)
    hidden_weight: Annotated[float, Field(ge=0.0, le=100.0, allow_inf_nan=False)] = 0.0
    seed: Annotated[int, Field(ge=0)] = 0

    @model_validator(mode="after")
    def _scale_order(self):
        if self.scale_range[0] > self.scale_range[1]:
            raise ValueError(f"train.scale_range: low {self.scale_range[0]:g} is above high {self.scale_range[1]:g}")
        if self.aspect_range[0] > self.aspect_range[1]:
            raise ValueError(f"train.aspect_range: low {self.aspect_range[0]:g} is above high {self.aspect_range[1]:g}")
        if self.crop_centre_range[0] > self.crop_centre_range[1]:
            raise ValueError(f"train.crop_centre_range: low {self.crop_centre_range[0]:g} is above high "
                             f"{self.crop_centre_range[1]:g}")
        return self


class RefineConfig(StrictModel):
    """The second stage (:mod:`mysim_jax.perception.detect.refine`): its network, how it is
    applied, and its training (:mod:`mysim_jax.perception.detect.refine_train`)."""

    widths: Annotated[list[PosInt], Field(min_length=2, max_length=6)] = [24, 32, 48, 64, 96]  # strides 1, 2, 4, ...
    hidden: PosInt = 128                 # units of the dense layer
    size: Annotated[int, Field(ge=16, le=256, multiple_of=16)] = 64    # px, resized window side
    context: Annotated[float, Field(ge=1.0, le=8.0, allow_inf_nan=False)] = 2.5   # window side / candidate's longer side
    min_window_px: Annotated[float, Field(ge=4.0, le=1024.0, allow_inf_nan=False)] = 16.0
    candidate_min_score: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.02   # first-stage candidates looked at
    max_candidates: Annotated[int, Field(ge=1, le=100)] = 16            # per image, best first
    flip_test: bool = True               # also look at the mirrored window and average
    score: Literal["refined", "geometric"] = "geometric"   # detection score: p2, or sqrt(p1 * p2)
    members: Annotated[int, Field(ge=1, le=8)] = 1   # networks averaged, trained with seeds seed, seed + 1, ...
    teammate_channel: bool = False       # a fourth input: where the team expects its own UAVs in the window
    mask_weight: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 0.0   # of a visible-pixel head's loss
                                         # in training (0: no such head); inference does not use the head
    # training
    steps: PosInt = 4000
    batch_size: PosInt = 64
    learning_rate: PosFloat = 1e-3
    warmup_steps: Annotated[int, Field(ge=0)] = 100
    weight_decay: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 1e-4
    box_weight: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 5.0    # of the L1 on edges (window units)
    p_positive: Prob = 0.35              # samples that are positive candidates
    p_synthetic: Prob = 0.2              # samples that are the target's box moved at random
    p_occluded: Prob | None = None       # of those two kinds, the share from frames with the target behind
                                         # the net or a UAV (none: as the frames come)
    synthetic_jitter: Annotated[float, Field(ge=0.0, le=1.0)] = 0.15    # box sides / log scale, std
    jitter: Annotated[float, Field(ge=0.0, le=1.0)] = 0.05              # every sample's box, std
    p_low_res: Prob = 0.5                # samples cut at a lower resolution
    low_res_max: Annotated[float, Field(ge=1.0, le=8.0)] = 2.0          # up to this many times fewer pixels
    seed: Annotated[int, Field(ge=0)] = 0
    fine_tune: bool = False              # start from the second stage of the --init weights, not a random init

    @model_validator(mode="after")
    def _shares(self):
        if self.p_positive + self.p_synthetic > 1.0:
            raise ValueError(f"refine: p_positive + p_synthetic = {self.p_positive + self.p_synthetic:g} is above 1")
        return self


class EvalConfig(StrictModel):
    min_score: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.3     # operating point of precision / recall
    iou_threshold: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.5
    n_examples: Annotated[int, Field(ge=0, le=100)] = 8          # annotated example images written


class DetectorConfig(StrictModel):
    name: str = "detector"
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    train: DetectorTrainConfig = DetectorTrainConfig()
    refine: RefineConfig | None = None   # the second stage; none: the first stage alone
    eval: EvalConfig = EvalConfig()

    @model_validator(mode="after")
    def _crop_fits(self):
        h_in = round(self.data.height * self.model.input_width / self.data.width)
        if self.train.crop > self.model.input_width or self.train.crop > h_in + 32:
            raise ValueError(f"train.crop: {self.train.crop} px does not fit the {self.model.input_width} x {h_in} px "
                             f"network input (model.input_width, data.width x data.height)")
        return self


def config_from_dict(raw, source: str = "<dict>") -> DetectorConfig:
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: a detector config is a mapping of sections (data, model, train, eval), "
                          f"got {type(raw).__name__}")
    try:
        return DetectorConfig.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(f"{source}: invalid detector config:\n{format_validation_error(err)}") from None


def load_config(path: str | Path) -> DetectorConfig:
    """Read and validate a detector config file."""
    return config_from_dict(read_yaml_file(path), str(path))
