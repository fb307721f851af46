"""What every baseline handle shares: ``disabled()`` and the context manager."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


class BaselineHandle:
    """Base of :class:`~raytun3r_plugin.baselines.LoraHandle` and
    :class:`~raytun3r_plugin.baselines.TokenHandle`: a subclass implements ``remove()``."""

    _enabled: bool = True

    def remove(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    @contextmanager
    def disabled(self) -> Iterator[None]:
        """Run the model without the baseline inside the block."""
        previous, self._enabled = self._enabled, False
        try:
            yield
        finally:
            self._enabled = previous

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.remove()
