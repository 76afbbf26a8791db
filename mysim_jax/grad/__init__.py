"""Gradients through the capture task: a smooth capture objective on rollouts of the
capture environment, its gradient with respect to the scripted team's parameters and to
a rollout's actions, a zeroth-order (randomised-smoothing) estimate of the same gradient,
and the map of where the two agree (:mod:`.gradmap`, ``scripts/gradmap.py``).

The package sits in the layer above :mod:`mysim_jax.tasks` and below
:mod:`mysim_jax.mappo`: it needs the capture environment and the scripted teams (which
:mod:`mysim_jax.tuning`, below the tasks, cannot import), and a first-order learner in
the trainer can reuse its objective and rollouts.

* :mod:`.objective` — the objective's terms (with units) on one environment's state;
* :mod:`.team` — the scripted team's continuous fields as a parameter vector;
* :mod:`.smoothing` — the antithetic Gaussian-smoothing gradient estimator;
* :mod:`.rollout` — closed-loop and open-loop policy steps, the forward rollout and the
  backward pass (reverse mode one policy step at a time, with optional truncation and
  clipping);
* :mod:`.segments` — where an episode's free flight, tether switches and contact start;
* :mod:`.gradmap` — the measurement and its statistics; :mod:`.gradmap_run` writes the
  map's files (JSON, CSV, plots).
"""
