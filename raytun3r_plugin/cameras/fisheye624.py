"""COLMAP's ``RAD_TAN_THIN_PRISM_FISHEYE``, Project Aria's ``Fisheye624`` camera model."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from raytun3r_plugin.cameras._math import (
    Coef,
    RadialTable,
    angle_ratio,
    radial_poly,
    safe_sqrt,
    small_threshold,
    solve_odd_poly,
    undistort,
)
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.kb import _equidistant_table, _ray_from_angle, _unit_points

__all__ = ["Fisheye624"]


class _TangentialPrism:
    """The second stage of Fisheye624: tangential and thin-prism terms on the radially scaled
    point ``(x, y)``, ``r2 = x^2 + y^2``:
    ``x' = x + 2 p1 x y + p0 (r2 + 2 x^2) + s0 r2 + s1 r2^2``,
    ``y' = y + 2 p0 x y + p1 (r2 + 2 y^2) + s2 r2 + s3 r2^2``.
    The interface of :class:`raytun3r_plugin.cameras._math.RadTan`, so :func:`undistort` inverts it.
    """

    def __init__(self, p0: Coef, p1: Coef, s: Sequence[Coef]) -> None:
        self.p0, self.p1 = p0, p1
        self.s0, self.s1, self.s2, self.s3 = s

    def __call__(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        r2 = x * x + y * y
        r4 = r2 * r2
        xy2 = 2.0 * x * y
        xd = x + self.p1 * xy2 + self.p0 * (r2 + 2.0 * x * x) + self.s0 * r2 + self.s1 * r4
        yd = y + self.p0 * xy2 + self.p1 * (r2 + 2.0 * y * y) + self.s2 * r2 + self.s3 * r4
        return xd, yd

    def with_jacobian(
        self, x: Tensor, y: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Distorted (x', y') and d(x', y')/d(x, y) = [[a, b], [c, d]]."""
        xd, yd = self(x, y)
        r2 = x * x + y * y
        a = 1.0 + 2.0 * self.p1 * y + 6.0 * self.p0 * x + 2.0 * self.s0 * x + 4.0 * self.s1 * r2 * x
        b = 2.0 * self.p1 * x + 2.0 * self.p0 * y + 2.0 * self.s0 * y + 4.0 * self.s1 * r2 * y
        c = 2.0 * self.p0 * y + 2.0 * self.p1 * x + 2.0 * self.s2 * x + 4.0 * self.s3 * r2 * x
        d = 1.0 + 2.0 * self.p0 * x + 6.0 * self.p1 * y + 2.0 * self.s2 * y + 4.0 * self.s3 * r2 * y
        return xd, yd, a, b, c, d

    # The Newton iterations call this without autograd; the terms are few, so no fused variant.
    with_jacobian_fast = with_jacobian


@functools.lru_cache(maxsize=256)
def _identity_table(g_max: float) -> RadialTable:
    """Start points for inverting :class:`_TangentialPrism`: the identity on [0, g_max] (the
    distorted point is close to the undistorted one), and the disc the iterates stay in."""
    return RadialTable.from_angles(g_max, lambda t: t, lambda t: np.asarray(t, dtype=np.float64))


class Fisheye624(Camera):
    """COLMAP ``RAD_TAN_THIN_PRISM_FISHEYE`` = Project Aria ``Fisheye624``.

    Equidistant coordinates ``(a, b) = theta (x, y) / r`` (theta = atan2(r, z)), a radial factor
    on them, ``(a_r, b_r) = (a, b) (1 + k0 theta^2 + k1 theta^4 + ... + k5 theta^12)``, then
    tangential and thin-prism terms on the radially scaled point (:class:`_TangentialPrism`:
    note p0 pairs with ``r2 + 2 x^2``, the other way round from OpenCV's p1), ``u = fx a' + cx``.
    Parameter order as COLMAP: fx, fy, cx, cy, k0..k5, p0, p1, s0..s3 (Aria's single focal length
    is fx = fy).

    ``max_angle``: ``pi / 2`` (open; COLMAP computes it through x / z), or the fold of the radial
    part if it comes earlier. Unprojection: the prism / tangential stage is inverted by 2-D
    Newton from the identity, the radial stage like Kannala-Brandt's (table start, Newton), each
    with one final differentiable step; valid where both converged inside the fold.
    """

    model = "fisheye624"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _fold: float
    _table: RadialTable
    _prism_table: RadialTable
    param_names = (
        "fx",
        "fy",
        "cx",
        "cy",
        "k0",
        "k1",
        "k2",
        "k3",
        "k4",
        "k5",
        "p0",
        "p1",
        "s0",
        "s1",
        "s2",
        "s3",
    )
    distortion_names = param_names[4:]
    newton_steps = 2

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        table = _equidistant_table(tuple(p[f"k{i}"] for i in range(6)), math.pi / 2)
        self._set("_fold", table.t_max)
        self._set("_table", table)
        self._set("_prism_table", _identity_table(table.g_max))
        return table.t_max

    @staticmethod
    def _ks(p: Tensor | tuple[float, ...]) -> list:
        return [p[4], p[5], p[6], p[7], p[8], p[9]]

    @staticmethod
    def _prism(p: Tensor | tuple[float, ...]) -> _TangentialPrism:
        return _TangentialPrism(p[10], p[11], (p[12], p[13], p[14], p[15]))

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z, nonzero = _unit_points(points)
        theta2, ratio, theta = angle_ratio(x, y, z)
        scale = ratio * radial_poly(theta2, self._ks(p))
        xd, yd = self._prism(p)(scale * x, scale * y)
        uv = torch.stack([p[0] * xd + p[2], p[1] * yd + p[3]], dim=-1)
        return uv, nonzero & (z > 0) & (theta < self._fold)

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        xr, yr, ok = undistort(
            self._prism(p), self._prism(self._values), mx, my, self._prism_table, self.newton_steps
        )
        rho2 = xr * xr + yr * yr
        small = rho2 < small_threshold(uv.dtype)
        rho = safe_sqrt(rho2)
        ks = self._ks(p)
        theta = solve_odd_poly(rho, ks, self._values[4:10], self._table, self.newton_steps)
        # Near the axis theta = rho (1 - k0 rho^2 + ...), so sin(theta) / rho = 1 - (k0 + 1/6) rho^2.
        series = 1.0 - (ks[0] + 1.0 / 6.0) * rho2
        rays = _ray_from_angle(theta, xr, yr, rho2, small, series)
        with torch.no_grad():
            valid = ok & (rho2 < self._table.g_max**2)
        return rays, valid
