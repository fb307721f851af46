"""What a frozen model runs in place of each hooked upstream method: pure ``torch`` code that
reads constant buffers registered on the method's owner (:mod:`raytun3r_plugin.deploy.freeze`
builds them).

None of these reads a camera, an adapter, a patch state or a cache: each takes its inputs,
the buffers computed once for one camera and input size, and upstream's own class methods.
That is what lets ``torch.export`` / ONNX trace them into a static graph. Each is installed as
an instance attribute (a :class:`FrozenMethod`), as ``apply`` installs its wrappers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.rope import apply_rope_2d

#: Prefix of every buffer the freeze registers (non-persistent: the state dict stays upstream's).
BUFFER_PREFIX = "raytun3r_frozen_"


class FrozenMethod:
    """``owner.<attribute>(*args)`` of a frozen model: ``function(owner, *args, **kwargs)``.

    Holds its owner (a frozen model is a copy made for deployment; the reference cycle is
    collected with it) and the Python constants the function needs.
    """

    def __init__(self, owner: nn.Module, attribute: str, function: Callable, **constants: Any):
        self.owner = owner
        self.attribute = attribute
        self.function = function
        self.constants = constants
        self.__name__ = attribute

    def __call__(self, *args, **kwargs):
        return self.function(self.owner, *args, **self.constants, **kwargs)

    def __repr__(self) -> str:
        return f"<frozen {type(self.owner).__qualname__}.{self.attribute}>"


def upstream_method(owner: nn.Module, attribute: str) -> Callable:
    """Upstream's class method ``attribute`` bound to ``owner`` (the frozen one shadows it)."""
    return getattr(type(owner), attribute).__get__(owner, type(owner))


def _buffers(owner: nn.Module, names: Sequence[str | None]) -> tuple:
    return tuple(None if name is None else getattr(owner, name) for name in names)


def constant_output(
    owner: nn.Module, *args, names: Sequence[str | None], single: bool, key: tuple, where: str
):
    """A method whose result depends only on the input size: the recorded result.

    ``key`` are the integer arguments it was recorded with (sizes); another call is refused.
    """
    given = tuple(arg for arg in args if isinstance(arg, int))
    if given != key:
        raise InputError(
            f"{where}: this model is frozen for sizes {key}, called with {given}; freeze it again"
        )
    values = _buffers(owner, names)
    return values[0] if single else values


def added_constant(owner: nn.Module, x: torch.Tensor, *args, table: dict, where: str, **kwargs):
    """``x + embedding``: a head's coordinate embedding, one buffer per feature-map shape."""
    name = table.get(tuple(x.shape[1:]))
    if name is None:
        raise InputError(
            f"{where}: this model is frozen for feature maps {sorted(table)}, called with {tuple(x.shape[1:])}"
        )
    return x + getattr(owner, name)


def resampled_patch_embedding(
    owner: nn.Module, x: torch.Tensor, *, grid: str | None, valid: str | None
) -> torch.Tensor:
    """Resample the images through the constant grid, embed them, refill the invalid tokens.

    x: (N, C, H, W) images; returns (N, hw, D) tokens, as upstream's ``PatchEmbed.forward``.
    """
    if grid is not None:
        sampled = getattr(owner, grid)
        x = F.grid_sample(
            x,
            sampled.expand(x.shape[0], -1, -1, -1),
            mode="bilinear",
            padding_mode="zeros",
            align_corners=False,
        ).contiguous()
    tokens = upstream_method(owner, "forward")(x)
    if valid is not None:
        mask = getattr(owner, valid)[None]
        weights = mask.to(tokens.dtype)[..., None]
        mean = (tokens * weights).sum(dim=1, keepdim=True) / weights.sum(dim=1, keepdim=True).clamp(
            min=1
        )
        tokens = torch.where(mask[..., None], tokens, mean)
    return tokens


def fixed_size_rope(
    owner: nn.Module,
    tokens: torch.Tensor,
    positions: torch.Tensor,
    *,
    cos: str,
    sin: str,
    apply_1d: str,
    base: float,
    displacement: str | None,
    columns: int,
) -> torch.Tensor:
    """Upstream's RoPE forward for one input size, with no data-dependent table length.

    Upstream sizes its cos/sin tables by ``int(positions.max()) + 1``: a value read from the
    data, which ``torch.export`` cannot trace. Here the tables are constant buffers built by
    upstream's own table method for the largest position of this size, and looked up by
    upstream's own 1-D function: every row of the table is computed independently, so the
    result is bit-identical to upstream's. With a ``displacement`` table (the adapter's radial
    RoPE correction, (1 + h w, 2), row 0 for the special tokens) the integer positions
    (y + 1, x + 1) are displaced and the angles evaluated continuously, as the patched model
    does; float positions (already displaced) are evaluated continuously.
    """
    if displacement is not None and not positions.is_floating_point():
        is_patch = (positions[..., 0] > 0) & (positions[..., 1] > 0)
        index = torch.where(
            is_patch,
            (positions[..., 0] - 1) * columns + positions[..., 1],
            torch.zeros_like(positions[..., 0]),
        )
        positions = positions.to(torch.float32) + getattr(owner, displacement)[index]
    if positions.is_floating_point():
        return apply_rope_2d(tokens, positions, base)
    cos_table, sin_table = getattr(owner, cos), getattr(owner, sin)
    one_dim = getattr(owner, apply_1d)
    vertical, horizontal = tokens.chunk(2, dim=-1)
    return torch.cat(
        (
            one_dim(vertical, positions[..., 0], cos_table, sin_table),
            one_dim(horizontal, positions[..., 1], cos_table, sin_table),
        ),
        dim=-1,
    )
