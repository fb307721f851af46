"""raytun3r_plugin.atomic_files: the one atomic write (temporary file, fsync, rename)."""

from __future__ import annotations

import pytest
import torch

from raytun3r_plugin.atomic_files import (
    atomic_path,
    atomic_save_safetensors,
    atomic_write_bytes,
    atomic_write_text,
)


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "file.txt"
    atomic_write_text(target, "old")
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in target.parent.iterdir()) == ["file.txt"]


def test_a_failed_write_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    target = tmp_path / "file.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="disk full"), atomic_path(target) as temporary:
        temporary.write_text("half")
        raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


def test_atomic_save_safetensors_round_trips(tmp_path):
    from safetensors import safe_open

    path = atomic_save_safetensors(tmp_path / "t.safetensors", {"a": torch.arange(3.0)}, {"k": "v"})
    with safe_open(str(path), framework="pt") as handle:
        assert handle.metadata() == {"k": "v"}
        assert torch.equal(handle.get_tensor("a"), torch.arange(3.0))


def _dead_pid() -> int:
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_write_uses_one_recognisable_temporary_and_removes_only_stale_ones(tmp_path):
    import os
    import time

    from raytun3r_plugin.atomic_files import STALE_SECONDS, remove_stale, temporary_name

    target = tmp_path / "file.txt"
    name = temporary_name(target)
    assert name.startswith(f".file.txt.raytun3r-tmp-{os.getpid()}-")
    with atomic_path(target) as temporary:
        assert temporary.parent == tmp_path
        assert temporary.name.startswith(f".file.txt.raytun3r-tmp-{os.getpid()}-")
        assert sorted(p.name for p in tmp_path.iterdir()) == [temporary.name]
        temporary.write_text("x")

    dead = tmp_path / f".file.txt.raytun3r-tmp-{_dead_pid()}-abc123"
    live = tmp_path / f".file.txt.raytun3r-tmp-{os.getppid()}-abc123"  # a live writer, young
    old = tmp_path / f".file.txt.raytun3r-tmp-{os.getpid()}-def456"  # live pid, long untouched
    other = tmp_path / f".other.txt.raytun3r-tmp-{_dead_pid()}-abc123"  # another target's, dead
    other_live = tmp_path / f".other.txt.raytun3r-tmp-{os.getppid()}-abc123"
    mine = tmp_path / ".file.txt.notes"  # not a temporary at all
    for path in (dead, live, old, other, other_live, mine):
        path.write_text("stale")
    past = time.time() - STALE_SECONDS - 5
    os.utime(old, (past, past))
    # The folder's stale temporaries, whichever file their writer was saving; live ones stay.
    assert sorted(remove_stale(target)) == sorted([dead, old, other])
    assert all(p.exists() for p in (live, other_live, mine))
    atomic_write_text(target, "new")  # a write runs the same cleanup
    assert live.exists() and target.read_text() == "new"
