"""Applications built on the core: the ``raytun3r`` command line, the demo, the synthetic
benchmark, the evaluation protocol, inference-to-files and the file exporters.

The core (everything else in ``raytun3r_plugin``, and ``raytun3r_plugin.patches``) never imports
from here; ``tests/test_layering.py`` enforces it, so a library user can patch a model without
pulling in argparse front ends or benchmark tables.
"""
