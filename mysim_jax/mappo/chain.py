"""Two training files trained one after the other: ``run.then``.

A training file may name the file to train next (``run.then``, a path relative to the
file). When its run has ended, that file trains from the run's final policy into
``OUT/then/``, a run folder of its own: its ``algo.init`` must be ``policy``, and its
``algo.init_policy`` is replaced by ``../policy`` (the first run's ``OUT/policy``). What
the chain trains is therefore exactly the first file followed by the second started from
the first's policy, the two commands one after the other. The chain's team is the second
run's policy, ``OUT/then/policy``; each run evaluates as its own ``run:`` says.

Everything that can refuse the second file is checked before the first run starts: the
file, its scene, its networks against the first's (:func:`prepare_then`, no JAX) and
what its environment's observations and actions mean against the first's
(:func:`check_chain_environments`). The second run's files are written into
``OUT/then/`` with the first's, so ``--resume OUT`` continues the chain from the folder
alone, whichever run it stopped in.

A chain has two files (the second file's own ``run.then`` is refused) and one seed.
"""

from __future__ import annotations

from pathlib import Path

from mysim_jax.core.config_base import ConfigError, read_yaml_file
from mysim_jax.mappo.config import load_eval_scene, load_scene, train_config_from_dict

THEN_DIR = "then"                    # the second run's folder, inside the first's
START = "../policy"                  # its starting policy, relative to its train.yaml
NETWORK_FIELDS = ("hidden", "activation", "normalize_obs", "residual")


def then_path(config, source: str | Path) -> Path | None:
    """``run.then``'s file, resolved relative to the training file ``source`` (None
    without one)."""
    if config.run.then is None:
        return None
    p = Path(config.run.then)
    return p if p.is_absolute() else Path(source).parent / p


def prepare_then(config, source: str | Path, out: Path):
    """The second run of a chain whose first run is ``config`` (read from ``source``,
    writing ``out``), checked (module docstring); None when ``config`` has no
    ``run.then``. Raises ConfigError naming the problem; imports no JAX."""
    from mysim_jax.mappo.run_files import Prepared

    path = then_path(config, source)
    if path is None:
        return None
    where = f"{source}: run.then {config.run.then}"
    if config.run.seeds > 1:
        raise ConfigError(f"{where}: a chain trains one seed (run.seeds {config.run.seeds} here); train each seed's "
                          "chain on its own (--set run.seed=N)")
    if not path.is_file():
        raise ConfigError(f"{where}: no such training file ({path}; paths are relative to the training file)")
    raw = read_yaml_file(path, "training file")
    algo = raw.get("algo") if isinstance(raw, dict) else None
    if not isinstance(algo, dict) or algo.get("init") != "policy":
        raise ConfigError(f"{where}: the file trained next starts from this run's policy: give it algo.init: policy "
                          f"(it has {(algo or {}).get('init', 'none') if isinstance(algo, dict) else 'no algo:'})")
    nxt = train_config_from_dict(raw, str(path), [f"algo.init_policy={START}"])
    if nxt.run.then is not None:
        raise ConfigError(f"{where}: that file names run.then {nxt.run.then} itself; a chain has two files")
    if nxt.run.seeds > 1:
        raise ConfigError(f"{where}: a chain trains one seed (run.seeds {nxt.run.seeds} there)")
    differ = [f"{k} {getattr(config.algo, k)!r} here, {getattr(nxt.algo, k)!r} there" for k in NETWORK_FIELDS
              if getattr(config.algo, k) != getattr(nxt.algo, k)]
    if differ:
        raise ConfigError(f"{where}: its networks must be this file's, which it starts from ({'; '.join(differ)})")
    scene = load_scene(nxt, path)
    return Prepared(nxt, scene, Path(out) / THEN_DIR, False, str(path), load_eval_scene(nxt, path, scene))


def check_chain_environments(p) -> None:
    """ConfigError unless the second run's environment means what the first's does (its
    observations and actions; :func:`mysim_jax.mappo.policies.check_trained_on` on the
    record the first run's policy will carry). Builds both environments; compiles
    nothing."""
    from mysim_jax.mappo.policies import PolicyError, check_trained_on
    from mysim_jax.mappo.run import make_environment
    from mysim_jax.tasks.contract import environment_contract

    env, params = make_environment(p)
    env2, params2 = make_environment(p.then)
    meta = {"obs_size": env.obs_size, "action_shape": list(env.action_shape)}
    if hasattr(env, "scene"):
        meta["environment"] = environment_contract(env, params)
    try:
        check_trained_on(meta, env2, params2, f"{p.source}: run.then {p.config.run.then}: this run's policy")
    except PolicyError as err:
        raise ConfigError(str(err)) from None


def first_run_done(p) -> bool:
    """Whether a resumed chain's first run has ended (its ``summary.json`` is written last)."""
    return p.resume and (p.out / "summary.json").is_file()


def train_chain(p, progress: bool = True, evaluate: bool = True, log=print) -> list[dict]:
    """Train the run ``p`` and, with ``run.then``, the file it names from its policy
    (module docstring). Returns each run's ``summary.json`` dict (the first run's is
    empty when a resumed chain had finished it)."""
    import jax

    from mysim_jax.mappo.run import train_run
    from mysim_jax.mappo.run_files import prepare

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
    log(f"then: {second.config.name} from {p.out / 'policy'}, writing {second.out}/")
    return [first, train_run(second, progress, evaluate, log)]
