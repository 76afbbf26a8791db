"""Checkpoints of a training run (orbax) and the saved policy.

**Checkpoints** (:class:`Checkpoints`): the whole :class:`~mysim_jax.mappo.trainer.TrainerState`
(networks, optimiser, normalisers, every environment's state, the PRNG key) under
``RUN/checkpoints/<iteration>/``, written synchronously through an orbax
``CheckpointManager``. Orbax writes each checkpoint into a temporary folder and renames it
when complete, so a run killed at any moment (SIGKILL included) leaves its last complete
checkpoint readable; :meth:`Checkpoints.latest` ignores unfinished ones. Restoring gives
the state bit for bit, so a resumed run continues exactly where the checkpoint was taken.

**Policy** (:func:`save_policy`, :func:`load_policy`): the deterministic policy alone, for
evaluation and deployment: ``policy.json`` (the network's shape and the environment it was
trained on) and ``policy.msgpack`` (the actor's parameters and observation statistics,
flax serialisation).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

POLICY_JSON = "policy.json"
POLICY_PARAMS = "policy.msgpack"


class Checkpoints:
    """Orbax checkpoints of a run's :class:`TrainerState` in ``folder``."""

    def __init__(self, folder: str | os.PathLike, keep: int = 2):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.folder = Path(folder).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False, create=True)
        self.manager = ocp.CheckpointManager(self.folder, options=options)

    def save(self, iteration: int, state) -> None:
        tree = serialization.to_state_dict(state)
        self.manager.save(int(iteration), args=self._ocp.args.StandardSave(tree), force=True)
        self.manager.wait_until_finished()

    def latest(self) -> int | None:
        """The last complete checkpoint's iteration, or None."""
        self.manager.reload()
        return self.manager.latest_step()

    def restore(self, iteration: int, like):
        """The state saved at ``iteration``, with the structure of ``like`` (a state of the
        same run, e.g. a fresh :meth:`Trainer.init`). Each leaf is placed as ``like``'s is:
        orbax returns arrays committed to a device, and a leaf that ``like`` holds
        uncommitted comes back uncommitted, so the resumed run calls the very program a
        fresh start compiled (the compilation cache hits) instead of one specialised to
        committed arguments."""
        target = serialization.to_state_dict(like)
        abstract = jax.tree.map(self._ocp.utils.to_shape_dtype_struct, target)
        tree = self.manager.restore(int(iteration), args=self._ocp.args.StandardRestore(abstract))

        def place(saved, fresh):
            if isinstance(fresh, jax.Array) and not fresh.committed:
                return jnp.asarray(np.asarray(saved))
            return saved
        return serialization.from_state_dict(like, jax.tree.map(place, tree, target))

    def close(self) -> None:
        self.manager.close()


def save_policy(folder: str | os.PathLike, arrays: dict, meta: dict) -> Path:
    """Write ``policy.json`` (``meta``) and ``policy.msgpack`` (``arrays``) into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    host = jax.tree.map(np.asarray, arrays)
    tmp = folder / (POLICY_PARAMS + ".tmp")
    tmp.write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(host)))
    os.replace(tmp, folder / POLICY_PARAMS)
    (folder / POLICY_JSON).write_text(json.dumps(meta, indent=2))
    return folder


def is_policy_folder(path: str | os.PathLike) -> bool:
    p = Path(path)
    return p.is_dir() and (p / POLICY_JSON).is_file() and (p / POLICY_PARAMS).is_file()


def load_policy(folder: str | os.PathLike):
    """``(meta, arrays)`` of a saved policy."""
    folder = Path(folder)
    meta = json.loads((folder / POLICY_JSON).read_text())
    arrays = serialization.msgpack_restore((folder / POLICY_PARAMS).read_bytes())
    return meta, arrays
