"""Test stub of VGGT-Omega (facebookresearch/vggt-omega), written for raytun3r (docs/stubs.md).

Same module paths, class names, attributes and signatures as upstream; own, much smaller
implementation; no upstream code.
"""

from .models import VGGTOmega

__raytun3r_stub__ = True
__version__ = "0.0.1"

__all__ = ["VGGTOmega", "__version__"]
