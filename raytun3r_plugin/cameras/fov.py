"""COLMAP's ``FOV`` model (Devernay and Faugeras 2001; Project Tango's fisheye cameras)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from raytun3r_plugin.cameras._math import safe_sqrt, small_threshold
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.checks import param_error
from raytun3r_plugin.cameras.kb import _ray_from_angle, _unit_points

__all__ = ["FOV"]


class FOV(Camera):
    """Field-of-view model: one parameter ``omega`` (radians, in (0, pi)).

    On the normalised plane ``(a, b) = (x / z, y / z)``, ``r = |(a, b)|``, ``c = 2 tan(omega / 2)``:
    ``(a', b') = (a, b) atan(c r) / (omega r)``, ``u = fx a' + cx``, ``v = fy b' + cy``
    (the centre is analytic: the factor tends to ``c / omega``). Written with the angle from the
    axis, the distorted radius is ``atan2(c sin theta, cos theta) / omega`` (basalt's form): the
    same numbers in front of the camera (COLMAP's domain, z > 0), and increasing on to ``pi /
    omega`` at 180 degrees, so lenses wider than 180 degrees work: ``max_angle = pi`` (open).
    Unprojection is closed-form, ``theta = atan2(sin(omega r_d), c cos(omega r_d))``, valid for
    ``omega r_d < pi``. Parameter order as COLMAP: fx, fy, cx, cy, omega.
    """

    model = "fov"
    param_names = ("fx", "fy", "cx", "cy", "omega")

    def _check_domain(self, p: dict[str, float]) -> None:
        # omega = 0 is the pinhole limit, where COLMAP itself warns the optimisation stalls;
        # omega >= pi has no lens (tan(omega / 2) is infinite or negative).
        if not 0.0 < p["omega"] < math.pi:
            raise param_error(
                type(self).__name__, "omega", f"must be in (0, pi) radians, got {p['omega']!r}"
            )

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        return math.pi

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z, nonzero = _unit_points(points)
        omega = p[4]
        c = 2.0 * torch.tan(omega / 2.0)
        rho2 = x * x + y * y
        # Near the axis (unit points: z = 1 there) atan2(c rho, z) / rho = c (1 - c^2 rho^2 / 3);
        # near the back pole (and for a zero point) any finite value: those are invalid below.
        small = rho2 < small_threshold(points.dtype)
        rho = torch.sqrt(torch.where(small, torch.ones_like(rho2), rho2))
        series = torch.where(z > 0, c * (1.0 - c * c * rho2 / 3.0), torch.zeros_like(rho2))
        ratio = torch.where(small, series, torch.atan2(c * rho, z) / rho)
        scale = ratio / omega
        uv = torch.stack([p[0] * scale * x + p[2], p[1] * scale * y + p[3]], dim=-1)
        # Strict bound: the back pole (a point on the axis behind the camera) is a whole circle
        # of pixels, as at a Kannala-Brandt fold; off the axis atan2(rho, z) < pi.
        return uv, nonzero & ~(small & (z <= 0))

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx = (uv[..., 0] - p[2]) / p[0]
        my = (uv[..., 1] - p[3]) / p[1]
        omega = p[4]
        c = 2.0 * torch.tan(omega / 2.0)
        rd2 = mx * mx + my * my
        small = rd2 < small_threshold(uv.dtype)
        t = omega * safe_sqrt(rd2)
        # atan2, not atan(tan(t) / c): finite and increasing for t up to pi (rays behind the
        # camera), where tan(t) would overflow at pi / 2.
        theta = torch.atan2(torch.sin(t), c * torch.cos(t))
        # sin(theta) / r_d near the axis: (omega / c) (1 + t^2 (1/3 - 1 / (2 c^2))).
        series = omega / c * (1.0 + omega * omega * rd2 * (1.0 / 3.0 - 1.0 / (2.0 * c * c)))
        rays = _ray_from_angle(theta, mx, my, rd2, small, series)
        with torch.no_grad():
            valid = t < math.pi
        return rays, valid
