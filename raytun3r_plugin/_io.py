"""Atomic file writes: the one place that knows how raytun3r replaces a file.

A reader (a resumed run, a second process, a crash-recovery) must see either the old file or the
complete new one, never a torn write. Every writer therefore writes a temporary file in the
destination's folder (same file system, so the rename is atomic), flushes it to disk (``fsync``:
without it a crash shortly after the rename can leave a zero-length file on ext4/xfs) and then
renames it over the destination. A failed write removes the temporary file and leaves the
destination as it was.

The temporary file is created by :func:`tempfile.mkstemp` (mode 0600, a unique name, so two
processes writing the same destination never share a temporary); callers that publish a file
for others (package data) ``chmod`` the yielded path.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

__all__ = ["atomic_path", "atomic_save_safetensors", "atomic_write_bytes", "atomic_write_text"]


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as handle:
        os.fsync(handle.fileno())


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on a clean exit it replaces ``path`` atomically.

    The body writes the whole file to the yielded path (any writer that takes a file name:
    ``safetensors.torch.save_file``, ``np.savez``, ...). On a clean exit the temporary file is
    fsynced and renamed over ``path`` (whose parent folders are created); on an exception it is
    deleted and ``path`` is left untouched.
    """
    destination = Path(path)
    folder = destination.parent if str(destination.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(prefix=f".{destination.name}.", suffix=".tmp", dir=folder)
    os.close(handle)
    temporary = Path(name)
    try:
        yield temporary
        _fsync_file(temporary)
        os.replace(temporary, destination)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


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
    from safetensors.torch import save_file

    with atomic_path(path) as temporary:
        save_file(
            dict(tensors), str(temporary), metadata=None if metadata is None else dict(metadata)
        )
    return Path(path)
