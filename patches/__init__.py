"""Backbone patch modules, installed as ``raytun3r_plugin.patches``; each registers itself."""

from raytun3r_plugin.patches import (
    da3,  # noqa: F401
    pi3,  # noqa: F401
    vggt,  # noqa: F401
)
