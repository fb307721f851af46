"""Maps the top-level ``patches/`` folder into the distribution as ``raytun3r_plugin.patches``.

pyproject.toml holds all metadata; only the package list needs code, because setuptools'
automatic discovery cannot combine found packages with a renamed folder.
"""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["raytun3r_plugin", "raytun3r_plugin.*"])
    + ["raytun3r_plugin.patches"],
    package_dir={"raytun3r_plugin.patches": "patches"},
)
