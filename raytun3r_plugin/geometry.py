"""The parameter-free geometry of the patched hooks: maps from a camera's pixels to the grids,
weights and positions each hook needs.

Everything here depends only on (camera, input size, patch size) and is computed in float64;
:mod:`raytun3r_plugin.size_geometry` caches it per input size, so a patched forward only reads
it. Conventions (docs/conventions.md sections 2, 4, 5):

* pixel coordinates have the centre of the top-left pixel at (0, 0);
* token (i, j) of patch size p covers pixels [j p, (j + 1) p) x [i p, (i + 1) p), so its centre is
  ((j + 0.5) p - 0.5, (i + 0.5) p - 0.5) in that convention (docs/conventions.md section 4 writes the same point as
  ((j + 0.5) p, (i + 0.5) p) with pixel edges at integers);
* the fisheye-to-pinhole map ``M`` sends a pixel whose ray makes angle ``a`` with the optical axis
  and has image-plane direction (cos b, sin b) to (cx + fx g(a) cos b, cy + fy g(a) sin b), with
  g(a) = tan a up to ``a_k`` and its C1 linear continuation beyond.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from raytun3r_plugin.errors import InputError

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

DEFAULT_KNEE_DEG = 60.0
DEFAULT_MAX_STRETCH = 2.0
# A map that moves no pixel by more than this (in pixels) is the identity for our purposes: the
# corrections then defer to upstream code, so a pinhole camera reproduces upstream bit for bit.
IDENTITY_TOLERANCE_PX = 1e-6
ASPECT_TOLERANCE = 0.01
#: The naive PE remap's largest ray angle (degrees from the axis): a perspective projection
#: exists only below 90 degrees and grows without bound towards it, so rays beyond this angle,
#: and pixels outside the lens, are placed at this angle (docs/components.md).
NAIVE_MAX_ANGLE_DEG = 80.0


def camera_for_input(camera: Camera, height: int, width: int):
    """Return ``camera`` rescaled to a network input of ``height`` x ``width`` pixels.

    A pure resize is assumed (docs/conventions.md section 3). Crops must be stated by the caller with
    ``camera.cropped(...)`` before calling; an aspect-ratio change beyond 1% is refused.
    """
    if camera.width == width and camera.height == height:
        return camera
    native = camera.width / camera.height
    given = width / height
    if abs(given - native) / native > ASPECT_TOLERANCE:
        raise InputError(
            f"input of {width}x{height} px (aspect {given:.4f}) does not match the camera's "
            f"{camera.width}x{camera.height} px (aspect {native:.4f}); only a pure resize is "
            "implied; describe a crop explicitly with camera.cropped(x0, y0, w, h)"
        )
    return camera.resized(width, height)


def _g(angle: torch.Tensor, knee: float) -> torch.Tensor:
    """Radial pinhole mapping tan(a), continued linearly (C1) beyond ``knee`` radians."""
    tan_k = math.tan(knee)
    slope = 1.0 / math.cos(knee) ** 2
    return torch.where(
        angle <= knee, torch.tan(torch.clamp(angle, max=knee)), tan_k + (angle - knee) * slope
    )


def fisheye_to_pinhole(
    camera: Camera, uv: torch.Tensor, knee_deg: float = DEFAULT_KNEE_DEG
) -> torch.Tensor:
    """Apply the map ``M`` to pixels ``uv`` (..., 2) of ``camera``; returns pinhole pixels (..., 2).

    Pixels whose ray is invalid are returned unchanged.
    """
    rays, valid = camera.unproject(uv)
    dtype = uv.dtype
    xy = rays[..., :2]
    radius = xy.norm(dim=-1)
    angle = torch.atan2(radius, rays[..., 2])
    safe = radius.clamp_min(torch.finfo(dtype).tiny)
    direction = xy / safe.unsqueeze(-1)
    g = _g(angle, math.radians(knee_deg))
    fx, fy, cx, cy = (
        torch.as_tensor(v, dtype=dtype, device=uv.device)
        for v in (camera.fx, camera.fy, camera.cx, camera.cy)
    )
    mapped = torch.stack((cx + fx * g * direction[..., 0], cy + fy * g * direction[..., 1]), dim=-1)
    # On the axis the direction is undefined but M is the principal point itself.
    mapped = torch.where(
        (radius > 0).unsqueeze(-1),
        mapped,
        torch.stack((cx.expand_as(uv[..., 0]), cy.expand_as(uv[..., 1])), -1),
    )
    return torch.where(valid.unsqueeze(-1), mapped, uv)


def token_centres(height: int, width: int, patch: int, dtype=torch.float64) -> torch.Tensor:
    """Pixel centres of the patch tokens, (h*w, 2) as (x, y), row-major like the token order."""
    ys = (torch.arange(height // patch, dtype=dtype) + 0.5) * patch - 0.5
    xs = (torch.arange(width // patch, dtype=dtype) + 0.5) * patch - 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack((grid_x.reshape(-1), grid_y.reshape(-1)), dim=-1)


@dataclass(frozen=True)
class TokenPolar:
    """Polar coordinates of the token centres around the principal point (docs/conventions.md section 4).

    rho: (hw,) normalised radius in [0, 1]; theta: (hw,) angle in [0, 2 pi);
    direction_yx: (hw, 2) unit outward direction in (y, x) order, zero at the exact centre.
    """

    rho: torch.Tensor
    theta: torch.Tensor
    direction_yx: torch.Tensor


def token_polar(camera: Camera, height: int, width: int, patch: int) -> TokenPolar:
    centres = token_centres(height, width, patch)
    offset = torch.stack(
        ((centres[:, 0] - float(camera.cx)) / patch, (centres[:, 1] - float(camera.cy)) / patch),
        dim=-1,
    )
    radius = offset.norm(dim=-1)
    rho = radius / radius.max().clamp_min(1e-12)
    theta = torch.remainder(torch.atan2(offset[:, 1], offset[:, 0]), 2 * math.pi)
    direction = torch.where(
        (radius > 1e-9).unsqueeze(-1),
        offset / radius.clamp_min(1e-12).unsqueeze(-1),
        torch.zeros_like(offset),
    )
    return TokenPolar(rho=rho, theta=theta, direction_yx=direction.flip(-1))


def radial_weights(rho: torch.Tensor, n_bins: int) -> torch.Tensor:
    """Linear-interpolation weights (n, n_bins) for bins at k / (n_bins - 1), clamped at the ends."""
    position = rho.clamp(0.0, 1.0) * (n_bins - 1)
    lower = position.floor().clamp(max=n_bins - 2 if n_bins > 1 else 0).long()
    frac = position - lower
    weights = torch.zeros(rho.shape[0], n_bins, dtype=rho.dtype)
    weights.scatter_(1, lower[:, None], (1 - frac)[:, None])
    if n_bins > 1:
        weights.scatter_add_(1, (lower + 1)[:, None], frac[:, None])
    return weights


def angular_weights(theta: torch.Tensor, n_bins: int) -> torch.Tensor:
    """Weights (n, n_bins) for bins at 2 pi k / n_bins with wrap-around."""
    position = torch.remainder(theta, 2 * math.pi) / (2 * math.pi) * n_bins
    lower = position.floor().long() % n_bins
    frac = position - position.floor()
    weights = torch.zeros(theta.shape[0], n_bins, dtype=theta.dtype)
    weights.scatter_(1, lower[:, None], (1 - frac)[:, None])
    weights.scatter_add_(1, ((lower + 1) % n_bins)[:, None], frac[:, None])
    return weights


def _central_difference(map_pixels, points: torch.Tensor, step: float) -> torch.Tensor:
    """Jacobian of ``map_pixels`` ((n, 2) -> (n, 2)) at ``points`` (n, 2) -> (n, 2, 2) (rows:
    output x, y), by central differences of ``step`` pixels."""
    columns = []
    for axis in range(2):
        delta = torch.zeros(2, dtype=points.dtype)
        delta[axis] = step
        columns.append((map_pixels(points + delta) - map_pixels(points - delta)) / (2 * step))
    return torch.stack(columns, dim=-1)


def _jacobian_of_map(
    camera: Camera, points: torch.Tensor, knee_deg: float, step: float = 0.25
) -> torch.Tensor:
    """Jacobian dM/dx of the map to the pinhole on the axis at ``points`` (n, 2) -> (n, 2, 2)."""
    return _central_difference(lambda uv: fisheye_to_pinhole(camera, uv, knee_deg), points, step)


def _turned_pinhole_jacobian(
    camera: Camera, points: torch.Tensor, step: float = 0.25
) -> torch.Tensor:
    """(n, 2, 2) Jacobian at ``points`` (n, 2) of the map to a pinhole turned to each point's ray.

    The pinhole has the camera's focal lengths and looks along the ray of the point (turned by
    the smallest rotation, about z x ray), so at the point it has no perspective stretch: the
    Jacobian is the lens's own local scale against a pinhole's. Points without a ray get the
    identity.
    """
    rays, valid = camera.unproject(points)
    rays = rays.to(torch.float64)
    axis = torch.stack((-rays[:, 1], rays[:, 0], torch.zeros_like(rays[:, 0])), dim=-1)
    sin = axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    axis = axis / sin
    cos = rays[:, 2:3]
    focal = torch.tensor([float(camera.fx), float(camera.fy)], dtype=torch.float64)

    def in_turned_pinhole(uv: torch.Tensor) -> torch.Tensor:
        ray, _ = camera.unproject(uv)
        ray = ray.to(torch.float64)
        # Rodrigues' formula with the inverse rotation: the ray in the turned pinhole's frame.
        local = (
            ray * cos
            - torch.cross(axis, ray, dim=-1) * sin
            + axis * (axis * ray).sum(-1, keepdim=True) * (1 - cos)
        )
        return focal * local[:, :2] / local[:, 2:3].clamp_min(1e-9)

    jacobian = _central_difference(in_turned_pinhole, points, step)
    eye = torch.eye(2, dtype=torch.float64).expand_as(jacobian)
    return torch.where(valid.bool()[:, None, None], jacobian, eye)


def patch_resample_grid(
    camera: Camera,
    height: int,
    width: int,
    patch: int,
    knee_deg: float = DEFAULT_KNEE_DEG,
    max_stretch: float = DEFAULT_MAX_STRETCH,
    local_map: str = "central",
) -> torch.Tensor | None:
    """Normalised ``grid_sample`` grid (1, H, W, 2) that locally undistorts every patch.

    The output pixel at patch centre c plus offset e samples the input at c + A e, with A the
    inverse Jacobian at c of the map to a pinhole, singular values clamped to [1/s, s].
    ``local_map="central"`` (the default): the map M to the pinhole on the lens axis
    (``knee_deg``). Its perspective stretch away from the axis zooms rim patches in, so about
    half of a 185-degree lens reaches no patch, yet indoors the depth error is lower with it.
    ``"turned"``: a pinhole turned to look along c's ray, so each patch becomes a pinhole crop
    from its own viewing direction at the lens's local scale and every lens pixel is read; it
    keeps the network's rotation near vanilla's (docs/decisions.md, "Patch resampling's local
    map"). Returns None when A is the identity for every patch (then resampling is skipped and
    upstream tokens are reproduced exactly).
    """
    sample = _patch_sample_pixels(camera, height, width, patch, knee_deg, max_stretch, local_map)
    if sample is None:
        return None
    normalised = torch.stack(
        ((2 * sample[..., 0] + 1) / width - 1, (2 * sample[..., 1] + 1) / height - 1), dim=-1
    )
    return normalised[None]


def _patch_sample_pixels(
    camera: Camera,
    height: int,
    width: int,
    patch: int,
    knee_deg: float,
    max_stretch: float,
    local_map: str,
) -> torch.Tensor | None:
    """The input pixel (x, y) each output pixel of :func:`patch_resample_grid` samples, (H, W,
    2), or None when the resampling is the identity."""
    centres = token_centres(height, width, patch)
    if local_map == "turned":
        jac = _turned_pinhole_jacobian(camera, centres)
    elif local_map == "central":
        jac = _jacobian_of_map(camera, centres, knee_deg)
    else:
        raise InputError(f"local_map must be 'turned' or 'central', got {local_map!r}")
    inverse = torch.linalg.inv(jac)
    u, s, vh = torch.linalg.svd(inverse)
    s = s.clamp(1.0 / max_stretch, max_stretch)
    local = u @ torch.diag_embed(s) @ vh
    offsets_1d = torch.arange(patch, dtype=torch.float64) - (patch - 1) / 2
    oy, ox = torch.meshgrid(offsets_1d, offsets_1d, indexing="ij")
    offsets = torch.stack((ox, oy), dim=-1).reshape(-1, 2)  # (p*p, 2) as (x, y)
    displaced = torch.einsum("nij,kj->nki", local, offsets)  # (hw, p*p, 2)
    if (displaced - offsets).abs().max() < IDENTITY_TOLERANCE_PX:
        return None
    sample = centres[:, None, :] + displaced
    h, w = height // patch, width // patch
    return sample.reshape(h, w, patch, patch, 2).permute(0, 2, 1, 3, 4).reshape(height, width, 2)


def resampled_share(
    camera: Camera, height: int, width: int, patch: int, local_map: str = "central"
) -> float:
    """Fraction of the camera's valid pixels (at ``height`` x ``width``) that the bilinear taps
    of some patch read under :func:`patch_resample_grid` with ``local_map``; 1.0 when nothing is
    resampled. What the default map leaves unread: docs/components.md."""
    camera = camera_for_input(camera, height, width)
    # As the patch does: a camera whose map M is the identity is not resampled by either map.
    if map_is_identity(camera, DEFAULT_KNEE_DEG):
        return 1.0
    sample = _patch_sample_pixels(
        camera, height, width, patch, DEFAULT_KNEE_DEG, DEFAULT_MAX_STRETCH, local_map
    )
    if sample is None:
        return 1.0
    x, y = sample[..., 0], sample[..., 1]
    read = torch.zeros(height, width, dtype=torch.bool)
    for column in (x.floor(), x.floor() + 1):
        for row in (y.floor(), y.floor() + 1):
            inside = (column >= 0) & (column < width) & (row >= 0) & (row < height)
            read[row[inside].long(), column[inside].long()] = True
    valid = camera.valid_mask().bool()
    return float((read & valid).sum() / valid.sum())


def naive_pe_positions(
    camera: Camera,
    height: int,
    width: int,
    patch: int,
    max_angle_deg: float = NAIVE_MAX_ANGLE_DEG,
) -> torch.Tensor | None:
    """Where the naive PE remap reads the backbone's PE table, (h*w, 2) as (column, row).

    The ablation ``"pe_naive_remap"`` (docs/components.md): each token centre is undistorted to
    the perspective image of the same intrinsics, ``c + (fx tan(a) dx, fy tan(a) dy)`` with
    ``a`` the angle of its ray from the axis, clamped to ``max_angle_deg``, and ``d`` the ray's
    unit image-plane direction (a pixel without a ray, outside the lens, is put at the clamp
    angle in its own direction from the principal point). The undistorted points are then scaled
    about the principal point, one factor for both axes, so that their extent fits the token
    grid's, and expressed in token units: token (i, j) of the unchanged grid sits at (j, i).

    Args:
        camera: the camera at the input size (``height`` x ``width`` px).
        height, width: input size in pixels, multiples of ``patch``.
        patch: patch size in pixels.
        max_angle_deg: the clamp angle, below 90 degrees.

    Returns:
        (h*w, 2) float64 fractional (column, row) positions in the h x w table, row-major like
        the tokens, clamped to the grid; None when every position is within
        :data:`IDENTITY_TOLERANCE_PX` (divided by ``patch``) of its own token (e.g. a pinhole
        camera), so that upstream's table is used unchanged.
    """
    if not 0.0 < max_angle_deg < 90.0:
        raise InputError(f"max_angle_deg must be in (0, 90) degrees, got {max_angle_deg}")
    centres = token_centres(height, width, patch)
    principal = torch.tensor([float(camera.cx), float(camera.cy)], dtype=torch.float64)
    focal = torch.tensor([float(camera.fx), float(camera.fy)], dtype=torch.float64)
    rays, valid = camera.unproject(centres)
    rays = rays.to(torch.float64)
    valid = valid.bool()
    xy = rays[..., :2]
    radius = xy.norm(dim=-1)
    angle = torch.atan2(radius, rays[..., 2])
    # Outside the lens there is no ray: the pixel's own direction in normalised coordinates.
    offset = (centres - principal) / focal
    offset_norm = offset.norm(dim=-1)
    ray_direction = xy / radius.clamp_min(1e-300).unsqueeze(-1)
    pixel_direction = offset / offset_norm.clamp_min(1e-300).unsqueeze(-1)
    direction = torch.where(
        (valid & (radius > 0)).unsqueeze(-1),
        ray_direction,
        torch.where((~valid & (offset_norm > 0)).unsqueeze(-1), pixel_direction, 0.0),
    )
    limit = math.radians(max_angle_deg)
    angle = torch.where(valid, angle.clamp(max=limit), torch.full_like(angle, limit))
    undistorted = principal + focal * torch.tan(angle).unsqueeze(-1) * direction
    # One scale for both axes (the perspective image is not stretched), the largest that keeps
    # the undistorted extent inside the token grid's on each axis.
    grid_extent = (centres - principal).abs().amax(dim=0)
    reached = (undistorted - principal).abs().amax(dim=0)
    ratios = [float(g / r) for g, r in zip(grid_extent, reached, strict=True) if float(r) > 0]
    scale = min(ratios) if ratios else 1.0
    positions = principal + scale * (undistorted - principal)
    if float((positions - centres).abs().max()) < IDENTITY_TOLERANCE_PX:
        return None
    rows, cols = height // patch, width // patch
    column = ((positions[:, 0] + 0.5) / patch - 0.5).clamp(0.0, cols - 1)
    row = ((positions[:, 1] + 0.5) / patch - 0.5).clamp(0.0, rows - 1)
    return torch.stack((column, row), dim=-1)


def resize_mask(mask: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """An (H, W) bool mask at ``size = (h, w)``, nearest neighbour (it stays binary; unchanged
    when already that size). The one resize for scene masks: the patched model, ``apply``'s
    check and adaptation must agree on which pixels a mask excludes."""
    mask = mask.bool()
    if tuple(mask.shape) == tuple(size):
        return mask
    return F.interpolate(mask[None, None].float(), size=tuple(size), mode="nearest")[0, 0] > 0.5


def token_validity(valid_pixels: torch.Tensor, patch: int) -> torch.Tensor:
    """(hw,) bool: tokens with at least half of their pixels valid. ``valid_pixels`` is (H, W)."""
    fraction = F.avg_pool2d(valid_pixels[None, None].double(), patch, stride=patch)[0, 0]
    return (fraction >= 0.5).reshape(-1)


def head_uv_grid(
    camera: Camera,
    height: int,
    width: int,
    cells_h: int,
    cells_w: int,
    knee_deg: float = DEFAULT_KNEE_DEG,
) -> torch.Tensor:
    """Camera-aware version of the DPT heads' normalised uv grid, (cells_h, cells_w, 2) as (u, v).

    Cell centres of a cells_h x cells_w grid over the image go through ``M``; the affine
    normalisation is the upstream one (half-diagonal of the image plane = 1), so an identity ``M``
    gives the upstream grid.
    """
    ys = (torch.arange(cells_h, dtype=torch.float64) + 0.5) * (height / cells_h) - 0.5
    xs = (torch.arange(cells_w, dtype=torch.float64) + 0.5) * (width / cells_w) - 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    mapped = fisheye_to_pinhole(camera, torch.stack((grid_x, grid_y), dim=-1), knee_deg)
    aspect = width / height
    diagonal = math.sqrt(aspect**2 + 1.0)
    u = (aspect / diagonal) * (mapped[..., 0] - (width - 1) / 2) / (width / 2)
    v = (1.0 / diagonal) * (mapped[..., 1] - (height - 1) / 2) / (height / 2)
    return torch.stack((u, v), dim=-1)


def map_is_identity(camera: Camera, knee_deg: float = DEFAULT_KNEE_DEG) -> bool:
    """True when ``M`` moves no pixel of the image (a pinhole whose field lies inside the knee)."""
    ys = torch.linspace(0, camera.height - 1, 17, dtype=torch.float64)
    xs = torch.linspace(0, camera.width - 1, 17, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)
    return bool(
        (fisheye_to_pinhole(camera, grid, knee_deg) - grid).abs().max() < IDENTITY_TOLERANCE_PX
    )
