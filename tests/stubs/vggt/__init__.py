"""raytun3r test stub of ``facebookresearch/vggt`` (not on PyPI).

Mirrors the upstream module paths, class names, attribute names and method signatures that
raytun3r hooks into, with small implementations written for the tests. It is not upstream code
and carries none of it. See ``docs/stubs.md`` for what is mirrored and what differs.
"""

__raytun3r_stub__ = True
