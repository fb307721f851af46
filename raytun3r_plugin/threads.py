"""torch's intra-op thread count for the duration of a block: the renderer's, and a task's where
:mod:`raytun3r_plugin.cluster` runs it in this process."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["torch_threads"]


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the body with ``n`` torch intra-op threads (process-wide, restored afterwards);
    ``None`` leaves torch's setting alone."""
    import torch

    old = torch.get_num_threads()
    if n is None or n == old:
        yield
        return
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)
