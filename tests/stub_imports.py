"""Import the stub packages of tests/stubs (docs/stubs.md) in the tests that check them: the
stubs go on ``sys.path`` only where a real upstream package is not importable."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

import pytest
import torch

STUBS = Path(__file__).resolve().parent / "stubs"
if any(importlib.util.find_spec(name) is None for name in ("vggt", "pi3", "vggt_omega")):
    if str(STUBS) not in sys.path:
        sys.path.insert(0, str(STUBS))

#: The token grid of a 2 x 3 patch image, (6, 2) row-major (y, x).
GRID = torch.cartesian_prod(torch.arange(2), torch.arange(3))


def stub(name: str):
    """The stub package ``name``; the test is skipped where the real package is installed."""
    module = importlib.import_module(name)
    if not getattr(module, "__raytun3r_stub__", False):
        pytest.skip(f"the real {name} package is installed; these tests cover the raytun3r stub")
    return module
