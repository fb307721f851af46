"""Replacement builders shared by the backbone patch modules.

Each builder has the :class:`raytun3r_plugin.registry.PatchTarget` ``build`` signature
``build(owner, state) -> behaviour``, and ``behaviour(original, *args)`` runs in place of one
upstream method of one instance. ``original`` is that method, bound to the owner, looked up by the
installed wrapper on every call: a behaviour must not keep the original or the owner itself, so
that a patched model is freed like any other and a deep copy runs its own submodules (the
wrapper rebuilds the behaviour for the copy). Plain values read from the owner at build time
(a frequency, a token offset) are fine. The backbone modules only say *where* these go; what
they do is written once here.
"""

from __future__ import annotations

import sys

import torch
import torch.nn.functional as F

from raytun3r_plugin.errors import UnsupportedUpstreamError
from raytun3r_plugin.registry import rope_base
from raytun3r_plugin.rope import apply_rope_2d, displaced_positions


def pe_interpolation(owner, state):
    """Wrap ``interpolate_pos_encoding(x, w, h)``: the adapter's PE correction, or the naive remap.

    Upstream names are swapped (``w`` receives the image height); the table's first row is the
    class slot and stays unchanged. With ``"pe"`` the adapter's correction is added to the patch
    rows; with the ablation ``"pe_naive_remap"`` (never both) the patch rows are instead
    upstream's own table sampled bilinearly at the tokens' undistorted positions
    (:func:`raytun3r_plugin.geometry.naive_pe_positions`).
    """

    def interpolate_pos_encoding(original, x, w, h):
        table = original(x, w, h)
        correct, remap = state.uses("pe"), state.uses("pe_naive_remap")
        if not (correct or remap):
            return table
        geometry = state.geometry(w, h)
        patches = table[:, 1:]
        if remap:
            grid = geometry.naive_pe_grid(table.device, table.dtype)
            if grid is not None:
                count, rows, cols = table.shape[0], geometry.height // geometry.patch, grid.shape[2]
                image = patches.reshape(count, rows, cols, -1).permute(0, 3, 1, 2)
                sampled = F.grid_sample(
                    image,
                    grid.expand(count, -1, -1, -1),
                    mode="bilinear",
                    padding_mode="border",
                    align_corners=True,
                )
                patches = sampled.permute(0, 2, 3, 1).reshape(count, rows * cols, -1)
            elif not correct:
                return table  # the remap is the identity here (a pinhole camera)
        if correct:
            correction = state.pe_correction(geometry, table.device, torch.float32)
            patches = patches + correction.to(table.dtype)
        return torch.cat((table[:, :1], patches), dim=1)

    return interpolate_pos_encoding


def patch_embedding(owner, state):
    """Wrap ``PatchEmbed.forward(x)``: local undistortion before, border tokens after.

    x: (N, C, H, W) images; returns (N, hw, D) tokens like upstream.
    """

    def forward(original, x):
        resample = state.uses("patch_resample")
        border = state.uses("border_tokens")
        if not (resample or border):
            return original(x)
        geometry = state.geometry(x.shape[-2], x.shape[-1])
        if resample:
            grid = geometry.resample_grid(x.device, x.dtype)
            if grid is not None:
                x = F.grid_sample(
                    x,
                    grid.expand(x.shape[0], -1, -1, -1),
                    mode="bilinear",
                    padding_mode="zeros",
                    align_corners=False,
                ).contiguous()
        tokens = original(x)
        if border:
            valid = geometry.token_valid(tokens.device)
            if valid is not None:
                weights = valid.to(tokens.dtype)[None, :, None]
                mean = (tokens * weights).sum(dim=1, keepdim=True) / weights.sum(
                    dim=1, keepdim=True
                )
                tokens = torch.where(valid[None, :, None], tokens, mean)
        return tokens

    return forward


def continuous_rope(owner, state):
    """Wrap a RoPE module's ``forward(tokens, positions)`` to accept fractional positions.

    Integer positions (upstream's own, or a disabled handle) go to the original table look-up;
    float positions are evaluated directly, bit-identical to the table at integer values. The
    frequency base is the owner's ``BackboneSpec.rope_base_attribute`` (refused when missing).
    """
    base = rope_base(state.spec, owner)

    def forward(original, tokens, positions):
        if not positions.is_floating_point():
            return original(tokens, positions)
        return apply_rope_2d(tokens, positions, base)

    return forward


def displaced_rope_positions(
    positions: torch.Tensor, patch_start: int, state, height: int, width: int
) -> torch.Tensor:
    """Apply the adapter's radial RoPE displacement to patch positions (..., patch_start + hw, 2)."""
    geometry = state.geometry(height, width)
    displacement = state.rope_displacement(geometry, positions.device, torch.float32)
    return displaced_positions(positions, patch_start, displacement)


def uv_grid_embedding(owner, state):
    """Wrap a DPT head's ``_add_pos_embed(x, W, H, ratio)`` / ``_apply_pos_embed``.

    The camera-aware uv grid goes through the sinusoidal embedding function that the head's own
    module uses (looked up by name there, so upstream's formula is reused, not copied).
    """
    module = sys.modules.get(type(owner).__module__)
    to_embed = getattr(module, "position_grid_to_embed", None)
    if to_embed is None:
        raise UnsupportedUpstreamError(
            f"{type(owner).__module__}: expected a module-level 'position_grid_to_embed' next to {type(owner).__qualname__}, found none"
        )

    def add_pos_embed(original, x, W, H, ratio=0.1):
        if not state.uses("grid"):
            return original(x, W, H, ratio)
        geometry = state.geometry(H, W)
        cells_h, cells_w, channels = x.shape[-2], x.shape[-1], x.shape[1]

        def build():
            grid = geometry.uv_grid(cells_h, cells_w, x.device, x.dtype)
            if grid is None:
                return None
            # The embedding depends only on camera and sizes, so it is computed once.
            return (
                (to_embed(grid, channels) * ratio).permute(2, 0, 1)[None].to(x.dtype).contiguous()
            )

        embed = geometry.memo(
            ("grid_embed", cells_h, cells_w, channels, ratio, x.device, x.dtype), build
        )
        if embed is None:
            return original(x, W, H, ratio)
        return x + embed

    return add_pos_embed


def displace_grid_positions(positions: torch.Tensor, state, patch_size: int) -> torch.Tensor:
    """Float positions: every patch token displaced by the adapter's radial RoPE table.

    ``positions`` (..., N, 2) are upstream integer (y, x) positions in any token layout: patch
    tokens carry (row + 1, col + 1) of an h x w grid, special tokens (0, 0). The grid size is read
    from the positions themselves (h = max y, w = max x), so the image is (h p, w p) pixels. A
    call without patch tokens (e.g. Pi3X's metric query at (0, 0)) returns the positions as they
    are.
    """
    rows, cols = (int(v) for v in positions.reshape(-1, 2).amax(dim=0).tolist())
    if rows < 1 or cols < 1:
        return positions
    geometry = state.geometry(rows * patch_size, cols * patch_size)
    displacement = state.rope_displacement(
        geometry, positions.device, torch.float32
    )  # (h*w, 2), (y, x)
    is_patch = (positions[..., 0] > 0) & (positions[..., 1] > 0)
    index = ((positions[..., 0] - 1) * cols + (positions[..., 1] - 1)).clamp(min=0)
    offset = torch.where(is_patch[..., None], displacement[index], displacement.new_zeros(()))
    return positions.to(torch.float32) + offset


def grid_position_rope(owner, state):
    """Wrap a RoPE module's ``forward(tokens, positions)``: radial displacement + continuous angles.

    Upstream integer positions (y + 1, x + 1) identify each patch token, whatever the layout of
    the call (per frame or all frames of a global block), so the position assembly code of the
    model (``Aggregator.forward``, ``Pi3.decode``) is left alone: q' = q + rope.radial(rho) d/|d|
    with q the upstream position including its +1 (docs/conventions.md section 4), special tokens at (0, 0)
    unchanged. Float positions and a disabled handle go straight to the continuous / upstream
    evaluation of :func:`raytun3r_plugin.hooks.continuous_rope`.
    """
    continuous = continuous_rope(owner, state)
    patch_size = state.info.patch_size

    def forward(original, tokens, positions):
        if positions.is_floating_point() or not state.uses("rope"):
            return continuous(original, tokens, positions)
        return continuous(original, tokens, displace_grid_positions(positions, state, patch_size))

    return forward
