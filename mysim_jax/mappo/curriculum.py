"""The training curriculum's stage, advanced between iterations (``env.curriculum``).

:class:`Curriculum` is plain Python: the run loop (:func:`mysim_jax.mappo.run.train_run`)
feeds it each iteration's training success rate and, when it moves to the next stage,
hands the trainer that stage's episode ranges
(:meth:`~mysim_jax.mappo.trainer.Trainer.set_episode_ranges` with
:func:`~mysim_jax.tasks.capture.scaled_target_ranges`). The rule is
:class:`~mysim_jax.mappo.config.CurriculumConfig`'s: advance once the mean success rate over
the last ``window`` iterations of the stage (iterations in which no episode ended are
skipped) reaches ``advance_success``, or after ``max_iterations`` iterations in the
stage.
"""

from __future__ import annotations

import math


class Curriculum:
    """Stage bookkeeping of one run (``config``: a CurriculumConfig)."""

    def __init__(self, config, stage: int = 0, iterations_in_stage: int = 0):
        if not 0 <= stage < len(config.stages):
            raise ValueError(f"curriculum stage {stage} of {len(config.stages)}")
        self.config = config
        self.stage = stage
        self.iterations_in_stage = iterations_in_stage
        self._recent: list[float] = []

    @property
    def fraction(self) -> float:
        """The current stage's fraction of the full ranges."""
        return float(self.config.stages[self.stage])

    @property
    def last_stage(self) -> bool:
        return self.stage == len(self.config.stages) - 1

    def update(self, success_rate: float) -> bool:
        """Count one iteration of the current stage with its training success rate (NaN
        when no episode ended); returns True when the curriculum moved to the next stage
        (from the next iteration on)."""
        c = self.config
        self.iterations_in_stage += 1
        if success_rate is not None and math.isfinite(success_rate):
            self._recent = (self._recent + [float(success_rate)])[-c.window:]
        if self.last_stage:
            return False
        by_success = (c.advance_success is not None and len(self._recent) == c.window
                      and sum(self._recent) / c.window >= c.advance_success)
        by_count = c.max_iterations is not None and self.iterations_in_stage >= c.max_iterations
        if by_success or by_count:
            self.stage += 1
            self.iterations_in_stage = 0
            self._recent = []
            return True
        return False

    @classmethod
    def resumed(cls, config, rows: list[dict]) -> "Curriculum":
        """The curriculum where a run's ``metrics.csv`` rows left it: every training
        iteration's row (those with a ``curriculum_stage``) replayed through
        :meth:`update`, so a resumed run advances as the uninterrupted one would."""
        cur = cls(config)
        for r in rows:
            if r.get("curriculum_stage") in ("", None):
                continue
            rate = r.get("success_rate")
            cur.update(float(rate) if rate not in ("", None) else float("nan"))
        return cur
