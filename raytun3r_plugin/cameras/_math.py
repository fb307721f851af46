"""Numerical helpers shared by the camera models (private).

Everything here is elementwise torch code with a fixed amount of work per element: no
data-dependent Python loops and no ``.item()``, so it batches, runs on any device and traces.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from raytun3r_plugin.errors import CameraError


def safe_sqrt(x: Tensor) -> Tensor:
    """sqrt with a finite gradient everywhere.

    ``torch.where`` does not protect a masked-out ``sqrt(0)``: its backward computes
    ``0 * inf = nan``. Clamping at the smallest normal number keeps value and gradient finite
    (the clamped branch gets a zero gradient), and only changes results at exact zeros.
    """
    return torch.sqrt(torch.clamp(x, min=torch.finfo(x.dtype).tiny))


def small_threshold(dtype: torch.dtype) -> float:
    """Squared radius below which series expansions replace ``f(r) / r`` (``r < sqrt(eps)``).

    The neglected series terms are O(r^4) relative, i.e. below eps^2.
    """
    return torch.finfo(dtype).eps


def unit(v: Tensor) -> Tensor:
    """Normalise (..., 3) vectors to unit length (zero vectors stay finite)."""
    return v / safe_sqrt((v * v).sum(dim=-1, keepdim=True))


def angle_ratio(x: Tensor, y: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Angle from the optical axis of unit vectors (x, y, z), in a form safe at the axis.

    Returns:
        theta2: theta^2 (theta = atan2(r, z), r = sqrt(x^2 + y^2)), exact near the front axis.
        ratio: theta / r (-> 1 + r^2 / 6 at the front axis), so ``ratio * (x, y)`` is
            ``theta * (x, y) / r`` without dividing by zero.
        theta: theta without gradient (for validity tests); pi near the back pole.
    """
    r2 = x * x + y * y
    small = r2 < small_threshold(x.dtype)
    front = z > 0
    r = torch.sqrt(torch.where(small, torch.ones_like(r2), r2))
    th = torch.atan2(r, z)
    ratio = torch.where(small, torch.where(front, 1.0 + r2 / 6.0, torch.zeros_like(r2)), th / r)
    theta2 = torch.where(small, r2, th * th)
    with torch.no_grad():
        theta = torch.where(
            small, torch.where(front, torch.zeros_like(th), torch.full_like(th, math.pi)), th
        )
    return theta2, ratio, theta


def first_positive_root(coeffs: Sequence[float], upper: float) -> float:
    """Smallest s in (0, upper] with ``c0 + c1 s + c2 s^2 + ... <= 0``, or ``upper`` if none.

    Used for the fold of radial mappings: written in s = t^2, the derivative of
    ``t (1 + k1 t^2 + k2 t^4 + ...)`` is the polynomial ``1 + 3 k1 s + 5 k2 s^2 + ...``, whose
    first positive root is where the mapping stops being monotone. ``c0 > 0`` is assumed.
    A dense scan (uniform up to a finite ``upper``, geometric up to 1e16 otherwise) finds the
    first sign change, bisection refines it; unlike companion-matrix root finding this copes
    with any coefficients (e.g. subnormal ones). Runs once per camera, in float64 numpy.
    """
    c = np.asarray(coeffs, dtype=np.float64)

    def poly(x: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore", invalid="ignore"):
            return np.polynomial.polynomial.polyval(x, c)

    if math.isfinite(upper):
        grid = np.linspace(0.0, upper, 20001)[1:]
    else:
        grid = np.geomspace(1e-8, 1e16, 20001)
    bad = np.nonzero(~(poly(grid) > 0))[0]
    if bad.size == 0:
        return upper
    i = int(bad[0])
    lo = float(grid[i - 1]) if i > 0 else 0.0
    hi = float(grid[i])
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if poly(np.array(mid)) > 0:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 4e-16 * hi:
            break
    return lo


def odd_poly_fold(ks: Sequence[float], t_max: float) -> float:
    """First t in (0, t_max] where ``t (1 + k1 t^2 + k2 t^4 + ...)`` stops increasing, or t_max."""
    coeffs = [1.0] + [(2 * i + 3) * k for i, k in enumerate(ks)]
    return math.sqrt(first_positive_root(coeffs, t_max * t_max))


Coef = Tensor | float


def radial_poly(t2: Tensor, ks: Sequence[Coef]) -> Tensor:
    """1 + k1 t2 + k2 t2^2 + ... (Horner; coefficients are 0-d tensors or floats)."""
    acc = ks[-1] * t2
    for k in reversed(ks[:-1]):
        acc = (acc + k) * t2
    return acc + 1.0


def radial_poly_d(t2: Tensor, ks: Sequence[Coef]) -> Tensor:
    """d/dt2 of :func:`radial_poly`: k1 + 2 k2 t2 + 3 k3 t2^2 + ..."""
    n = len(ks)
    if n == 1:
        return torch.zeros_like(t2) + ks[0]
    acc = (n * ks[-1]) * t2
    for i in range(n - 2, 0, -1):
        acc = (acc + (i + 1) * ks[i]) * t2
    return acc + ks[0]


class Distortion(Protocol):
    """What :func:`undistort` needs of a distortion of normalised coordinates: the forward map
    and its Jacobian. :class:`RadTan` and Fisheye624's tangential/thin-prism stage provide it."""

    def __call__(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]: ...

    def with_jacobian(
        self, x: Tensor, y: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]: ...

    def with_jacobian_fast(
        self, x: Tensor, y: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]: ...


class RadTan:
    """Radial + tangential (+ optional thin-prism) distortion of normalised coordinates.

    ``xd = x R + 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2``,
    ``yd = y R + p1 (r2 + 2 y^2) + 2 p2 x y + s2 r2``, ``R = 1 + k1 r2 + k2 r2^2 + ...``
    (OpenCV / COLMAP OPENCV / MEI / COLMAP THIN_PRISM_FISHEYE share this form).
    Coefficients are 0-d tensors (differentiable) or Python floats (cheaper, for the
    iterations that run without autograd).
    """

    def __init__(
        self,
        ks: Sequence[Coef],
        p1: Coef,
        p2: Coef,
        s1: Coef | None = None,
        s2: Coef | None = None,
    ) -> None:
        self.ks = list(ks)
        self.p1, self.p2, self.s1, self.s2 = p1, p2, s1, s2

    def __call__(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        r2 = x * x + y * y
        rad = radial_poly(r2, self.ks)
        xy2 = 2.0 * x * y
        xd = x * rad + self.p1 * xy2 + self.p2 * (r2 + 2.0 * x * x)
        yd = y * rad + self.p1 * (r2 + 2.0 * y * y) + self.p2 * xy2
        s1, s2 = self.s1, self.s2
        if s1 is not None and s2 is not None:  # the thin-prism pair is given together or not at all
            xd = xd + s1 * r2
            yd = yd + s2 * r2
        return xd, yd

    def with_jacobian(
        self, x: Tensor, y: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Distorted (xd, yd) and the Jacobian entries d(xd, yd)/d(x, y) = [[a, b], [c, d]]."""
        p1, p2 = self.p1, self.p2
        xx = x * x
        yy = y * y
        r2 = xx + yy
        rad = radial_poly(r2, self.ks)
        drad2 = 2.0 * radial_poly_d(r2, self.ks)
        xy = x * y
        xd = x * rad + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
        yd = y * rad + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
        p1x2 = 2.0 * p1 * x
        p2y2 = 2.0 * p2 * y
        b = xy * drad2 + p1x2 + p2y2
        a = rad + xx * drad2 + 3.0 * p2 * (2.0 * x) + p1 * (2.0 * y)
        d = rad + yy * drad2 + 3.0 * p1 * (2.0 * y) + p2 * (2.0 * x)
        c = b
        s1, s2 = self.s1, self.s2
        if s1 is not None and s2 is not None:
            xd = xd + s1 * r2
            yd = yd + s2 * r2
            a = a + 2.0 * s1 * x
            b = b + 2.0 * s1 * y
            c = c + 2.0 * s2 * x
            d = d + 2.0 * s2 * y
        return xd, yd, a, b, c, d

    def with_jacobian_fast(
        self, x: Tensor, y: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """:meth:`with_jacobian` for float coefficients and no autograd: the same numbers
        with about half the full-size tensor operations (fused ``addcmul``, in place). The
        Newton iterations of :func:`undistort` are memory bound, so this is what they cost."""
        ks = [float(k) for k in self.ks]
        p1, p2 = float(self.p1), float(self.p2)
        xx = x * x
        yy = y * y
        xy = x * y
        r2 = xx + yy
        rad = r2 * ks[-1]  # Horner: rad = 1 + k1 r2 + k2 r2^2 + ...
        for k in reversed(ks[:-1]):
            rad.add_(k).mul_(r2)
        rad.add_(1.0)
        # 2 dR/dr2 = sum_i 2 (i + 1) k_i r2^i, Horner again.
        dc = [2.0 * (i + 1) * k for i, k in enumerate(ks)]
        if len(dc) == 1:
            drad2 = torch.full_like(r2, dc[0])
        else:
            drad2 = (r2 * dc[-1]).add_(dc[-2])
            for ci in reversed(dc[:-2]):
                drad2.mul_(r2).add_(ci)
        xd = (x * rad).addcmul_(xy, xy.new_tensor(2.0 * p1)).add_(r2, alpha=p2)
        xd.add_(xx, alpha=2.0 * p2)
        yd = (y * rad).addcmul_(xy, xy.new_tensor(2.0 * p2)).add_(r2, alpha=p1)
        yd.add_(yy, alpha=2.0 * p1)
        b = (xy * drad2).add_(x, alpha=2.0 * p1).add_(y, alpha=2.0 * p2)
        a = torch.addcmul(rad, xx, drad2).add_(x, alpha=6.0 * p2).add_(y, alpha=2.0 * p1)
        d = torch.addcmul(rad, yy, drad2).add_(y, alpha=6.0 * p1).add_(x, alpha=2.0 * p2)
        c = b
        if self.s1 is not None and self.s2 is not None:
            s1, s2 = float(self.s1), float(self.s2)
            xd.add_(r2, alpha=s1)
            yd.add_(r2, alpha=s2)
            c = b.clone()
            a.add_(x, alpha=2.0 * s1)
            b.add_(y, alpha=2.0 * s1)
            c.add_(x, alpha=2.0 * s2)
            d.add_(y, alpha=2.0 * s2)
        return xd, yd, a, b, c, d


# Perspective-type mappings diverge at their domain edge (tan(theta) -> inf); their table, and
# with it ``max_angle``, stops this far (radians) before it.
EDGE_MARGIN = 1e-4


class RadialTable:
    """Tabulated inverse of a monotone radial distortion, used only for Newton starting points.

    The distorted radius ``g`` is sampled uniformly in a variable ``w(g)`` and the exact
    undistorted radius ``t`` of every sample is found once, at construction, by bisection on
    the ray angle. A lookup is O(1): ``w``, a floor and one gather give the cell
    ``[t_i, t_i+1]`` that brackets the root and a linear guess inside it. From there 2-3 Newton
    steps reach full precision whatever the size of the distortion (starting at ``t = g`` can
    need dozens of steps, e.g. for a strong ``k2 r^5`` term far from the centre).

    ``w = log(1 + g)`` when the map diverges at the end of its domain (perspective models,
    where g grows like a power of tan(theta): equal steps in log g are equal relative steps in
    t); otherwise ``w = sqrt(G) - sqrt(G - g)`` with ``G = g(end)``, which
    is linear near the centre and matches the square-root shape of ``t(g)`` at a fold, so the
    cells next to the fold stay narrow in t and Newton keeps converging there.
    """

    def __init__(self, t: np.ndarray, g_end: float, diverges: bool) -> None:
        t = np.ascontiguousarray(t, dtype=np.float64)
        if not (np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0) and math.isfinite(g_end)):
            raise CameraError("radial table must be finite and increasing")
        self.t_max = float(t[-1])
        self.g_max = float(g_end)
        self.n = t.shape[0] - 1
        self.diverges = diverges
        self.w_max = math.log1p(g_end) if diverges else math.sqrt(g_end)
        # Pairs (t_i, t_i+1) so one gather fetches both ends of a cell.
        self._pairs64 = torch.from_numpy(np.stack([t[:-1], t[1:]], axis=-1))
        self._conv: dict[tuple[str, torch.dtype], Tensor] = {}

    @classmethod
    def from_angles(
        cls,
        theta_end: float,
        t_of_theta: Callable[[np.ndarray], np.ndarray],
        g_of_t: Callable[[np.ndarray], np.ndarray],
        diverges: bool = False,
        n: int = 2048,
    ) -> RadialTable:
        """Table of ``g(t(theta))``, increasing for theta in [0, theta_end]."""

        def g_of_theta(th: np.ndarray) -> np.ndarray:
            return g_of_t(t_of_theta(th))

        g_end = float(g_of_theta(np.array([theta_end]))[0])
        w = np.linspace(0.0, 1.0, n + 1)
        if diverges:
            targets = np.expm1(w * math.log1p(g_end))
        else:
            targets = g_end - (math.sqrt(g_end) * (1.0 - w)) ** 2
        targets[-1] = g_end
        lo = np.zeros(n + 1)
        hi = np.full(n + 1, theta_end)
        for _ in range(64):  # bisection: the map is monotone, 64 halvings reach float64 ulp
            mid = 0.5 * (lo + hi)
            below = g_of_theta(mid) < targets
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        theta = 0.5 * (lo + hi)
        theta[0], theta[-1] = 0.0, theta_end
        return cls(t_of_theta(theta), g_end, diverges)

    def _table(self, like: Tensor) -> Tensor:
        key = (str(like.device), like.dtype)
        hit = self._conv.get(key)
        if hit is None:
            hit = self._pairs64.to(like.device, like.dtype)
            self._conv[key] = hit
        return hit

    def lookup(self, target: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(guess, lo, hi) for distorted radii ``target`` >= 0 (no grad); [lo, hi] is the
        table cell holding the root. Targets beyond the table get the last cell."""
        pairs = self._table(target)
        with torch.no_grad():
            g = target.detach()
            if self.diverges:
                w = torch.log1p(g)
            else:
                w = self.w_max - torch.sqrt((self.g_max - g).clamp_(min=0.0))
            pos = w.mul_(self.n / self.w_max)
            i = pos.long().clamp_(0, self.n - 1)
            frac = (pos - i).clamp_(0.0, 1.0)
            lo, hi = pairs[i].unbind(-1)
            return torch.lerp(lo, hi, frac), lo, hi


def undistort(
    dist: Distortion, dist_f: Distortion, mx: Tensor, my: Tensor, table: RadialTable, steps: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Invert ``dist`` at (mx, my) with a fixed number of 2-D Newton steps.

    ``dist_f`` is the same distortion with float coefficients, used in the iterations.

    The start point is the inverse of the radial part alone (``table``), so that only the
    small tangential / thin-prism terms are left to Newton.

    The iterations run without autograd; one last Newton step is taken with autograd on,
    starting from the (detached) converged point. Its derivative is the implicit-function
    derivative ``-J^-1 d(residual)``, i.e. the exact gradient of the inverse, without storing
    the whole iteration graph. Iterates are kept inside the disc ``|x| <= r_max`` (the radius
    where the radial mapping folds) so that they cannot run away or swap to the wrong branch.

    Returns:
        x, y: undistorted normalised coordinates; valid: (no grad) the iteration converged
        (residual below ``64 eps sqrt(1 + |m|^2)`` in the input dtype) strictly inside the disc.
    """
    r_max = table.t_max
    r_max2 = r_max * r_max
    # Converged points have a residual of a few ulp of |m|; allow 64 ulp.
    tol2 = (64.0 * torch.finfo(mx.dtype).eps) ** 2

    def clamp_disc(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        rr = x * x + y * y
        s = torch.where(rr > r_max2, r_max / safe_sqrt(rr), torch.ones_like(rr))
        return x * s, y * s

    def newton(
        dd: Distortion, x: Tensor, y: Tensor, tx: Tensor, ty: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        xd, yd, a, b, c, d = dd.with_jacobian(x, y)
        ex = xd - tx
        ey = yd - ty
        det = a * d - b * c
        det = torch.where(det.abs() > torch.finfo(det.dtype).tiny, det, torch.ones_like(det))
        return x - (d * ex - b * ey) / det, y - (a * ey - c * ex) / det, ex, ey

    tiny = torch.finfo(mx.dtype).tiny
    tx, ty = mx.detach(), my.detach()

    def fast_step(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        # newton() with float coefficients and in-place ops: these steps are memory bound.
        xd, yd, a, b, c, d = dist_f.with_jacobian_fast(x, y)
        ex = xd.sub_(tx)
        ey = yd.sub_(ty)
        det = (a * d).sub_(b * c)
        det.masked_fill_(det.abs() <= tiny, 1.0)
        return x - (d * ex).sub_(b * ey).div_(det), y - (a * ey).sub_(c * ex).div_(det)

    with torch.no_grad():
        rd2 = tx * tx + ty * ty
        rd = safe_sqrt(rd2)
        t0, _lo, _hi = table.lookup(rd)
        scale = torch.where(rd2 > tiny, t0 / rd, torch.ones_like(rd))
        x, y = clamp_disc(tx * scale, ty * scale)
        for _ in range(steps):
            x, y = fast_step(x, y)
            # Back into the fold disc: scale = min(1, r_max / |x|) (rsqrt(0) = inf -> 1).
            s_ = torch.addcmul(x * x, y, y).rsqrt_().mul_(r_max).clamp_(max=1.0)
            x.mul_(s_)
            y.mul_(s_)
    if mx.requires_grad or my.requires_grad:
        x, y, _ex, _ey = newton(dist, x, y, mx, my)
    else:  # nothing to differentiate: the same last step, the cheap way
        with torch.no_grad():
            x, y = fast_step(x, y)
    with torch.no_grad():
        # Convergence is judged on the returned point (one cheap distortion evaluation).
        xf, yf = x.detach(), y.detach()
        xd, yd = dist_f(xf, yf)
        res = (xd - tx) ** 2 + (yd - ty) ** 2
        ok = (res <= tol2 * (1.0 + tx * tx + ty * ty)) & torch.isfinite(xf) & torch.isfinite(yf)
        # A pixel beyond the fold has its solution pinned to the disc edge, from where the
        # last Newton step points outwards: that (not a residual tolerance, which float32
        # would have to keep loose) decides validity at the boundary.
        ok = ok & (xf * xf + yf * yf < r_max2)
    # Only invalid points can move far in this step; keep them finite.
    x, y = clamp_disc(x, y)
    fin = torch.isfinite(x) & torch.isfinite(y)
    x = torch.where(fin, x, torch.zeros_like(x))
    y = torch.where(fin, y, torch.zeros_like(y))
    return x, y, ok


def solve_odd_poly(
    target: Tensor, ks: Sequence[Tensor], k_values: Sequence[float], table: RadialTable, steps: int
) -> Tensor:
    """Solve ``t * (1 + k1 t^2 + k2 t^4 + ...) = target`` for t in [0, t_max].

    Newton with a fixed number of steps, started in the table cell that holds the root and
    clamped to it (the function is increasing on [0, t_max], ``t_max = table.t_max``, so the
    cell is a true bracket). ``k_values`` are the coefficients as floats for the iterations,
    ``ks`` the tensors for the final step, which alone carries autograd (see :func:`undistort`).
    Targets beyond the range end at t_max.
    """
    t_max = table.t_max
    c = [float(k) for k in k_values]
    d = [(2 * i + 3) * k for i, k in enumerate(c)]
    tiny = torch.finfo(target.dtype).tiny
    need_grad = target.requires_grad
    with torch.no_grad():
        tgt = target.detach()
        t, lo, hi = table.lookup(tgt)
        # Widen the cell a little: the float32 copy of the table may miss the root by an ulp.
        pad = 0.01 * (hi - lo)
        lo = (lo - pad).clamp_(min=0.0)
        hi = (hi + pad).clamp_(max=t_max)
        # Without autograd the final step is just one more of these (cheaper) steps.
        for _ in range(steps if need_grad else steps + 1):
            t2 = t * t
            f = t2 * c[-1]  # Horner, in place: f = t (1 + k1 t^2 + ...) - target
            fp = t2 * d[-1]  # f' = 1 + 3 k1 t^2 + 5 k2 t^4 + ...
            for k, dk in zip(reversed(c[:-1]), reversed(d[:-1]), strict=True):
                f.add_(k).mul_(t2)
                fp.add_(dk).mul_(t2)
            f.add_(1.0).mul_(t).sub_(tgt)
            # f' > 0 inside the bracket; the clamp only matters at a fold end, where f' = 0
            # would turn a zero residual into 0 / 0 (clamp with tensor bounds keeps NaN).
            fp.add_(1.0).clamp_(min=tiny)
            t = (t - f.div_(fp)).clamp_(min=lo, max=hi)
    if not need_grad:
        return t
    t2 = t * t
    f = t * radial_poly(t2, ks)
    fp = radial_poly(t2, ks) + 2.0 * t2 * radial_poly_d(t2, ks)
    fp = torch.where(fp.abs() > tiny, fp, torch.ones_like(fp))
    # The clamp is inactive for targets inside the range; outside it keeps the result finite.
    return torch.clamp(t - (f - target) / fp, 0.0, t_max)
