"""Shared fixtures. Stub ``vggt`` / ``pi3`` packages are used only when the real ones are absent."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import pytest

STUBS = Path(__file__).parent / "stubs"
REAL_UPSTREAM = {
    name: importlib.util.find_spec(name) is not None for name in ("vggt", "pi3", "vggt_omega")
}
if not all(REAL_UPSTREAM.values()) and STUBS.is_dir():
    sys.path.append(str(STUBS))

warnings.filterwarnings("ignore", message="register_new_resolver")

try:  # property-based tests (tests/test_*_properties.py); hypothesis is in the [test] extra
    from hypothesis import HealthCheck, settings

    # Derandomised: CI and every machine draw the same examples, so a red run reproduces; no
    # example database is written into the source tree; no per-example deadline (CPU speeds vary).
    settings.register_profile(
        "raytun3r",
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow],
    )
    settings.load_profile("raytun3r")
except ImportError:  # pragma: no cover - the [test] extra installs it
    pass


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """The whole suite on one torch thread: its tensors are tiny, and on a shared 2-core machine
    intra-op threads mostly wait on each other (a test that needs more sets it, e.g. with
    ``raytun3r_plugin.threads.torch_threads``). Processes a test starts keep their own."""
    from raytun3r_plugin.threads import torch_threads

    with torch_threads(1):
        yield


@pytest.fixture(autouse=True)
def _quiet_da3_logger():
    """DA3 logs at INFO on every forward with 3+ views; keep test output readable."""
    import logging

    logging.getLogger("depth_anything_3").setLevel(logging.WARNING)
    yield
