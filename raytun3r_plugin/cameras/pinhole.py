"""Perspective models: :class:`Pinhole` and :class:`OpenCVRadTan` (COLMAP ``OPENCV``)."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

from raytun3r_plugin.cameras._math import (
    EDGE_MARGIN,
    RadialTable,
    RadTan,
    odd_poly_fold,
    undistort,
    unit,
)
from raytun3r_plugin.cameras.base import Camera

__all__ = ["OpenCVRadTan", "Pinhole"]


def _perspective(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(x / z, y / z) and z > 0; points behind the camera get finite dummy values."""
    x, y, z = points.unbind(-1)
    front = z > 0
    zs = torch.where(front, z, torch.ones_like(z))
    return x / zs, y / zs, front


@functools.lru_cache(maxsize=256)
def _radtan_table(k1: float, k2: float) -> tuple[float, RadialTable]:
    """(max angle, inverse table) of the radial part r (1 + k1 r^2 + k2 r^4), r = tan(theta).
    Cached: it depends only on the distortion."""
    r_fold = odd_poly_fold([k1, k2], math.inf)
    fold_angle = math.atan(r_fold)
    diverges = fold_angle >= math.pi / 2 - EDGE_MARGIN
    theta_end = math.pi / 2 - EDGE_MARGIN if diverges else fold_angle
    table = RadialTable.from_angles(
        theta_end, np.tan, lambda t: t * (1.0 + t * t * (k1 + t * t * k2)), diverges=diverges
    )
    return theta_end, table


class Pinhole(Camera):
    """Ideal perspective camera.

    ``u = fx x / z + cx``, ``v = fy y / z + cy``; defined for z > 0, so ``max_angle = pi / 2``
    (open bound). Unprojection: ``ray = normalise((u - cx) / fx, (v - cy) / fy, 1)``, valid for
    every pixel. COLMAP ``PINHOLE`` and ``SIMPLE_PINHOLE`` map here.
    """

    model = "pinhole"
    param_names = ("fx", "fy", "cx", "cy")

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        return math.pi / 2

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        a, b, front = _perspective(points)
        uv = torch.stack([p[0] * a + p[2], p[1] * b + p[3]], dim=-1)
        return uv, front

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        rays = unit(torch.stack([mx, my, torch.ones_like(mx)], dim=-1))
        return rays, torch.ones_like(mx, dtype=torch.bool)


class OpenCVRadTan(Camera):
    """Perspective camera with OpenCV radial-tangential distortion (COLMAP ``OPENCV``).

    On the normalised plane (a, b) = (x / z, y / z), r2 = a^2 + b^2:
    ``a' = a (1 + k1 r2 + k2 r2^2) + 2 p1 a b + p2 (r2 + 2 a^2)``,
    ``b' = b (1 + k1 r2 + k2 r2^2) + p1 (r2 + 2 b^2) + 2 p2 a b``, ``u = fx a' + cx``.

    ``max_angle`` is ``atan(r_fold)``, where ``r_fold`` is the first radius at which the radial
    mapping ``r (1 + k1 r^2 + k2 r^4)`` stops increasing (``pi / 2 - 1e-4`` if it never does);
    the tangential terms are ignored for this bound. Unprojection: start at the tabulated inverse
    of the radial part, 2 fixed 2-D Newton steps plus one differentiable step; valid where the
    inverse converged inside ``r_fold``.
    """

    model = "opencv"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _table: RadialTable
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
    distortion_names = ("k1", "k2", "p1", "p2")
    newton_steps = 2

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        theta_end, table = _radtan_table(p["k1"], p["k2"])
        self._set("_table", table)
        return theta_end

    def _dist(self, p: Tensor | tuple[float, ...]) -> RadTan:
        return RadTan([p[4], p[5]], p[6], p[7])

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        a, b, front = _perspective(points)
        ad, bd = self._dist(p)(a, b)
        uv = torch.stack([p[0] * ad + p[2], p[1] * bd + p[3]], dim=-1)
        valid = front & ((a * a + b * b).detach() < self._table.t_max**2)
        return uv, valid

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        a, b, ok = undistort(
            self._dist(p), self._dist(self._values), mx, my, self._table, self.newton_steps
        )
        rays = unit(torch.stack([a, b, torch.ones_like(a)], dim=-1))
        return rays, ok
