"""Checkpoints of a training run (orbax) and the saved policy.

**Checkpoints** (:class:`Checkpoints`): the whole :class:`~mysim_jax.mappo.trainer.TrainerState`
(networks, optimiser, normalisers, every environment's state, the PRNG key, the
curriculum's stage and the episode ranges it draws from) under
``RUN/checkpoints/<iteration>/``, written synchronously through an orbax
``CheckpointManager``. Orbax writes each checkpoint into a temporary folder and renames it
when complete, so a run killed at any moment (SIGKILL included) leaves its last complete
checkpoint readable; :meth:`Checkpoints.latest` ignores unfinished ones. Beside each one,
``<iteration>.sha256.json`` holds the SHA-256 of every file in it, written once the
checkpoint is complete. :meth:`Checkpoints.restore_newest` resumes from the newest
checkpoint whose files match their checksums and that restores, and says which newer
ones it skipped and why (files changed or missing, or the restore failing; a checkpoint
without a checksum file, as left by a run stopped between the two writes, is first
restored in a child process, where a failure cannot leave orbax's reads behind); the skipped ones are renamed ``damaged-<iteration>``, so the resumed run writes
those iterations again. When none is usable it raises :class:`CheckpointError` and
changes nothing; so it does, naming the fields, for a checkpoint of an earlier layout of the
state (one written by an earlier version), which is not damaged and is not renamed. Restoring gives the state bit for bit, so a resumed run continues exactly where
the checkpoint was taken.

**Policy** (:func:`save_policy`, :func:`load_policy`): the deterministic policy alone, for
evaluation and deployment: ``policy.json`` (the network's shape and the environment it was
trained on) and ``policy.msgpack`` (the actor's parameters and observation statistics,
flax serialisation).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization
from jax.experimental import multihost_utils
import orbax.checkpoint as ocp

POLICY_JSON = "policy.json"
POLICY_PARAMS = "policy.msgpack"


class CheckpointError(ValueError):
    """No checkpoint of a run can be restored. The message names the folder and each reason."""


def _digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder``, by path relative to it."""
    out = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            h = hashlib.sha256()
            with path.open("rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
            out[path.relative_to(folder).as_posix()] = h.hexdigest()
    return out


class Checkpoints:
    """Orbax checkpoints of a run's :class:`TrainerState` in ``folder``."""

    def __init__(self, folder: str | os.PathLike, keep: int = 2):
        self._ocp = ocp
        self.folder = Path(folder).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False, create=True)
        self.manager = ocp.CheckpointManager(self.folder, options=options)

    def save(self, iteration: int, state) -> None:
        tree = serialization.to_state_dict(state)
        self.manager.save(int(iteration), args=self._ocp.args.StandardSave(tree), force=True)
        self.manager.wait_until_finished()
        if jax.process_index() != 0:           # several processes: the first writes the checksums
            return
        sums = self.folder / f"{int(iteration)}.sha256.json"
        tmp = sums.with_name(sums.name + ".tmp")
        tmp.write_text(json.dumps(_digests(self.folder / str(int(iteration))), indent=0))
        os.replace(tmp, sums)
        kept = {str(s) for s in self.manager.all_steps()}
        for old in self.folder.glob("*.sha256.json"):          # of checkpoints orbax deleted
            if old.name.split(".")[0] not in kept:
                old.unlink(missing_ok=True)

    def check(self, iteration: int) -> str | None:
        """Why checkpoint ``iteration``'s files do not match their checksums (None: they do,
        or no checksum file was written)."""
        sums = self._sums(iteration)
        if not sums.is_file():
            return None
        try:
            want = json.loads(sums.read_text())
        except (OSError, ValueError) as exc:
            return f"its checksum file {sums.name} is unreadable ({type(exc).__name__})"
        have = _digests(self.folder / str(int(iteration)))
        missing = sorted(set(want) - set(have))
        if missing:
            return f"{len(missing)} of its files are missing ({missing[0]}, ...)"
        changed = sorted(k for k in want if have[k] != want[k])
        if changed:
            return f"{len(changed)} of its files differ from their checksums ({changed[0]}, ...)"
        return None

    def restore_newest(self, like, log=print):
        """``(iteration, state)`` of the newest checkpoint that verifies and restores, or
        ``(None, like)`` when there is none at all. Each newer one skipped is logged with its
        reason; raises :class:`CheckpointError` when checkpoints exist but none is usable."""
        self.manager.reload()
        steps = sorted(self.manager.all_steps(), reverse=True)
        reasons, skipped = [], []
        for step in steps:
            reason = self.check(step)
            if reason is None and not self._sums(step).is_file():
                reason = self._trial_restore(step)
            if reason is None:
                # intact: its metadata can be read here without leaving orbax's reads behind
                missing = self._missing_fields(step, like)
                if missing:
                    raise CheckpointError(f"{self.folder}: checkpoint {step} was written by an earlier version of "
                                          f"mysim_jax (it has no {', '.join(missing)}): resume it with that version, "
                                          "or start the run again")
                try:
                    state = self.restore(step, like)
                except Exception as exc:          # noqa: BLE001: any failure of a damaged checkpoint
                    first = (str(exc).strip().splitlines() or [""])[0][:160]
                    reason = f"restoring it failed: {type(exc).__name__}: {first}"
                else:
                    if jax.process_count() > 1:   # every process has chosen before any renaming

                        multihost_utils.sync_global_devices("mysim_jax checkpoint chosen")
                    if jax.process_index() == 0:
                        self._set_aside(skipped, log)
                    else:
                        self.manager.reload()
                    return step, state
            reasons.append(f"checkpoint {step}: {reason}")
            skipped.append(step)
            log(f"skipping checkpoint {step} in {self.folder}: {reason}")
        if steps:
            raise CheckpointError(f"{self.folder}: none of the {len(steps)} checkpoints can be resumed from: "
                                  + "; ".join(reasons))
        return None, like

    def _missing_fields(self, step: int, like) -> list[str]:
        """The fields of ``like``'s state that the intact checkpoint ``step`` does not hold (a
        checkpoint of an earlier layout of the state); empty when they match or when its
        metadata cannot be read (the restore that follows then names the failure)."""
        try:
            reader = self._ocp.Checkpointer(self._ocp.StandardCheckpointHandler())
            meta = reader.metadata(self.folder / str(int(step)) / "default")
            reader.close()
            have = set(meta.item_metadata.keys())
        except Exception:                          # noqa: BLE001: unreadable metadata is damage, named later
            return []
        return sorted(set(serialization.to_state_dict(like)) - have)

    def _sums(self, step: int) -> Path:
        return self.folder / f"{int(step)}.sha256.json"

    def _trial_restore(self, step: int) -> str | None:
        """Restore checkpoint ``step`` in a child process (on the CPU) and say why it failed
        (None: it restored). For checkpoints without a checksum file: orbax abandons a
        failed restore with reads still in flight, whose completions then print tracebacks
        from its closed event loop; in a child they end with it."""
        code = ("import sys, orbax.checkpoint as ocp\n"
                "m = ocp.CheckpointManager(sys.argv[1])\n"
                "m.restore(int(sys.argv[2]), args=ocp.args.StandardRestore())\n"
                "m.close()\n")
        res = subprocess.run([sys.executable, "-c", code, str(self.folder), str(int(step))], capture_output=True,
                             text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})
        if res.returncode == 0:
            return None
        errors = [line for line in res.stderr.splitlines()
                  if re.match(r"^[\w.]*(Error|Exception)\b", line) and "Event loop is closed" not in line]
        return f"restoring it failed: {(errors or ['exit code %d' % res.returncode])[-1][:160]}"

    def latest(self) -> int | None:
        """The last complete checkpoint's iteration, or None."""
        self.manager.reload()
        return self.manager.latest_step()

    def _set_aside(self, steps, log) -> None:
        """Rename damaged checkpoints to ``damaged-<iteration>`` (kept for inspection), so
        that the resumed run can write those iterations again."""
        for step in steps:
            n = 0
            while (self.folder / f"damaged-{step}{'' if n == 0 else f'-{n}'}").exists():
                n += 1
            name = f"damaged-{step}{'' if n == 0 else f'-{n}'}"
            os.replace(self.folder / str(step), self.folder / name)
            sums = self.folder / f"{step}.sha256.json"
            if sums.exists():
                os.replace(sums, self.folder / f"{name}.sha256.json")
            log(f"moved the damaged checkpoint {step} to {self.folder / name}")
        if steps:
            self.manager.reload()

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
