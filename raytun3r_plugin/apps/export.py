"""The depth panel, TUM and PLY writers; they live in :mod:`raytun3r_plugin.exports.files` now
and are re-exported here so that existing imports keep working."""

from __future__ import annotations

from raytun3r_plugin.exports.files import (
    colourise_depth,
    depth_panel,
    read_ply,
    write_ply,
    write_tum,
)

__all__ = ["colourise_depth", "depth_panel", "read_ply", "write_ply", "write_tum"]
