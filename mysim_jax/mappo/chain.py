"""Two training files trained one after the other: ``run.then``.

A training file may name the file to train next (``run.then``, a path relative to the
file). When its run has ended, that file trains from the run's final policy into
``OUT/then/``, a run folder of its own: its ``algo.init`` must be ``policy``, and its
``algo.init_policy`` is replaced by ``../policy`` (the first run's ``OUT/policy``). What
the chain trains is therefore exactly the first file followed by the second started from
the first's policy, the two commands one after the other. The chain's team is the second
run's policy, ``OUT/then/policy``; each run evaluates as its own ``run:`` says.

Everything that can refuse the second file is checked before the first run starts: the
file, its scene, its networks against the first's
(:func:`mysim_jax.mappo.run_files.prepare_then`, when the run is prepared; no JAX) and
what its environment's observations and actions mean against the first's
(:func:`check_chain_environments`). The second run's files are written into
``OUT/then/`` with the first's, so ``--resume OUT`` continues the chain from the folder
alone, whichever run it stopped in.

A chain has two files (the second file's own ``run.then`` is refused) and one seed: the
first run's ``run.seed`` (as ``--set run.seed=N`` makes it) replaces the second file's, so
``--set run.seed=N`` trains another seed of the whole chain; the log names it. Overrides
of the second file are ``--set then.KEY=VALUE``
(:func:`mysim_jax.mappo.run_files.split_then`).
"""

from __future__ import annotations

import jax

from mysim_jax.core.config_base import ConfigError
from mysim_jax.mappo.policies import PolicyError, check_trained_on, widen_policy
from mysim_jax.mappo.run import make_environment, train_run
from mysim_jax.mappo.run_files import THEN_DIR, prepare
from mysim_jax.tasks.contract import environment_contract


def check_chain_environments(p) -> None:
    """ConfigError unless the second run's environment means what the first's does (its
    observations and actions; :func:`mysim_jax.mappo.policies.check_trained_on` on the
    record the first run's policy will carry). Builds both environments; compiles
    nothing."""
    env, params = make_environment(p)
    env2, params2 = make_environment(p.then)
    meta = {"obs_size": env.obs_size, "action_shape": list(env.action_shape)}
    if hasattr(env, "scene"):
        meta["environment"] = environment_contract(env, params)
    try:
        where = f"{p.source}: run.then {p.config.run.then}: this run's policy"
        check_trained_on(widen_policy(meta, None, env2, params2, where)[0], env2, params2, where)
    except PolicyError as err:
        raise ConfigError(str(err)) from None


def first_run_done(p) -> bool:
    """Whether a resumed chain's first run has ended (its ``summary.json`` is written last)."""
    return p.resume and (p.out / "summary.json").is_file()


def train_chain(p, progress: bool = True, evaluate: bool = True, log=print) -> list[dict]:
    """Train the run ``p`` and, with ``run.then``, the file it names from its policy
    (module docstring). Returns each run's ``summary.json`` dict (the first run's is
    empty when a resumed chain had finished it)."""
    if p.then is None:
        return [train_run(p, progress, evaluate, log)]
    if jax.process_count() > 1:
        raise ConfigError(f"{p.source}: run.then with several processes: a chain runs in one process")
    first = {}
    if not first_run_done(p):
        if not p.resume:
            check_chain_environments(p)
        first = train_run(p, progress, evaluate, log)
    else:
        log(f"{p.out}: the first run of the chain has ended; continuing with {p.out / THEN_DIR}")
    second = prepare(None, resume=str(p.out / THEN_DIR))
    log(f"then: {second.config.name} from {p.out / 'policy'}, seed {second.config.run.seed} (the chain's), "
        f"writing {second.out}/")
    return [first, train_run(second, progress, evaluate, log)]
