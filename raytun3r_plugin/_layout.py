"""The split package root: ``patches/`` (top level in the source tree) is ``raytun3r_plugin.patches``.

``setup.py`` maps the folder into the package with ``package_dir``. In a source tree the two sit
side by side (``<tree>/raytun3r_plugin`` and ``<tree>/patches``); in a wheel the folder is inside
the package (``<site>/raytun3r_plugin/patches``). When an editable install points at another
clone, Python can take ``raytun3r_plugin`` from the current directory and
``raytun3r_plugin.patches`` from that clone, and tests would silently run the other clone's
patch modules; this module refuses that mix at import time.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from raytun3r_plugin.errors import SplitInstallError

_PACKAGE_DIR = Path(__file__).resolve().parent


def same_tree(package_dir: Path, patches_dir: Path) -> bool:
    """True when ``patches_dir`` is the patches folder belonging to ``package_dir``."""
    package_dir, patches_dir = Path(package_dir).resolve(), Path(patches_dir).resolve()
    return patches_dir in (package_dir / "patches", package_dir.parent / "patches")


def check_patches_location(patches_init: str | None) -> None:
    """Raise :class:`SplitInstallError` when ``patches_init`` belongs to another source tree."""
    if patches_init is None:
        return
    patches_dir = Path(patches_init).resolve().parent
    if not same_tree(_PACKAGE_DIR, patches_dir):
        raise SplitInstallError(
            f"raytun3r_plugin is imported from {_PACKAGE_DIR} but raytun3r_plugin.patches from {patches_dir}: "
            "two source trees are mixed (typically an editable install of another clone while running in this one). "
            "Run 'pip install -e .' in the tree you work in, or run from outside it."
        )


def check_installed_layout() -> None:
    """Check where ``raytun3r_plugin.patches`` would be imported from, without importing it."""
    spec = importlib.util.find_spec("raytun3r_plugin.patches")
    if spec is not None:
        check_patches_location(spec.origin)
