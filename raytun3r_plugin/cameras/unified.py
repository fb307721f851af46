"""Unified-projection family: :class:`UCM`, :class:`EUCM`, :class:`DoubleSphere`, :class:`MEI`.

These models project through a (possibly ellipsoidal / doubled) sphere and can represent rays
beyond 90 degrees. Closed-form inverses for UCM / EUCM / DS (formulas as in basalt-headers,
restated in docs/cameras.md); MEI inverts its radial-tangential distortion with fixed Newton
steps.
"""

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
    safe_sqrt,
    undistort,
    unit,
)
from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.checks import check_range, param_error

#: Upper bound of EUCM's beta (real lenses: about 0.5 to 2).
EUCM_BETA_MAX = 100.0

#: Upper bound of MEI's xi (real lenses: about 0.5 to 3; KITTI-360 image_02 has 2.2).
MEI_XI_MAX = 100.0

__all__ = ["EUCM", "MEI", "UCM", "DoubleSphere"]


def _in_unit_interval(model: str, name: str, v: float) -> None:
    if not 0.0 <= v <= 1.0:
        raise param_error(model, name, f"must be in [0, 1], got {v!r}")


def _w_alpha(alpha: float) -> float:
    """The projection-domain constant of the unified models: z > -w * d.

    For alpha <= 0.5 it is where the denominator vanishes (xi = alpha / (1 - alpha) <= 1);
    for alpha > 0.5 the fold of the mapping comes first, at (1 - alpha) / alpha.
    """
    if alpha <= 0.5:
        return alpha / (1.0 - alpha)
    return (1.0 - alpha) / alpha


def _normalised(uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    mx = (uv[..., 0] - p[2]) / p[0]
    my = (uv[..., 1] - p[3]) / p[1]
    return mx, my, mx * mx + my * my


def _inside(mx: Tensor, my: Tensor, r2: Tensor, valid: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Replace pixels outside the unprojection domain by the principal point (0, 0, 0), so
    the closed forms stay finite there (their rays are marked invalid anyway): without it
    alpha = 1 gives sqrt(negative) / 0 beyond the image circle."""
    zero = torch.zeros_like(r2)
    return torch.where(valid, mx, zero), torch.where(valid, my, zero), torch.where(valid, r2, zero)


def _pixels(p: Tensor, x: Tensor, y: Tensor, den: Tensor, valid: Tensor) -> Tensor:
    # Invalid points get a dummy denominator so that uv (and gradients) stay finite.
    den = torch.where(valid, den, torch.ones_like(den))
    return torch.stack([p[0] * x / den + p[2], p[1] * y / den + p[3]], dim=-1)


class UCM(Camera):
    """Unified camera model, alpha form (basalt ``ucm``): params fx, fy, cx, cy, alpha.

    Project: ``d = |P|``, ``u = fx x / (alpha d + (1 - alpha) z) + cx`` (same for v).
    Valid for ``z > -w d``, ``w = alpha / (1 - alpha)`` if alpha <= 0.5 else
    ``(1 - alpha) / alpha``, so ``max_angle = acos(-w)``.
    Unproject: ``m = ((u - cx) / fx, (v - cy) / fy)``, ``r2 = |m|^2`` (alpha > 0.5 needs
    ``r2 < 1 / (2 alpha - 1)``); the ray's z is
    ``c = (sqrt(1 + (1 - 2 alpha) r2) - alpha (1 - alpha) r2) / (1 + (1 - alpha)^2 r2)`` and its
    xy part ``m (alpha + (1 - alpha) c)``.
    The xi form (Kalibr ``omni`` without distortion) converts as ``alpha = xi / (1 + xi)``,
    ``f_alpha = f_xi / (1 + xi)``.
    """

    model = "ucm"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _w: float
    _r2_max: float
    param_names = ("fx", "fy", "cx", "cy", "alpha")

    def _check_domain(self, p: dict[str, float]) -> None:
        _in_unit_interval(type(self).__name__, "alpha", p["alpha"])

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        a = p["alpha"]
        w = _w_alpha(a)
        self._set("_w", w)
        self._set("_r2_max", 1.0 / (2.0 * a - 1.0) if a > 0.5 else math.inf)
        return math.acos(-w)

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        d2 = x * x + y * y + z * z
        d = safe_sqrt(d2)
        a = p[4]
        den = a * d + (1.0 - a) * z
        valid = (d2 > 0) & (z.detach() > -self._w * d.detach())
        return _pixels(p, x, y, den, valid), valid

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx, my, r2 = _normalised(uv, p)
        valid = r2.detach() < self._r2_max
        mx, my, r2 = _inside(mx, my, r2, valid)
        a = p[4]
        b = 1.0 - a
        c = (safe_sqrt(1.0 + (1.0 - 2.0 * a) * r2) - a * b * r2) / (1.0 + b * b * r2)
        k = a + b * c
        rays = unit(torch.stack([mx * k, my * k, c], dim=-1))
        return rays, valid


class EUCM(Camera):
    """Extended unified camera model (Khomutenko et al. 2016): fx, fy, cx, cy, alpha, beta.

    Project: ``d = sqrt(beta (x^2 + y^2) + z^2)``, ``u = fx x / (alpha d + (1 - alpha) z) + cx``;
    valid for ``z > -w d`` (w as in :class:`UCM`), so
    ``max_angle = acos(-sqrt(w^2 beta / (1 - w^2 + w^2 beta)))``.
    Unproject: ``r2 = |m|^2`` (alpha > 0.5 needs ``r2 < 1 / ((2 alpha - 1) beta)``),
    ``m_z = (1 - beta alpha^2 r2) / (alpha sqrt(1 - (2 alpha - 1) beta r2) + 1 - alpha)``,
    ray = normalise(m_x, m_y, m_z). Domain: alpha in [0, 1], beta in (0, 100].
    """

    model = "eucm"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _w: float
    _r2_max: float
    param_names = ("fx", "fy", "cx", "cy", "alpha", "beta")

    def _check_domain(self, p: dict[str, float]) -> None:
        _in_unit_interval(type(self).__name__, "alpha", p["alpha"])
        check_range(type(self).__name__, "beta", p["beta"], 0.0, EUCM_BETA_MAX, lo_open=True)

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        a, beta = p["alpha"], p["beta"]
        w = _w_alpha(a)
        self._set("_w", w)
        self._set("_r2_max", 1.0 / ((2.0 * a - 1.0) * beta) if a > 0.5 else math.inf)
        # z = -w sqrt(beta r^2 + z^2) on the unit sphere (r^2 = 1 - z^2), solved for z.
        return math.acos(-math.sqrt(w * w * beta / (1.0 - w * w + w * w * beta)))

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        a, beta = p[4], p[5]
        d2 = beta * (x * x + y * y) + z * z
        d = safe_sqrt(d2)
        den = a * d + (1.0 - a) * z
        valid = (d2.detach() > 0) & (z.detach() > -self._w * d.detach())
        return _pixels(p, x, y, den, valid), valid

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx, my, r2 = _normalised(uv, p)
        valid = r2.detach() < self._r2_max
        mx, my, r2 = _inside(mx, my, r2, valid)
        a, beta = p[4], p[5]
        mz = (1.0 - beta * a * a * r2) / (
            a * safe_sqrt(1.0 - (2.0 * a - 1.0) * beta * r2) + (1.0 - a)
        )
        rays = unit(torch.stack([mx, my, mz], dim=-1))
        return rays, valid


def _ds_radius2(xi: float, alpha: float, theta: float) -> float:
    """Squared normalised image radius of the unit ray at ``theta`` (inf where undefined)."""
    x, z = math.sin(theta), math.cos(theta)
    k = xi + z
    den = alpha * math.sqrt(x * x + k * k) + (1.0 - alpha) * k
    if not den > 0.0:
        return math.inf
    return (x / den) ** 2


class DoubleSphere(Camera):
    """Double sphere model (Usenko et al. 2018, basalt ``ds``): fx, fy, cx, cy, xi, alpha.

    Project: ``d1 = |P|``, ``k = xi d1 + z``, ``d2 = sqrt(x^2 + y^2 + k^2)``,
    ``u = fx x / (alpha d2 + (1 - alpha) k) + cx``. Valid for ``k > -w1 d2`` (w1 = the UCM w
    of alpha, applied to the second sphere): on the unit sphere that is
    ``z > -xi (1 - w1^2) - w1 sqrt(1 - xi^2 (1 - w1^2))``, which gives ``max_angle``. (The
    paper's ``z > -w2 d1``, ``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)``, is a slightly
    smaller, conservative bound that does not match the unprojection domain.)
    Unproject: ``r2 = |m|^2`` (alpha > 0.5 needs ``r2 < 1 / (2 alpha - 1)``),
    ``m_z = (1 - alpha^2 r2) / (alpha sqrt(1 - (2 alpha - 1) r2) + 1 - alpha)``,
    ``P = (m_z xi + sqrt(m_z^2 + (1 - xi^2) r2)) / (m_z^2 + r2) * (m_x, m_y, m_z) - (0, 0, xi)``.
    Domain: xi in (-1, 1] (xi = -1 collapses the image onto the axis and is refused), alpha
    in [0, 1].
    """

    model = "ds"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _w1: float
    _r2_max: float
    param_names = ("fx", "fy", "cx", "cy", "xi", "alpha")

    def _check_domain(self, p: dict[str, float]) -> None:
        # xi = -1 is refused on purpose: there k = (|m_z| - m_z) / (...) is 0 in front of the
        # camera, every pixel unprojects to the optical axis and the model cannot be inverted.
        # Any xi > -1 works (the round-trip check at construction decides how close).
        check_range(type(self).__name__, "xi", p["xi"], -1.0, 1.0, lo_open=True)
        _in_unit_interval(type(self).__name__, "alpha", p["alpha"])

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        xi, a = p["xi"], p["alpha"]
        w1 = _w_alpha(a)
        self._set("_w1", w1)
        self._set("_r2_max", 1.0 / (2.0 * a - 1.0) if a > 0.5 else math.inf)
        # Boundary k = -w1 d2 on the unit sphere: (xi + z)^2 (1 - w1^2) = w1^2 (1 - z^2) with
        # xi + z < 0, i.e. the smaller root of z^2 + 2 xi (1 - w1^2) z + xi^2 (1 - w1^2) - w1^2.
        q = 1.0 - w1 * w1
        z = -xi * q - w1 * math.sqrt(max(1.0 - xi * xi * q, 0.0))
        angle = math.acos(max(-1.0, min(1.0, -1.0 if z < -1.0 else z)))
        # Where the domain ends before the fold (large xi: the back pole at xi = 1), the image
        # of the projection is the disc of the boundary ray's radius, smaller than the fold's
        # 1 / (2 alpha - 1): pixels between the two have no ray, and the closed-form inverse
        # would return one that projects elsewhere. Found by the round-trip check.
        r2_b = _ds_radius2(xi, a, angle - 1e-7)
        if r2_b < self._r2_max * (1.0 - 1e-6):
            self._set("_r2_max", r2_b)
        return angle

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        xi, a = p[4], p[5]
        n2 = x * x + y * y + z * z
        d1 = safe_sqrt(n2)
        k = xi * d1 + z
        d2 = safe_sqrt(x * x + y * y + k * k)
        den = a * d2 + (1.0 - a) * k
        # The UCM condition applied to the second sphere. This is the exact domain (the fold
        # for alpha > 0.5, den = 0 otherwise); the paper's closed-form z > -w2 d1 bound is
        # slightly smaller (125.2 vs 126.1 degrees for TUM-VI) and would disagree with the
        # unprojection's r2 < 1 / (2 alpha - 1).
        valid = (n2.detach() > 0) & (k.detach() > -self._w1 * d2.detach())
        return _pixels(p, x, y, den, valid), valid

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx, my, r2 = _normalised(uv, p)
        valid = r2.detach() < self._r2_max
        mx, my, r2 = _inside(mx, my, r2, valid)
        xi, a = p[4], p[5]
        mz = (1.0 - a * a * r2) / (a * safe_sqrt(1.0 - (2.0 * a - 1.0) * r2) + 1.0 - a)
        mz2 = mz * mz
        k = (mz * xi + safe_sqrt(mz2 + (1.0 - xi * xi) * r2)) / (mz2 + r2)
        rays = unit(torch.stack([k * mx, k * my, k * mz - xi], dim=-1))
        return rays, valid


@functools.lru_cache(maxsize=256)
def _mei_table(xi: float, k1: float, k2: float) -> tuple[float, RadialTable]:
    """(max angle, inverse table) of the MEI radial map theta -> distorted plane radius.
    Cached: it depends only on xi and the radial distortion."""
    # End of the sphere-to-plane map: the fold s_z = -1/xi for xi > 1 (finite radius); the
    # pole of 1 / (s_z + xi) for xi <= 1 (stop EDGE_MARGIN before it, as for the pinhole).
    if xi > 1.0:
        theta_end = math.acos(-1.0 / xi)
    else:
        theta_end = math.acos(-xi) - EDGE_MARGIN
    diverges = xi <= 1.0
    rho_fold = odd_poly_fold([k1, k2], math.inf)
    if math.isfinite(rho_fold):
        r2 = rho_fold * rho_fold
        zs = (-xi * r2 + math.sqrt(max(1.0 + r2 * (1.0 - xi * xi), 0.0))) / (r2 + 1.0)
        fold_angle = math.acos(max(-1.0, min(1.0, zs)))
        if fold_angle < theta_end:
            theta_end, diverges = fold_angle, False
    table = RadialTable.from_angles(
        theta_end,
        lambda th: np.sin(th) / (np.cos(th) + xi),
        lambda t: t * (1.0 + t * t * (k1 + t * t * k2)),
        diverges=diverges,
    )
    return theta_end, table


class MEI(Camera):
    """Unified model with radial-tangential distortion (Mei & Rives 2007; KITTI-360 fisheye,
    Kalibr ``omni`` + ``radtan``, camodocal ``MEI``): fx, fy, cx, cy, xi, k1, k2, p1, p2.

    KITTI-360 names: ``gamma1 = fx``, ``gamma2 = fy``, ``u0 = cx``, ``v0 = cy``.
    Project: ``s = P / |P|``, ``(x_u, y_u) = (s_x, s_y) / (s_z + xi)``, radial-tangential
    distortion with ``rho2 = x_u^2 + y_u^2`` (as OpenCV), ``u = fx x_d + cx``.
    The sphere-to-plane map folds where ``s_z = -1 / xi`` (xi > 1) or vanishes at
    ``s_z = -xi`` (xi <= 1): ``max_angle = acos(-min(xi, 1 / xi))`` (minus 1e-4 rad in the
    second case, where the plane radius diverges), tighter if the radial
    distortion folds first (tangential terms ignored for the bound). KITTI-360 image_02
    (xi = 2.2134) reaches 116.9 degrees.
    Unproject: start at the tabulated inverse of the radial part, 2 fixed 2-D Newton steps (plus
    one differentiable) undo the distortion, then
    ``Z_s = (-xi r2 + sqrt(1 + (1 - xi^2) r2)) / (r2 + 1)``,
    ``ray = (x (Z_s + xi), y (Z_s + xi), Z_s)``. Domain: xi in [0, 100].
    """

    model = "mei"
    # Derived in _natural_max_angle (via _set); declared for the type checker.
    _w: float
    _table: RadialTable
    param_names = ("fx", "fy", "cx", "cy", "xi", "k1", "k2", "p1", "p2")
    distortion_names = ("k1", "k2", "p1", "p2")
    newton_steps = 2

    def _check_domain(self, p: dict[str, float]) -> None:
        check_range(type(self).__name__, "xi", p["xi"], 0.0, MEI_XI_MAX)

    def _natural_max_angle(self, p: dict[str, float]) -> float:
        xi = p["xi"]
        self._set("_w", xi if xi <= 1.0 else 1.0 / xi)
        theta_end, table = _mei_table(xi, p["k1"], p["k2"])
        self._set("_table", table)
        return theta_end

    def _dist(self, p: Tensor | tuple[float, ...]) -> RadTan:
        return RadTan([p[5], p[6]], p[7], p[8])

    def _project(self, points: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        n2 = (points * points).sum(dim=-1)
        s = points / safe_sqrt(n2).unsqueeze(-1)
        sx, sy, sz = s.unbind(-1)
        valid = (n2.detach() > 0) & (sz.detach() > -self._w)
        den = torch.where(valid, sz + p[4], torch.ones_like(sz))
        xu = sx / den
        yu = sy / den
        valid = valid & ((xu * xu + yu * yu).detach() < self._table.t_max**2)
        xd, yd = self._dist(p)(xu, yu)
        return torch.stack([p[0] * xd + p[2], p[1] * yd + p[3]], dim=-1), valid

    def _unproject(self, uv: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
        mx, my, _ = _normalised(uv, p)
        xi = p[4]
        x, y, ok = undistort(
            self._dist(p), self._dist(self._values), mx, my, self._table, self.newton_steps
        )
        r2 = x * x + y * y
        zs = (-xi * r2 + safe_sqrt(1.0 + (1.0 - xi * xi) * r2)) / (r2 + 1.0)
        rays = unit(torch.stack([x * (zs + xi), y * (zs + xi), zs], dim=-1))
        return rays, ok
