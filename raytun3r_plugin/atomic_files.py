"""Atomic file writes: the one place that knows how raytun3r replaces a file.

A reader (a resumed run, a second process, a crash-recovery) must see either the old file or the
complete new one, never a torn write. Every writer therefore writes ONE temporary file in the
destination's folder (same file system, so the rename is atomic), flushes it to disk (``fsync``:
without it a crash shortly after the rename can leave a zero-length file on ext4/xfs), renames it
over the destination and fsyncs the folder. A failed write removes the temporary file and leaves
the destination as it was.

The temporary file is named ``.NAME.raytun3r-tmp-<pid>-<random>`` (:func:`temporary_name`),
created exclusively with mode 0600 (callers that publish a file for others, such as package
data, ``chmod`` the yielded path). A process killed mid-write (``kill -9``) leaves that file
behind; the next write of any file in that folder removes such leftovers (:func:`remove_stale`):
those whose writer process is dead, and any older than :data:`STALE_SECONDS`. So a kill at any
moment leaves the old file, the new file or no file, and at most one temporary file until the
next write there. Writers serialise in memory and write the bytes themselves (safetensors'
``save_file`` would make a second temporary file of its own).
"""

from __future__ import annotations

import os
import re
import secrets
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

__all__ = [
    "STALE_SECONDS",
    "atomic_path",
    "atomic_save_safetensors",
    "atomic_write_bytes",
    "atomic_write_text",
    "remove_stale",
    "temporary_name",
]

#: The marker in every temporary file name (``.NAME.raytun3r-tmp-<pid>-<random>``).
TEMPORARY_MARK = ".raytun3r-tmp-"
#: A temporary file untouched for this long is stale even if its pid names a live process
#: (the pid may have been reused, or belong to another machine's process on a shared folder).
STALE_SECONDS = 60.0


def temporary_name(destination: str | os.PathLike) -> str:
    """A fresh temporary file name for ``destination``: ``.NAME.raytun3r-tmp-<pid>-<random>``."""
    return f".{Path(destination).name}{TEMPORARY_MARK}{os.getpid()}-{secrets.token_hex(6)}"


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it exists, owned by someone else
        return True
    return True


def remove_stale(destination: str | os.PathLike) -> list[Path]:
    """Remove leftover temporary files of writes in ``destination``'s folder; returns those
    removed.

    Only files of this module's name pattern are considered (of any destination in the folder,
    so a kill while saving one file is cleaned up by the next save of any other), and only
    those whose writer process is dead or that were not touched for :data:`STALE_SECONDS`: a
    live writer's temporary file is left alone.
    """
    destination = Path(destination)
    folder = destination.parent if str(destination.parent) else Path(".")
    # Any destination's in that folder: a temporary file whose writer was killed while saving
    # another file of the folder is as stale as one of this destination.
    pattern = re.compile(r"\..+" + re.escape(TEMPORARY_MARK) + r"(\d+)-[0-9a-f]+")
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None:
            continue
        try:
            age = now - entry.stat(follow_symlinks=False).st_mtime
        except OSError:  # gone already (its writer renamed it, or another cleaner removed it)
            continue
        pid = int(match.group(1))
        writer_alive = pid == os.getpid() or _pid_alive(pid)
        if writer_alive and age < STALE_SECONDS:  # a live writer's (this process's threads too)
            continue
        with suppress(OSError):
            os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as handle:
        os.fsync(handle.fileno())


def _fsync_folder(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:  # a platform without directory descriptors
        return
    try:
        with suppress(OSError):
            os.fsync(descriptor)
    finally:
        os.close(descriptor)


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on a clean exit it replaces ``path`` atomically.

    The body writes the whole file to the yielded path (any writer that takes a file name and
    writes it in place, e.g. ``np.savez`` or ``open(..., "wb")``; not one that makes temporary
    files of its own). Stale temporary files of earlier, killed writes of ``path`` are removed
    first (:func:`remove_stale`). On a clean exit the temporary file is fsynced and renamed over
    ``path`` (whose parent folders are created); on an exception it is deleted and ``path`` is
    left untouched.
    """
    destination = Path(path)
    folder = destination.parent if str(destination.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    remove_stale(destination)
    temporary = folder / temporary_name(destination)
    try:
        os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        yield temporary
        _fsync_file(temporary)
        os.replace(temporary, destination)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    _fsync_folder(folder)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Replace ``path`` by ``data`` atomically (see :func:`atomic_path`); returns ``Path(path)``."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Replace ``path`` by ``text`` atomically (see :func:`atomic_path`); returns ``Path(path)``."""
    return atomic_write_bytes(path, text.encode(encoding))


def atomic_save_safetensors(
    path: str | os.PathLike,
    tensors: Mapping[str, torch.Tensor],
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Write a safetensors file atomically (see :func:`atomic_path`); returns ``Path(path)``.

    ``tensors`` must be contiguous and must not share storage (``save_file``'s rules);
    ``metadata`` is the header's string-to-string map.
    """
    from safetensors.torch import save

    # Serialised here and written by atomic_write_bytes: save_file would write through a
    # temporary file of its own, a second one that a kill leaves behind.
    data = save(dict(tensors), metadata=None if metadata is None else dict(metadata))
    return atomic_write_bytes(path, data)
