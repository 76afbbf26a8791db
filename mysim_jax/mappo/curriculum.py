"""The training curriculum's stage, advanced by every training iteration (``env.curriculum``).

Where a run's curriculum stands is a :class:`CurriculumState`, a field of the trainer's
:class:`~mysim_jax.mappo.trainer.TrainerState`: it is checkpointed with the rest of the
run, so a resumed run continues the curriculum from its checkpoint alone. The rule is
:class:`Curriculum`'s, written in ``jax.numpy`` so that it runs inside the trainer's
compiled iteration (:meth:`~mysim_jax.mappo.trainer.Trainer.iterations` scans it with the
rest, vmapped over seeds alike): after each iteration it counts the iteration's training
success rate and, when the stage changes, the next iteration draws its episodes from the
new stage's ranges (:meth:`Curriculum.ranges`, by default
:func:`~mysim_jax.tasks.capture.scaled_target_ranges` of the environment's full ranges).
The rule is :class:`~mysim_jax.mappo.config.CurriculumConfig`'s: advance once the mean
success rate over the last ``window`` iterations of the stage (iterations in which no
episode ended are skipped) reaches ``advance_success``, or after ``max_iterations``
iterations in the stage.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
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
    """The stage rule of ``config`` (a CurriculumConfig), applied to a :class:`CurriculumState`;
    ``scale(ranges, fraction)`` gives a stage's episode ranges from the full ones."""

    def __init__(self, config, scale: Callable | None = None):
        self.config = config
        self.scale = scale

    def start(self) -> CurriculumState:
        return CurriculumState.start(self.config.window)

    def fraction(self, cs: CurriculumState) -> float:
        """The stage's fraction of the full ranges (a host value; traced: :meth:`fraction_of`)."""
        return float(self.config.stages[self.stage(cs)])

    def fraction_of(self, cs: CurriculumState):
        """The stage's fraction of the full ranges, ``()`` float32, traceable."""
        return jnp.asarray(self.config.stages, jnp.float32)[cs.stage]

    def ranges(self, full, cs: CurriculumState):
        """The episode ranges of ``cs``'s stage, from the environment's ``full`` ranges (traceable)."""
        if self.scale is None:
            raise ValueError("Curriculum: no scale(ranges, fraction) to give a stage's ranges")
        return self.scale(full, self.fraction_of(cs))

    def stage(self, cs: CurriculumState) -> int:
        stage = int(cs.stage)
        if not 0 <= stage < len(self.config.stages):
            raise ValueError(f"curriculum stage {stage} of {len(self.config.stages)}")
        return stage

    def last_stage(self, cs: CurriculumState) -> bool:
        return self.stage(cs) == len(self.config.stages) - 1

    def update(self, cs: CurriculumState, success_rate) -> tuple[CurriculumState, jnp.ndarray]:
        """Count one iteration of the current stage with its training success rate (NaN
        when no episode ended): ``(new state, whether the curriculum moved to the next
        stage)`` (a ``()`` bool array), the move taking effect from the next iteration on.
        Traceable: the trainer's iteration runs it."""
        c = self.config
        rate = jnp.asarray(success_rate, jnp.float32)
        count = cs.iterations_in_stage + 1
        finite = jnp.isfinite(rate)
        recent = jnp.where(finite, jnp.append(cs.recent[1:], jnp.where(finite, rate, 0.0)), cs.recent)
        n = jnp.where(finite, jnp.minimum(cs.n_recent + 1, c.window), cs.n_recent)
        last = cs.stage >= len(c.stages) - 1
        by_success = jnp.bool_(False)
        if c.advance_success is not None:
            by_success = (n == c.window) & (jnp.sum(recent) / c.window >= jnp.float32(c.advance_success))
        by_count = jnp.bool_(False)
        if c.max_iterations is not None:
            by_count = count >= c.max_iterations
        moved = ~last & (by_success | by_count)
        stay = CurriculumState(stage=cs.stage, iterations_in_stage=count.astype(jnp.int32), recent=recent,
                               n_recent=n.astype(jnp.int32))
        advance = CurriculumState(stage=(cs.stage + 1).astype(jnp.int32), iterations_in_stage=jnp.int32(0),
                                  recent=jnp.zeros_like(cs.recent), n_recent=jnp.int32(0))
        return jax.tree.map(lambda a, b: jnp.where(moved, a, b), advance, stay), moved
