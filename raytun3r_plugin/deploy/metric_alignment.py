"""Nested DA3's metric alignment with no data-dependent shape: what a frozen
``NestedDepthAnything3Net`` runs in place of upstream's masked quantiles.

Upstream (``depth_anything_3.model.da3``) selects the non-sky pixels with a boolean mask
(``x[mask]``, a tensor whose length is read from the data), takes ``torch.quantile`` over
them, and branches in Python on pixel counts; ``torch.export`` can trace none of that. For a
fixed input size the same numbers come from whole-tensor operations: :func:`masked_quantile`
sorts all values with the unselected ones pushed to the end and reads the quantile at the rank
computed from the selected count, exactly as ``torch.quantile`` (``'linear'``) computes it, and
the counts' branches become ``torch.where``. Three upstream methods are replaced on the frozen
copy (``deploy.freeze``), each taking upstream's own elementwise helpers from upstream's module:

* ``DepthAnything3Net._process_mono_sky_estimation`` (the metric branch's sky handling);
* ``NestedDepthAnything3Net._apply_depth_alignment`` (median confidence, least-squares scale);
* ``NestedDepthAnything3Net._handle_sky_regions`` (sky set to the 0.99 quantile, at most 200).

What differs from upstream, and why (docs/deployment.md): upstream subsamples at random when
more than 100000 pixels are selected (a different draw on every call); these use all of them.
The least-squares scale sums over the masked whole tensor instead of the compacted pixels, so
its float32 rounding may differ in the last bits. Where upstream raises (at most 10 non-sky
pixels: ``AssertionError``), these raise the same in eager and, in a traced graph that cannot
raise, return NaN depth and translation. The frozen output carries no ``scale_factor`` (upstream
reads it with ``.item()``, a host value a graph does not have).
"""

from __future__ import annotations

import sys
from types import ModuleType

import torch
from torch import nn

#: Upstream's thresholds (``depth_anything_3.model.da3``).
SKY_THRESHOLD = 0.3
MIN_NON_SKY_PIXELS = 10
#: Upstream's message where too few pixels are not sky (patches/da3.py turns it into InputError).
INSUFFICIENT_NON_SKY = "Insufficient non-sky pixels for alignment"


def masked_quantile(values: torch.Tensor, mask: torch.Tensor, q: float) -> torch.Tensor:
    """``torch.quantile(values[mask], q)`` ('linear') without the data-dependent ``values[mask]``.

    values, mask: tensors of one shape (any). Returns a 0-d tensor of values' dtype: bit for bit
    torch.quantile's (same rank in the input's dtype, same truncation and ceiling, same lerp),
    NaN where a selected value is NaN (as torch.quantile) and NaN for an empty selection (where
    torch.quantile raises).
    """
    flat, selected = values.reshape(-1), mask.reshape(-1)
    count = selected.sum()
    infinity = torch.full_like(flat, float("inf"))
    ordered = torch.sort(torch.where(selected, flat, infinity)).values
    # torch.quantile: rank = q * (n - 1) in the input's dtype (q is a tensor of that dtype).
    rank = torch.tensor(q, dtype=flat.dtype, device=flat.device) * (count - 1).clamp(min=0)
    below = rank.to(torch.long)
    weight = rank - below
    above = rank.ceil().to(torch.long)
    result = torch.lerp(ordered[below], ordered[above], weight)
    has_nan = (torch.isnan(flat) & selected).any()
    return torch.where(has_nan | (count == 0), torch.full_like(result, float("nan")), result)


def _upstream_module(owner: nn.Module) -> ModuleType:
    """Upstream's module of ``owner``'s class: its own helpers (compute_alignment_mask, ...)."""
    return sys.modules[type(owner).__module__]


def _tracing() -> bool:
    return bool(
        torch.compiler.is_compiling()
        or torch.compiler.is_exporting()
        or torch.jit.is_tracing()
        or torch.jit.is_scripting()
    )


def _fill_sky(depth, conf, non_sky, value):
    """``set_sky_regions_to_max_depth`` without boolean-index assignment: the same values."""
    depth = torch.where(non_sky, depth, value.to(depth.dtype))
    if conf is not None:
        conf = torch.where(non_sky, conf, torch.ones_like(conf))
    return depth, conf


def frozen_mono_sky_estimation(owner: nn.Module, output):
    """Upstream's ``DepthAnything3Net._process_mono_sky_estimation``: sky pixels set to the 0.99
    quantile of the other depths, only where more than 10 pixels are sky and more than 10 not."""
    if "sky" not in output:
        return output
    non_sky = _upstream_module(owner).compute_sky_mask(output.sky, threshold=SKY_THRESHOLD)
    count = non_sky.sum()
    applies = (count > MIN_NON_SKY_PIXELS) & (non_sky.numel() - count > MIN_NON_SKY_PIXELS)
    non_sky_max = masked_quantile(output.depth, non_sky, 0.99)
    filled, _ = _fill_sky(output.depth, None, non_sky, non_sky_max)
    output.depth = torch.where(applies, filled, output.depth)
    return output


def frozen_depth_alignment(owner: nn.Module, output, metric_output):
    """Upstream's ``NestedDepthAnything3Net._apply_depth_alignment``: the least-squares scale of
    the depth onto the metric depth, over confident, non-sky pixels, applied to the depth and
    the translations."""
    upstream = _upstream_module(owner)
    non_sky = upstream.compute_sky_mask(metric_output.sky, threshold=SKY_THRESHOLD)
    count = non_sky.sum()
    if not _tracing() and not bool(count > MIN_NON_SKY_PIXELS):
        raise AssertionError(INSUFFICIENT_NON_SKY)
    median_conf = masked_quantile(output.depth_conf, non_sky, 0.5)
    align = upstream.compute_alignment_mask(
        output.depth_conf, non_sky, output.depth, metric_output.depth, median_conf
    )
    zero = torch.zeros((), dtype=output.depth.dtype, device=output.depth.device)
    metric = torch.where(align, metric_output.depth, zero).reshape(-1)
    depth = torch.where(align, output.depth, zero).reshape(-1)
    scale = torch.dot(metric, depth) / torch.dot(depth, depth).clamp_min(1e-12)
    scale = torch.where(count > MIN_NON_SKY_PIXELS, scale, torch.full_like(scale, float("nan")))
    output.depth = output.depth * scale
    extrinsics = output.extrinsics.clone()
    extrinsics[:, :, :3, 3] = extrinsics[:, :, :3, 3] * scale
    output.extrinsics = extrinsics
    output.is_metric = 1
    return output


def frozen_sky_regions(owner: nn.Module, output, metric_output, sky_depth_def: float = 200.0):
    """Upstream's ``NestedDepthAnything3Net._handle_sky_regions``: sky pixels set to the 0.99
    quantile of the non-sky depth (at most ``sky_depth_def``), their confidence to 1."""
    non_sky = _upstream_module(owner).compute_sky_mask(metric_output.sky, threshold=SKY_THRESHOLD)
    quantile = masked_quantile(output.depth, non_sky, 0.99)
    # Python's min(quantile, 200.0) as upstream calls it: 200 only where 200 < quantile.
    cap = torch.full_like(quantile, sky_depth_def)
    non_sky_max = torch.where(cap < quantile, cap, quantile)
    output.depth, output.depth_conf = _fill_sky(
        output.depth, output.depth_conf, non_sky, non_sky_max
    )
    return output
