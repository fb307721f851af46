"""raytun3r_plugin._io: the one atomic write (temporary file, fsync, rename)."""

from __future__ import annotations

import pytest
import torch

from raytun3r_plugin._io import (
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
