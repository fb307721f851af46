"""The PE-Jacobian analysis: how fast a backbone's absolute PE changes with position, by radius.

A pinhole-trained PE table is smooth and nearly isotropic, so its Jacobian against the token
position is about constant over the image (flat curves). A fisheye image packs more of the
scene into each token towards the rim; a PE that followed the rays instead of the pixels would
change faster there, by the camera's own stretch. These curves put the two side by side: the
model's PE Jacobian per radius bin (pretrained, or with an adapter applied) and the analytic
reference of the camera.

Definitions (docs/analysis.md):

- the PE field P(x, y) in R^C is the table the backbone adds to its patch tokens at the input
  size, read through the backbone's own interpolation (and raytun3r's hook when applied);
- its Jacobian J = [dP/dx, dP/dy] (C x 2, per token step) by central differences, one-sided at
  the border; sigma_1 its largest singular value, the area element sqrt(det J^T J);
- rho = the token centre's distance from the principal point divided by the distance from the
  principal point to the nearest grid edge (tokens with rho > 1, the corners, are left out);
- every curve is divided by its innermost bin, so it starts at 1 and curves of different
  models share an axis. The pinhole reference is flat at 1.
- reference: for a radially symmetric lens r_d = d(theta), sigma_1 / sigma_1(0) =
  sec^2(theta) / d'(theta) and area / area(0) = sec^2(theta) tan(theta) / (d(theta) d'(theta)),
  with d(theta) read from the camera's own ``project`` (any camera model).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.errors import InputError, UnsupportedUpstreamError

if TYPE_CHECKING:
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["JacobianCurves", "jacobian_of_field", "pe_field", "pe_jacobian", "reference_curves"]


@dataclass
class JacobianCurves:
    """Per-radius-bin statistics of the PE Jacobian, each normalised at the innermost bin.

    Attributes:
        rho: (bins,) bin centres in [0, 1].
        sigma1, area: (bins, 3) the 25th, 50th and 75th percentile per bin (NaN for an empty bin).
        count: (bins,) tokens per bin.
        scale: the innermost bin's median sigma_1 and area before normalisation (per token step).
    """

    rho: torch.Tensor
    sigma1: torch.Tensor
    area: torch.Tensor
    count: torch.Tensor
    scale: dict[str, float] = field(default_factory=dict)


def pe_field(model: nn.Module, width: int, height: int) -> torch.Tensor:
    """The absolute PE a backbone adds to its patch tokens at a ``width x height`` input.

    Read through the backbone's declared PE target (``hook="pe"``), so a patched model gives the
    corrected field. Returns (h, w, C) float64 over the h x w patch grid.
    """
    from raytun3r_plugin.registry import resolve_path, spec_for

    spec, root = spec_for(model)
    info = spec.describe(root)
    if info.pos_embed is None:
        raise UnsupportedUpstreamError(f"{info.name}: has no absolute PE table to analyse")
    patch = info.patch_size
    if width % patch or height % patch:
        raise InputError(f"input {width}x{height} is not a multiple of the patch size {patch}")
    targets = [target for target in spec.targets if target.hook == "pe"]
    if not targets:
        raise UnsupportedUpstreamError(f"{spec.family}: declares no PE target")
    target = targets[0]
    owner = resolve_path(root, target.owners[0])
    h, w = height // patch, width // patch
    rows = info.pos_embed.shape[1]
    prefix = rows - int(round(math.sqrt(rows - 1))) ** 2  # the class slot(s) before the grid
    tokens = torch.zeros(1, prefix + h * w, info.embed_dim, dtype=info.pos_embed.dtype)
    with torch.no_grad():
        # DINOv2-style interpolate_pos_encoding(x, w, h): its "w" receives the image height
        # (docs/conventions.md section 6).
        table = getattr(owner, target.attribute)(tokens, height, width)
    grid = table[0, -h * w :].to(torch.float64)
    return grid.reshape(h, w, -1)


def jacobian_of_field(grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """sigma_1 and the area element of a (h, w, C) field's Jacobian, per token step.

    Central differences inside, one-sided at the border. Returns two (h, w) float64 tensors.
    """
    grid = grid.to(torch.float64)
    dx = torch.gradient(grid, dim=1)[0]
    dy = torch.gradient(grid, dim=0)[0]
    aa, bb, ab = (dx * dx).sum(-1), (dy * dy).sum(-1), (dx * dy).sum(-1)
    half_trace = (aa + bb) / 2
    det = (aa * bb - ab * ab).clamp_min(0.0)
    lam1 = half_trace + (half_trace**2 - det).clamp_min(0.0).sqrt()
    return lam1.sqrt(), det.sqrt()


def token_rho(h: int, w: int, patch: int, cx: float, cy: float) -> torch.Tensor:
    """rho of every token centre (h, w): distance from (cx, cy) over the distance to the nearest
    edge of the grid, both in pixels of the input."""
    ys = (torch.arange(h, dtype=torch.float64) + 0.5) * patch - 0.5
    xs = (torch.arange(w, dtype=torch.float64) + 0.5) * patch - 0.5
    edge = min(cx + 0.5, w * patch - 0.5 - cx, cy + 0.5, h * patch - 0.5 - cy)
    if edge <= 0:
        raise InputError(f"principal point ({cx:.1f}, {cy:.1f}) is outside the token grid")
    distance = torch.hypot(xs[None, :] - cx, ys[:, None] - cy)
    return distance / edge


def _binned(
    values: torch.Tensor, rho: torch.Tensor, bins: int
) -> tuple[torch.Tensor, torch.Tensor]:
    quantiles = torch.full((bins, 3), float("nan"), dtype=torch.float64)
    count = torch.zeros(bins, dtype=torch.int64)
    index = (rho * bins).floor().clamp_max(bins - 1).long()
    inside = rho <= 1.0
    q = torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)
    for k in range(bins):
        members = values[inside & (index == k)]
        count[k] = members.numel()
        if members.numel():
            quantiles[k] = torch.quantile(members, q)
    return quantiles, count


def _normalised(stats: torch.Tensor) -> tuple[torch.Tensor, float]:
    first = next((float(row[1]) for row in stats if math.isfinite(float(row[1]))), float("nan"))
    if not math.isfinite(first) or first == 0.0:
        return stats, first
    return stats / first, first


def pe_jacobian(
    model: nn.Module,
    width: int,
    height: int,
    *,
    camera: Camera | None = None,
    bins: int = 20,
) -> JacobianCurves:
    """PE-Jacobian curves of ``model`` at a ``width x height`` input.

    Args:
        model: any registered backbone with an absolute PE table, patched or not.
        width, height: input size in pixels, multiples of the patch size.
        camera: sets the principal point (resized to the input); default: the image centre.
        bins: radius bins over rho in [0, 1].
    """
    from raytun3r_plugin.registry import spec_for

    spec, root = spec_for(model)
    patch = spec.describe(root).patch_size
    grid = pe_field(model, width, height)
    sigma1, area = jacobian_of_field(grid)
    if camera is None:
        cx, cy = (width - 1) / 2, (height - 1) / 2
    else:
        resized = camera.resized(width, height)
        cx, cy = float(resized.cx), float(resized.cy)
    h, w = grid.shape[:2]
    rho = token_rho(h, w, patch, cx, cy)
    sigma_stats, count = _binned(sigma1, rho, bins)
    area_stats, _ = _binned(area, rho, bins)
    sigma_stats, sigma0 = _normalised(sigma_stats)
    area_stats, area0 = _normalised(area_stats)
    centres = (torch.arange(bins, dtype=torch.float64) + 0.5) / bins
    return JacobianCurves(
        centres, sigma_stats, area_stats, count, {"sigma1": sigma0, "area": area0}
    )


def reference_curves(
    camera: Camera, rho: torch.Tensor, width: int, height: int
) -> dict[str, torch.Tensor]:
    """The camera's analytic reference at radii ``rho`` of a ``width x height`` input.

    A pixel at rho is r = rho R from the principal point (R: distance to the nearest image edge);
    theta is the angle of its ray, d(theta) = r / f the lens mapping and d'(theta) its
    derivative, both read from ``camera.project`` along the +x axis. Returns ``{"sigma1",
    "area"}``, (len(rho),) each, normalised to 1 at theta = 0; NaN beyond the lens's domain.
    """
    cam = camera.resized(width, height)
    cx, cy, fx = float(cam.cx), float(cam.cy), float(cam.fx)
    edge = min(cx + 0.5, width - 0.5 - cx, cy + 0.5, height - 0.5 - cy)
    pixels = torch.stack(
        [cx + rho.to(torch.float64) * edge, torch.full_like(rho, cy, dtype=torch.float64)], -1
    )
    rays, valid = cam.unproject(pixels)
    theta = torch.atan2(rays[..., :2].norm(dim=-1), rays[..., 2])
    step = 1e-4

    def d(angle: torch.Tensor) -> torch.Tensor:
        points = torch.stack([angle.sin(), torch.zeros_like(angle), angle.cos()], -1)
        uv, _ = cam.project(points)
        return (uv[..., 0] - cx) / fx

    slope = (d(theta + step) - d((theta - step).clamp_min(0.0))) / (
        theta + step - (theta - step).clamp_min(0.0)
    )
    slope0 = float(((d(torch.tensor([step], dtype=torch.float64)) - 0.0) / step)[0])
    sec2 = 1.0 / theta.cos() ** 2
    sigma1 = sec2 / (slope / slope0)
    tan_over_d = torch.where(
        theta > 1e-6, theta.tan() / (d(theta) / slope0), torch.ones_like(theta)
    )
    area = sigma1 * tan_over_d
    nan = torch.full_like(sigma1, float("nan"))
    ok = valid & (theta < math.pi / 2 - 1e-3)
    return {"sigma1": torch.where(ok, sigma1, nan), "area": torch.where(ok, area, nan)}


def curves_table(
    curves: Mapping[str, JacobianCurves], reference: Mapping[str, torch.Tensor] | None = None
) -> list[dict[str, Any]]:
    """Rows for a CSV: one per bin, the median and IQR of each named curve, and the reference."""
    names = list(curves)
    first = curves[names[0]]
    rows = []
    for k in range(first.rho.numel()):
        row: dict[str, Any] = {"rho": round(float(first.rho[k]), 4), "tokens": int(first.count[k])}
        for name in names:
            for quantity in ("sigma1", "area"):
                q25, q50, q75 = (float(v) for v in getattr(curves[name], quantity)[k])
                row[f"{name}_{quantity}"] = q50
                row[f"{name}_{quantity}_q25"] = q25
                row[f"{name}_{quantity}_q75"] = q75
        if reference is not None:
            row["reference_sigma1"] = float(reference["sigma1"][k])
            row["reference_area"] = float(reference["area"][k])
        rows.append(row)
    return rows
