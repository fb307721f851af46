"""Equidistant-family fisheye models: :class:`KannalaBrandt4` and :class:`ThinPrismFisheye`."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

from raytun3r_plugin.cameras._math import (
    RadialTable,
    RadTan,
    angle_ratio,
    odd_poly_fold,
    radial_poly,
    safe_sqrt,
    small_threshold,
    solve_odd_poly,
    undistort,
    unit,
)
from raytun3r_plugin.cameras.base import Camera

__all__ = ["KannalaBrandt4", "ThinPrismFisheye"]


def _odd_poly(t: np.ndarray, ks: list[float]) -> np.ndarray:
    """t (1 + k1 t^2 + k2 t^4 + ...) in numpy (for the radial tables)."""
    t2 = t * t
    acc = np.zeros_like(t)
    for k in reversed(ks):
        acc = (acc + k) * t2
    return t * (1.0 + acc)


@functools.lru_cache(maxsize=256)
def _equidistant_table(ks: tuple[float, ...], limit: float) -> RadialTable:
    """Inverse table of theta_d = theta (1 + k1 theta^2 + ...) up to its fold (at most
    ``limit``). Cached: it depends only on the distortion, so resized / cropped copies of a
    camera share it."""
    fold = odd_poly_fold(list(ks), limit)
    return RadialTable.from_angles(fold, lambda th: th, lambda t: _odd_poly(t, list(ks)))


def _unit_points(points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Unit direction (x, y, z) of the points and the mask of non-zero points."""
    n2 = (points * points).sum(dim=-1)
    nonzero = n2 > 0
    s = points / safe_sqrt(n2).unsqueeze(-1)
    x, y, z = s.unbind(-1)
    return x, y, z, nonzero


def _ray_from_angle(
    theta: Tensor, dx: Tensor, dy: Tensor, r2: Tensor, small: Tensor, series: Tensor
) -> Tensor:
    """Unit ray at angle ``theta`` from the axis in image-plane direction (dx, dy) / sqrt(r2).

    ``sin(theta) / r`` is replaced near the axis (``small``) by the series value ``series``
    (the caller knows how theta depends on r there).
    """
    r = torch.sqrt(torch.where(small, torch.ones_like(r2), r2))
    scale = torch.where(small, series, torch.sin(theta) / r)
    return torch.stack([scale * dx, scale * dy, torch.cos(theta)], dim=-1)


class KannalaBrandt4(Camera):
    """Kannala-Brandt with 4 coefficients (OpenCV ``cv2.fisheye``, COLMAP ``OPENCV_FISHEYE``,
    Kalibr ``pinhole`` + ``equidistant``, basalt ``kb4``).

    Project: ``theta = atan2(r, z)`` (so rays beyond 90 degrees work),
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``,
    ``u = fx theta_d x / r + cx``, ``v = fy theta_d y / r + cy``.

    Unproject: ``m = ((u - cx) / fx, (v - cy) / fy)``, solve ``theta_d(theta) = |m|``: start in
    the cell of a 2048-entry table of theta_d(theta) that holds the root, 2 Newton
    steps (clamped to the cell) plus one differentiable step; ray
    ``(sin(theta) m / |m|, cos(theta))``.

    ``max_angle``: the first angle where ``theta_d`` stops increasing (where
    ``1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8`` reaches 0), at most pi; tighter if
    ``max_fov_deg`` is given. Pixels with ``|m| > theta_d(max_angle)`` are invalid.
    """

    model = "kb4"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _fold: float
    _table: RadialTable
    _td_max: float
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    distortion_names = ("k1", "k2", "k3", "k4")
    newton_steps = 2

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        table = _equidistant_table((p["k1"], p["k2"], p["k3"], p["k4"]), math.pi)
        fold = table.t_max
        self._set("_fold", fold)
        self._set("_table", table)
        # theta_d at the fold: the radius of the image circle in normalised units.
        self._set("_td_max", table.g_max)
        return fold

    def _ks(self, p: Tensor) -> list[Tensor]:
        return [p[4], p[5], p[6], p[7]]

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z, nonzero = _unit_points(points)
        theta2, ratio, theta = angle_ratio(x, y, z)
        g = ratio * radial_poly(theta2, self._ks(p))  # theta_d / r
        uv = torch.stack([p[0] * g * x + p[2], p[1] * g * y + p[3]], dim=-1)
        # Strict bound: at the fold (or the back pole) several rays share one pixel.
        valid = nonzero & (theta < self._fold)
        return uv, valid

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        ks = self._ks(p)
        td2 = mx * mx + my * my
        small = td2 < small_threshold(uv.dtype)
        td = safe_sqrt(td2)
        theta = solve_odd_poly(td, ks, self._values[4:8], self._table, self.newton_steps)
        # Near the axis theta = td (1 - k1 td^2 + ...), so sin(theta) / td = 1 - (k1 + 1/6) td^2.
        series = 1.0 - (ks[0] + 1.0 / 6.0) * td2
        rays = _ray_from_angle(theta, mx, my, td2, small, series)
        with torch.no_grad():
            valid = td2 < self._td_max**2
        return rays, valid


class ThinPrismFisheye(Camera):
    """COLMAP ``THIN_PRISM_FISHEYE`` (ETH3D), defined for theta < 90 degrees only.

    Equidistant coordinates ``(a, b) = theta (x, y) / r`` (theta = atan2(r, z)), then with
    ``r2 = a^2 + b^2`` and ``R = k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4``:
    ``a' = a (1 + R) + 2 p1 a b + p2 (r2 + 2 a^2) + sx1 r2``,
    ``b' = b (1 + R) + 2 p2 a b + p1 (r2 + 2 b^2) + sy1 r2``, ``u = fx a' + cx``.
    Parameter order as COLMAP: fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1.

    ``max_angle``: ``pi / 2`` (open), or the fold of the radial part if it comes earlier
    (tangential and prism terms ignored for the bound). Unprojection: start at the tabulated
    inverse of the radial part, 2 fixed 2-D Newton steps plus a differentiable one; valid where
    it converged with theta < max_angle.
    """

    model = "thin_prism_fisheye"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _fold: float
    _table: RadialTable
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")
    distortion_names = param_names[4:]
    newton_steps = 2

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        table = _equidistant_table((p["k1"], p["k2"], p["k3"], p["k4"]), math.pi / 2)
        self._set("_fold", table.t_max)
        self._set("_table", table)
        return table.t_max

    def _dist(self, p: Tensor | tuple[float, ...]) -> RadTan:
        return RadTan([p[4], p[5], p[8], p[9]], p[6], p[7], p[10], p[11])

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z, nonzero = _unit_points(points)
        _theta2, ratio, theta = angle_ratio(x, y, z)
        ad, bd = self._dist(p)(ratio * x, ratio * y)
        uv = torch.stack([p[0] * ad + p[2], p[1] * bd + p[3]], dim=-1)
        return uv, nonzero & (z > 0) & (theta < self._fold)

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        a, b, ok = undistort(
            self._dist(p), self._dist(self._values), mx, my, self._table, self.newton_steps
        )
        t2 = a * a + b * b
        small = t2 < small_threshold(uv.dtype)
        theta = safe_sqrt(t2)
        rays = _ray_from_angle(theta, a, b, t2, small, 1.0 - t2 / 6.0)
        return unit(rays), ok
