"""The training curriculum's stage, advanced between iterations (``env.curriculum``).

Where a run's curriculum stands is a :class:`CurriculumState`, a field of the trainer's
:class:`~mysim_jax.mappo.trainer.TrainerState`: it is checkpointed with the rest of the
run, so a resumed run continues the curriculum from its checkpoint alone. The rule is
:class:`Curriculum`'s, plain Python run between iterations by the run loop
(:func:`mysim_jax.mappo.run.train_run`), which feeds it each iteration's training success
rate and, when it moves to the next stage, gives the trainer that stage's episode ranges
(:meth:`~mysim_jax.mappo.trainer.Trainer.with_episode_ranges` with
:func:`~mysim_jax.tasks.capture.scaled_target_ranges`). The rule is
:class:`~mysim_jax.mappo.config.CurriculumConfig`'s: advance once the mean success rate over
the last ``window`` iterations of the stage (iterations in which no episode ended are
skipped) reaches ``advance_success``, or after ``max_iterations`` iterations in the
stage.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class CurriculumState:
    """Where a run's curriculum stands (all zeros for a run without one)."""

    stage: jnp.ndarray                # () int32, index into env.curriculum.stages
    iterations_in_stage: jnp.ndarray  # () int32, training iterations counted in this stage
    recent: jnp.ndarray               # (window,) float32, the stage's latest finite success rates, oldest first
    n_recent: jnp.ndarray             # () int32, how many of ``recent`` hold a rate (the last n_recent)

    @classmethod
    def start(cls, window: int = 1) -> "CurriculumState":
        """The first stage, nothing counted yet, a window of ``window`` rates."""
        return cls(stage=jnp.int32(0), iterations_in_stage=jnp.int32(0),
                   recent=jnp.zeros((window,), jnp.float32), n_recent=jnp.int32(0))


class Curriculum:
    """The stage rule of ``config`` (a CurriculumConfig), applied to a :class:`CurriculumState`."""

    def __init__(self, config):
        self.config = config

    def start(self) -> CurriculumState:
        return CurriculumState.start(self.config.window)

    def fraction(self, cs: CurriculumState) -> float:
        """The stage's fraction of the full ranges."""
        return float(self.config.stages[self.stage(cs)])

    def stage(self, cs: CurriculumState) -> int:
        stage = int(cs.stage)
        if not 0 <= stage < len(self.config.stages):
            raise ValueError(f"curriculum stage {stage} of {len(self.config.stages)}")
        return stage

    def last_stage(self, cs: CurriculumState) -> bool:
        return self.stage(cs) == len(self.config.stages) - 1

    def update(self, cs: CurriculumState, success_rate: float) -> tuple[CurriculumState, bool]:
        """Count one iteration of the current stage with its training success rate (NaN
        when no episode ended): ``(new state, whether the curriculum moved to the next
        stage)``, the move taking effect from the next iteration on."""
        c = self.config
        stage, count = self.stage(cs), int(cs.iterations_in_stage) + 1
        recent = np.asarray(cs.recent, np.float32)
        n = int(cs.n_recent)
        if success_rate is not None and math.isfinite(success_rate):
            recent = np.append(recent[1:], np.float32(success_rate))
            n = min(n + 1, c.window)
        if self.last_stage(cs):
            return self._state(stage, count, recent, n), False
        by_success = (c.advance_success is not None and n == c.window
                      and float(np.sum(recent.astype(np.float64))) / c.window >= c.advance_success)
        by_count = c.max_iterations is not None and count >= c.max_iterations
        if by_success or by_count:
            return self._state(stage + 1, 0, np.zeros_like(recent), 0), True
        return self._state(stage, count, recent, n), False

    @staticmethod
    def _state(stage: int, count: int, recent: np.ndarray, n: int) -> CurriculumState:
        return CurriculumState(stage=jnp.int32(stage), iterations_in_stage=jnp.int32(count),
                               recent=jnp.asarray(recent, jnp.float32), n_recent=jnp.int32(n))
