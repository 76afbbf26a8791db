"""Output folders of the command-line scripts: checked before any work, written whole.

``check_output_dir(path)`` tells, before anything is loaded or compiled, whether a run
could write to ``path``: not empty, not an existing file or device, no part of it an
existing non-directory, every name within the file system's length limit, and the
nearest existing folder writable (a folder is made in it and removed again, as the
permission bits do not tell about read-only mounts or /proc). It raises
:class:`OutputError` saying which of these fails.

``staged_output(path)`` is where a run writes: a hidden temporary folder beside the
destination. Only when the ``with`` block finishes do its files move into ``path``
(created then, with its parents; files of the same name are replaced, other files in
``path`` are left alone). If the block raises, the temporary folder is removed and
``path`` is untouched, so a failed run never leaves half of its outputs behind.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import stat
import tempfile
from pathlib import Path


class OutputError(ValueError):
    """The output folder cannot be used. The message names it and says why."""


def _nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (``.`` for a relative path at worst)."""
    probe = path
    while True:
        try:
            os.stat(probe)
            return probe
        except FileNotFoundError:
            if probe.parent == probe:
                return probe
            probe = probe.parent


def check_output_dir(path: str | os.PathLike, flag: str = "--out") -> Path:
    """Check that ``path`` can become (or already is) a writable output folder."""
    text = os.fspath(path)
    if text.strip() == "":
        raise OutputError(f"{flag}: empty path; name the folder to write into (e.g. {flag} out/run)")
    out = Path(text)
    try:
        name_max = os.pathconf(_nearest_existing(out.absolute()), "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    for part in out.parts:
        if len(os.fsencode(part)) > name_max:
            raise OutputError(f"{flag} {text}: the name '{part[:40]}...' is longer than the file system "
                              f"allows ({name_max} bytes)")
    try:
        existing = _nearest_existing(out)
        info = os.stat(existing)
    except NotADirectoryError:
        raise OutputError(f"{flag} {text}: a part of the path is an existing file, not a folder") from None
    except OSError as exc:
        raise OutputError(f"{flag} {text}: cannot use the path: {exc.strerror or exc}") from None
    if not stat.S_ISDIR(info.st_mode):
        if existing == out:
            raise OutputError(f"{flag} {text}: exists and is not a folder (outputs are several files)")
        raise OutputError(f"{flag} {text}: '{existing}' is a file, not a folder, so nothing can be made under it")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"{flag} {text}: no permission to write into '{existing}'")
    # what staged_output will do first: make a folder in ``existing``. Permission bits do
    # not tell everything (a read-only mount, /proc or /sys, where even root cannot)
    try:
        probe = tempfile.mkdtemp(prefix=f".{out.name or 'out'}.check-", dir=existing)
    except OSError as exc:
        raise OutputError(f"{flag} {text}: cannot make a folder in '{existing}': "
                          f"{exc.strerror or exc}") from None
    os.rmdir(probe)
    return out


@contextlib.contextmanager
def staged_output(path: str | os.PathLike):
    """Yield a temporary folder to write into; move its files into ``path`` on success."""
    out = Path(path)
    base = _nearest_existing(out.absolute())
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name or 'out'}.partial-", dir=base))
    try:
        yield tmp
        out.mkdir(parents=True, exist_ok=True)
        for item in sorted(tmp.iterdir()):
            target = out / item.name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            try:
                os.replace(item, target)
            except OSError as exc:
                if exc.errno != errno.EXDEV:       # another file system: copy instead of rename
                    raise
                shutil.move(str(item), str(target))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
