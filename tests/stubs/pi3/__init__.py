"""raytun3r test stub of ``yyfz/Pi3`` (not on PyPI).

Mirrors the upstream module paths, class names, attribute names and method signatures that
raytun3r hooks into, with small implementations written for the tests. It is not upstream code
and carries none of it. See ``docs/stubs.md`` for what is mirrored and what differs.
"""

__raytun3r_stub__ = True

from .models.pi3x import Pi3X  # noqa: E402  (upstream's package exports Pi3X)

__all__ = ["Pi3X"]
