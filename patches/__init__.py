"""Backbone patch modules, installed as ``raytun3r_plugin.patches``; each registers itself."""

from raytun3r_plugin._layout import check_patches_location

check_patches_location(__file__)

from raytun3r_plugin.patches import (  # noqa: E402
    da3,  # noqa: F401
    pi3,  # noqa: F401
    vggt,  # noqa: F401
    vggt_omega,  # noqa: F401
)
