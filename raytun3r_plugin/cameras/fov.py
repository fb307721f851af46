"""COLMAP's ``FOV`` model (Devernay and Faugeras 2001; Project Tango's fisheye cameras)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from raytun3r_plugin.cameras._math import safe_sqrt, small_threshold
from raytun3r_plugin.cameras.base import Camera, param_error
from raytun3r_plugin.cameras.kb import _ray_from_angle, _unit_points

__all__ = ["FOV"]


class FOV(Camera):
    """Field-of-view model: one parameter ``omega`` (radians, in (0, pi)).

    On the normalised plane ``(a, b) = (x / z, y / z)``, ``r = |(a, b)|``, ``c = 2 tan(omega / 2)``:
    ``(a', b') = (a, b) atan(c r) / (omega r)``, ``u = fx a' + cx``, ``v = fy b' + cy``
    (the centre is analytic: the factor tends to ``c / omega``). In angles the distorted radius
    is ``atan2(c sin theta, cos theta) / omega``: increasing, ``pi / (2 omega)`` at 90 degrees,
    where the model ends (COLMAP divides by z), so ``max_angle = pi / 2`` (open bound).
    Unprojection is closed-form, ``theta = atan2(sin(omega r_d), c cos(omega r_d))``, valid for
    ``omega r_d < pi / 2``. Parameter order as COLMAP: fx, fy, cx, cy, omega.
    """

    model = "fov"
    param_names = ("fx", "fy", "cx", "cy", "omega")

    def _check_domain(self, p: dict[str, float]) -> None:
        # omega = 0 is the pinhole limit, where COLMAP itself warns the optimisation stalls;
        # omega >= pi has no lens (tan(omega / 2) is infinite or negative).
        if not 0.0 < p["omega"] < math.pi:
            raise param_error(type(self).__name__, "omega", f"must be in (0, pi) radians, got {p['omega']!r}")

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        return math.pi / 2

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z, nonzero = _unit_points(points)
        omega = p[4]
        c = 2.0 * torch.tan(omega / 2.0)
        rho2 = x * x + y * y
        small = rho2 < small_threshold(points.dtype)
        front = z > 0
        zs = torch.where(front, z, torch.ones_like(z))
        rho = torch.sqrt(torch.where(small, torch.ones_like(rho2), rho2))
        # atan2(c rho, z) / rho, with its series c / z (1 - c^2 rho^2 / (3 z^2)) at the axis.
        ratio = torch.where(small, c / zs * (1.0 - c * c * rho2 / (3.0 * zs * zs)), torch.atan2(c * rho, z) / rho)
        scale = ratio / omega
        uv = torch.stack([p[0] * scale * x + p[2], p[1] * scale * y + p[3]], dim=-1)
        return uv, nonzero & front

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        omega = p[4]
        c = 2.0 * torch.tan(omega / 2.0)
        rd2 = mx * mx + my * my
        small = rd2 < small_threshold(uv.dtype)
        t = omega * safe_sqrt(rd2)
        # atan2 keeps theta finite past t = pi / 2, where tan(t) would overflow; those pixels
        # are marked invalid below.
        theta = torch.atan2(torch.sin(t), c * torch.cos(t))
        # sin(theta) / r_d near the axis: (omega / c) (1 + t^2 (1/3 - 1 / (2 c^2))).
        series = omega / c * (1.0 + omega * omega * rd2 * (1.0 / 3.0 - 1.0 / (2.0 * c * c)))
        rays = _ray_from_angle(theta, mx, my, rd2, small, series)
        with torch.no_grad():
            valid = t < math.pi / 2
        return rays, valid
