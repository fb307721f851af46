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

import functools
import sys

import torch
import torch.nn.functional as F

from raytun3r_plugin.errors import InputError, UnsupportedUpstreamError
from raytun3r_plugin.registry import rope_base
from raytun3r_plugin.rope import apply_rope_2d, displaced_positions


def owner_of(original):
    """The instance an ``original`` runs on: the owner the wrapper looked up for this call.

    The wrapper passes upstream's class method as ``functools.partial(method, owner)`` rather
    than a bound method (torch.compile rebuilds a bound method after a graph break by an
    attribute look-up on the owner, which finds the wrapper again); an instance attribute that
    was there before the patch comes as it was (a bound method).
    """
    if isinstance(original, functools.partial):
        return original.args[0]
    return original.__self__


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
        if state.rig:
            return _rig_pe_table(state, table, x.shape[0], w, h, correct, remap)
        geometry = state.geometry(w, h)
        patches = table[:, 1:]
        if remap:
            grid = geometry.naive_pe_grid(table.device, table.dtype)
            if grid is not None:
                patches = _remapped(patches, grid, geometry)
            elif not correct:
                return table  # the remap is the identity here (a pinhole camera)
        if correct:
            correction = state.pe_correction(geometry, table.device, torch.float32)
            patches = patches + correction.to(table.dtype)
        return torch.cat((table[:, :1], patches), dim=1)

    return interpolate_pos_encoding


def _remapped(patches: torch.Tensor, grid: torch.Tensor, geometry) -> torch.Tensor:
    """The (N, hw, C) PE rows sampled bilinearly at ``grid`` (1, rows, cols, 2) (the naive remap)."""
    count, rows, cols = patches.shape[0], geometry.height // geometry.patch, grid.shape[2]
    image = patches.reshape(count, rows, cols, -1).permute(0, 3, 1, 2)
    sampled = F.grid_sample(
        image,
        grid.expand(count, -1, -1, -1),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    return sampled.permute(0, 2, 3, 1).reshape(count, rows * cols, -1)


def _rig_pe_table(state, table, rows: int, height: int, width: int, correct: bool, remap: bool):
    """(rows, 1 + hw, C) PE table of a rig forward: image r gets the table of view r % V.

    Upstream adds the table to the (B S, 1 + hw, C) tokens, so a per-image table broadcasts as
    its (1, 1 + hw, C) one did.
    """
    index = state.view_rows(rows, "PE interpolation", table.device)
    per_view = []
    for geometry in state.geometry_views(height, width):
        patches = table[:, 1:]
        grid = geometry.naive_pe_grid(table.device, table.dtype) if remap else None
        per_view.append(_remapped(patches, grid, geometry) if grid is not None else patches)
    patches = torch.cat(per_view)  # (V, hw, C)
    if correct:
        corrections = state.pe_correction_views(height, width, table.device, torch.float32)
        patches = patches + corrections.to(table.dtype)
    return torch.cat((table[:, :1].expand(rows, -1, -1), patches[index]), dim=1)


def patch_embedding(owner, state):
    """Wrap ``PatchEmbed.forward(x)``: local undistortion before, border tokens after.

    x: (N, C, H, W) images; returns (N, hw, D) tokens like upstream.
    """

    def forward(original, x):
        resample = state.uses("patch_resample")
        border = state.uses("border_tokens")
        if not (resample or border):
            return original(x)
        if state.rig:
            return _rig_patch_embedding(state, original, x, resample, border)
        geometry = state.geometry(x.shape[-2], x.shape[-1])
        if resample:
            grid = geometry.resample_grid(x.device, x.dtype, state.resample_map)
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
                tokens = _border_filled(tokens, valid[None])
        return tokens

    return forward


def _border_filled(tokens: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Tokens (N, hw, D) with every invalid one (``valid`` (N or 1, hw)) set to its image's mean valid token."""
    weights = valid.to(tokens.dtype)[..., None]
    mean = (tokens * weights).sum(dim=1, keepdim=True) / weights.sum(dim=1, keepdim=True).clamp(
        min=1
    )
    return torch.where(valid[..., None], tokens, mean)


def _rig_patch_embedding(state, original, x, resample: bool, border: bool):
    """:func:`patch_embedding` of a rig forward: image r resampled and masked as view r % V."""
    index = state.view_rows(x.shape[0], "patch embedding", x.device)
    geometries = state.geometry_views(x.shape[-2], x.shape[-1])
    if resample:
        # Only the images of views whose map is not the identity are resampled, so a pinhole
        # view of the rig stays bit-identical to upstream.
        parts = list(x.unbind(0))
        for view, geometry in enumerate(geometries):
            grid = geometry.resample_grid(x.device, x.dtype, state.resample_map)
            rows = (index == view).nonzero().flatten().tolist()
            if grid is None or not rows:
                continue
            sampled = F.grid_sample(
                x[rows],
                grid.expand(len(rows), -1, -1, -1),
                mode="bilinear",
                padding_mode="zeros",
                align_corners=False,
            )
            for row, image in zip(rows, sampled.unbind(0), strict=True):
                parts[row] = image
        x = torch.stack(parts).contiguous()
    tokens = original(x)
    if border:
        valid = [g.token_valid(tokens.device) for g in geometries]
        if any(v is not None for v in valid):
            hw = tokens.shape[1]
            full = torch.ones(hw, dtype=torch.bool, device=tokens.device)
            stacked = torch.stack([full if v is None else v for v in valid])
            tokens = _border_filled(tokens, stacked[index])
    return tokens


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
    """Apply the adapter's radial RoPE displacement to patch positions (..., patch_start + hw, 2).

    A rig's positions are (B, S, patch_start + hw, 2): view s is displaced as camera s % V.
    """
    if state.rig:
        frames = positions.shape[-3]
        state.check_views(frames, "RoPE positions")
        displacement = state.rope_displacement_views(height, width, positions.device, torch.float32)
        return displaced_positions(
            positions, patch_start, displacement.repeat(frames // len(state.views), 1, 1)
        )
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
        cells_h, cells_w, channels = x.shape[-2], x.shape[-1], x.shape[1]

        def embedding(geometry):
            def build():
                grid = geometry.uv_grid(cells_h, cells_w, x.device, x.dtype)
                if grid is None:
                    return None
                # The embedding depends only on camera and sizes, so it is computed once.
                return (
                    (to_embed(grid, channels) * ratio)
                    .permute(2, 0, 1)[None]
                    .to(x.dtype)
                    .contiguous()
                )

            return geometry.memo(
                ("grid_embed", cells_h, cells_w, channels, ratio, x.device, x.dtype), build
            )

        if state.rig:
            index = state.view_rows(x.shape[0], "prediction grid", x.device)
            embeds = [embedding(geometry) for geometry in state.geometry_views(H, W)]
            if all(embed is None for embed in embeds):
                return original(x, W, H, ratio)
            # A view whose grid is upstream's own (a pinhole camera) goes through upstream.
            plain = original(x, W, H, ratio) if any(embed is None for embed in embeds) else x
            parts = [
                plain[row] if embeds[view] is None else x[row] + embeds[view][0]
                for row, view in enumerate(index.tolist())
            ]
            return torch.stack(parts)
        embed = embedding(state.geometry(H, W))
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
    is_patch = (positions[..., 0] > 0) & (positions[..., 1] > 0)
    index = ((positions[..., 0] - 1) * cols + (positions[..., 1] - 1)).clamp(min=0)
    if state.rig:
        displacement = state.rope_displacement_views(
            rows * patch_size, cols * patch_size, positions.device, torch.float32
        )  # (V, h*w, 2)
        index = index + _token_views(positions, is_patch, rows * cols, state) * (rows * cols)
        displacement = displacement.flatten(0, 1)
    else:
        geometry = state.geometry(rows * patch_size, cols * patch_size)
        displacement = state.rope_displacement(
            geometry, positions.device, torch.float32
        )  # (h*w, 2), (y, x)
    offset = torch.where(is_patch[..., None], displacement[index], displacement.new_zeros(()))
    return positions.to(torch.float32) + offset


def _token_views(positions: torch.Tensor, is_patch: torch.Tensor, hw: int, state) -> torch.Tensor:
    """(..., N) view index of every token of a rig call, in either layout upstream uses.

    A per-frame call holds one image per row ((B S), N); a global call holds all S images of a
    sample in one row (B, S N). Patch tokens come in whole images of ``hw`` each, so the
    ordinal of a patch token in its row, divided by ``hw``, is its image within the row, and
    ``rows_before * images_per_row + image_in_row`` its image in (B S) order: view ``% V``.
    """
    flat = is_patch.reshape(-1, is_patch.shape[-1])
    per_row = int(flat[0].sum())
    if per_row % hw:
        raise InputError(
            f"RoPE positions: {per_row} patch tokens in a row are not whole images of {hw}"
        )
    images_per_row = per_row // hw
    if images_per_row > 1:
        state.check_views(images_per_row, "RoPE positions of a global block")
    ordinal = (flat.cumsum(dim=-1) - 1).clamp(min=0) // hw
    row = torch.arange(flat.shape[0], device=flat.device)[:, None]
    view = (row * images_per_row + ordinal) % len(state.views)
    if images_per_row == 1:
        state.view_rows(flat.shape[0], "RoPE positions")
    return view.reshape(is_patch.shape)


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
