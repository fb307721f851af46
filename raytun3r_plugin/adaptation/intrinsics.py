"""Rough calibration: refine the focal length and the first distortion term from the matches.

A user's calibration is often a few percent off (a data-sheet focal, a lens of the same type).
:func:`refine_intrinsics` takes the adaptation set (matches of every ordered frame pair and their
relative-pose targets, :func:`~raytun3r_plugin.adaptation.windows.prepare_adaptation_set`) and
refines jointly

* one relative focal factor ``fx, fy <- exp(s) fx, exp(s) fy`` (the aspect ratio and the
  principal point are kept),
* the model's first distortion parameter (:data:`DISTORTION_TERM`: ``k1`` for Kannala-Brandt,
  ``xi`` for double sphere, ...), and
* every pair's relative pose (rotation + unit translation, 5 degrees of freedom),

by Levenberg-Marquardt on the Cauchy-robustified tangent-Sampson error of the unit rays (the
residual of the pose targets' own polish,
:func:`~raytun3r_plugin.adaptation.pose_targets.tangent_sampson_error`: an angle, uniform over a
fisheye image). The normal equations are solved by a Schur complement on the two intrinsic
unknowns (each pose block is 5 x 5), Jacobians by finite differences (central for the intrinsics,
which go through ``camera.unproject``; forward for the poses), all in float64 numpy: the result is
a deterministic function of the inputs.

Matches used: each distinct ordered frame pair once (overlapping windows share pairs), its
target's inliers only (subsampled evenly to ``max_matches_per_pair``); pairs whose target failed
are skipped.

Conditioning: the epipolar error of a pair whose translation runs along the optical axis (a
car driving forward) does not change when the focal or a radial distortion changes (the epipolar
great circles all pass through the axis), so no data determine the intrinsics. The refinement
estimates the standard deviation of the focal factor from the reduced Gauss-Newton Hessian
(``sigma^2 S^-1``, ``sigma^2`` the weighted residual variance) before and after the fit, and
leaves the camera unchanged, saying why in the report, when it exceeds ``max_focal_std``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from raytun3r_plugin.adaptation.pose_targets import (
    _so3_exp,
    _tangent_basis,
    camera_focal_px,
    tangent_sampson_error,
    unproject_pixels,
)
from raytun3r_plugin.errors import CameraError, InputError

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.adaptation.windows import AdaptationSet
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["DISTORTION_TERM", "IntrinsicsReport", "distortion_term", "refine_intrinsics"]

#: The parameter refined as "the first distortion term" of each camera model (``None``: the
#: model has none, only the focal can be refined). ``"k1"`` in ``params`` means this parameter.
DISTORTION_TERM: dict[str, str | None] = {
    "pinhole": None,
    "opencv": "k1",
    "kb4": "k1",
    "thin_prism_fisheye": "k1",
    "fisheye624": "k0",
    "ucm": "alpha",
    "eucm": "alpha",
    "ds": "xi",
    "mei": "xi",
    "fov": "omega",
}

# Finite-difference steps: relative focal (log units) and the distortion parameter.
_EPS_FOCAL = 1e-6
_EPS_DIST = 1e-6
_EPS_POSE = 1e-7


def distortion_term(camera: Camera) -> str | None:
    """Name of ``camera``'s first distortion parameter (:data:`DISTORTION_TERM`), or ``None``.

    Models not in the table use the first parameter after ``fx, fy, cx, cy`` when there is one.
    """
    model = str(getattr(camera, "model", ""))
    if model in DISTORTION_TERM:
        return DISTORTION_TERM[model]
    names = tuple(getattr(camera, "param_names", ()))
    return names[4] if len(names) > 4 else None


@dataclass
class IntrinsicsReport:
    """What :func:`refine_intrinsics` did.

    Attributes:
        model: camera model name.
        params: what was refined (``"focal"`` and/or the distortion parameter's name).
        refined: the returned camera differs from the input one.
        reason: why the camera was left unchanged (empty when ``refined``).
        initial, final: ``{"fx", "fy", <distortion name>}`` before and after.
        focal_change: relative change of the focal, ``final fx / initial fx - 1``.
        error_before_px, error_after_px: root mean square of the tangent-Sampson error over the
            inlier matches, in pixels at the image centre (radians times the initial camera's
            :func:`~raytun3r_plugin.adaptation.pose_targets.camera_focal_px`), at the targets'
            poses with the initial camera and at the refined poses and camera.
        cost_before, cost_after: the robust (Cauchy) objective, same matches.
        focal_std_before, focal_std: estimated standard deviation of the relative focal factor
            at the start and at the solution (conditioning, module docstring).
        distortion_std: same for the distortion parameter at the solution (its own units).
        pairs_used: distinct ordered frame pairs used; ``matches_used``: their matches.
        pairs_rotating: of those, pairs whose target rotation exceeds 1 degree.
        iterations: LM iterations done; ``converged``: the relative cost decrease fell below
            the tolerance (or the step below it) before ``max_iterations``.
    """

    model: str
    params: list[str]
    refined: bool
    reason: str
    initial: dict[str, float]
    final: dict[str, float]
    focal_change: float
    error_before_px: float
    error_after_px: float
    cost_before: float
    cost_after: float
    focal_std_before: float
    focal_std: float
    distortion_std: float | None
    pairs_used: int
    matches_used: int
    pairs_rotating: int
    iterations: int
    converged: bool
    settings: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (non-finite numbers become ``None``)."""

        def clean(value: Any) -> Any:
            if isinstance(value, float) and not math.isfinite(value):
                return None
            if isinstance(value, dict):
                return {k: clean(v) for k, v in value.items()}
            if isinstance(value, list):
                return [clean(v) for v in value]
            return value

        return clean(asdict(self))


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass
class _PairData:
    uv_i: np.ndarray  # (M, 2) native pixels
    uv_j: np.ndarray
    R: np.ndarray  # (3, 3) start rotation
    t: np.ndarray  # (3,) start unit translation


def _collect_pairs(adaptation: AdaptationSet, max_matches: int) -> list[_PairData]:
    """Each distinct ordered global pair once, its target's inliers, evenly subsampled."""
    seen: set[tuple[int, int]] = set()
    out: list[_PairData] = []
    for window in adaptation.windows:
        for key, matches in window.pairs.items():
            pair = window.global_pair(*key)
            target = window.targets.get(key)
            if pair in seen or target is None or not target.ok:
                continue
            seen.add(pair)
            idx = np.flatnonzero(target.inlier_mask)
            if idx.size > max_matches:
                # Evenly spaced, not random: the result must not depend on a generator.
                idx = idx[np.linspace(0, idx.size - 1, max_matches).round().astype(np.int64)]
            if idx.size < 8:
                continue
            out.append(
                _PairData(
                    np.asarray(matches.uv_i, np.float64)[idx],
                    np.asarray(matches.uv_j, np.float64)[idx],
                    target.R.copy(),
                    target.t.copy(),
                )
            )
    return out


def _rotation_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))))


class _Intrinsics:
    """The camera as a function of ``(s, d)``: focal factor ``exp(s)``, distortion value ``d``."""

    def __init__(self, camera: Camera, dist_index: int | None) -> None:
        self.camera = camera
        self.base = camera.params.detach().to(torch.float64).clone()
        self.dist_index = dist_index

    def start(self) -> np.ndarray:
        d = 0.0 if self.dist_index is None else float(self.base[self.dist_index])
        return np.array([0.0, d])

    def make(self, x: np.ndarray) -> Camera:
        p = self.base.clone()
        p[:2] = p[:2] * math.exp(float(x[0]))
        if self.dist_index is not None:
            p[self.dist_index] = float(x[1])
        return type(self.camera)(
            self.camera.width, self.camera.height, p, max_fov_deg=self.camera.max_fov_deg
        )


def _rays(camera: Camera, pairs: list[_PairData]) -> list[tuple[np.ndarray, np.ndarray]]:
    uv = np.concatenate([np.concatenate([p.uv_i, p.uv_j]) for p in pairs])
    rays, _ = unproject_pixels(camera, uv)
    out, start = [], 0
    for p in pairs:
        m = len(p.uv_i)
        out.append((rays[start : start + m], rays[start + m : start + 2 * m]))
        start += 2 * m
    return out


def _robust(res: np.ndarray, scale: float) -> float:
    return float(np.sum(np.log1p((res / scale) ** 2)))


# --------------------------------------------------------------------------------------------
# Refinement
# --------------------------------------------------------------------------------------------


def refine_intrinsics(
    camera: Camera,
    adaptation_set: AdaptationSet,
    *,
    params: tuple[str, ...] | list[str] = ("focal", "k1"),
    robust_px: float = 1.0,
    max_iterations: int = 50,
    max_matches_per_pair: int = 400,
    min_pairs: int = 3,
    max_focal_std: float = 0.01,
    tolerance: float = 1e-10,
) -> tuple[Camera, IntrinsicsReport]:
    """Jointly refine the focal and the first distortion term with every pair's relative pose.

    Args:
        camera: the (rough) camera of the native frames the adaptation set was matched on.
        adaptation_set: :func:`~raytun3r_plugin.adaptation.windows.prepare_adaptation_set`'s
            result for ``camera``: its matches, targets (start poses) and inlier masks.
        params: any of ``"focal"`` (one relative factor on ``fx`` and ``fy``) and ``"k1"``
            (the model's first distortion parameter, :data:`DISTORTION_TERM`; its own name,
            e.g. ``"xi"``, is accepted too).
        robust_px: scale of the Cauchy loss, pixels at the image centre.
        max_iterations: Levenberg-Marquardt iteration cap.
        max_matches_per_pair: inliers kept per pair (evenly spaced).
        min_pairs: fewer distinct usable pairs than this is refused.
        max_focal_std: leave the camera unchanged when the estimated standard deviation of the
            relative focal (before or after the fit) exceeds this (0.01 = 1 %).
        tolerance: convergence: relative cost decrease below this.

    Returns:
        ``(camera, report)``: the refined camera (same model, size, principal point, other
        parameters and ``max_fov_deg``), or the input camera itself when the data cannot
        determine the intrinsics (``report.refined`` false, ``report.reason`` says why).

    Raises:
        InputError: unknown ``params``, a distortion term asked of a model without one
            (``pinhole``: refine ``("focal",)``), fewer than ``min_pairs`` usable pairs, or
            bad settings.
    """
    names = [str(p) for p in params]
    dist_name = distortion_term(camera)
    want_focal = "focal" in names
    want_dist = False
    for name in names:
        if name == "focal":
            continue
        if name == "k1" or name == dist_name:
            if dist_name is None:
                raise InputError(
                    f"camera model {camera.model!r} has no distortion term to refine; "
                    "use params=('focal',)"
                )
            want_dist = True
            continue
        raise InputError(
            f"refine_intrinsics: unknown parameter {name!r}; expected 'focal' and/or 'k1' "
            f"(this model's first distortion term is {dist_name!r})"
        )
    if not (want_focal or want_dist):
        raise InputError("refine_intrinsics: params is empty")
    for label, ok in (
        ("robust_px", robust_px > 0),
        ("max_iterations", max_iterations >= 1),
        ("max_matches_per_pair", max_matches_per_pair >= 8),
        ("min_pairs", min_pairs >= 1),
        ("max_focal_std", max_focal_std > 0),
    ):
        if not ok:
            raise InputError(f"refine_intrinsics: {label} is not allowed")
    pairs = _collect_pairs(adaptation_set, max_matches_per_pair)
    if len(pairs) < min_pairs:
        raise InputError(
            f"refine_intrinsics needs at least {min_pairs} frame pairs with a usable pose target, "
            f"got {len(pairs)}: the intrinsics cannot be determined"
        )

    refined_names = (["focal"] if want_focal else []) + ([str(dist_name)] if want_dist else [])
    dist_index = (
        list(camera.param_names).index(dist_name) if want_dist and dist_name is not None else None
    )
    model = _Intrinsics(camera, dist_index)
    free = np.array([want_focal, want_dist])
    focal0 = camera_focal_px(camera)
    scale = robust_px / focal0  # radians

    def values(cam: Camera) -> dict[str, float]:
        out = {"fx": float(cam.params[0]), "fy": float(cam.params[1])}
        if dist_name is not None:
            out[dist_name] = float(cam.params[list(cam.param_names).index(dist_name)])
        return out

    x = model.start()
    poses = [(p.R.copy(), p.t.copy()) for p in pairs]
    rays = _rays(camera, pairs)

    def residuals(
        ray_list: list[tuple[np.ndarray, np.ndarray]],
        pose_list: list[tuple[np.ndarray, np.ndarray]],
    ) -> list[np.ndarray]:
        return [
            np.nan_to_num(tangent_sampson_error(R, t, f1, f2), nan=1.0, posinf=1.0, neginf=-1.0)
            for (f1, f2), (R, t) in zip(ray_list, pose_list, strict=True)
        ]

    def normal_equations(
        x: np.ndarray,
        ray_list: list[tuple[np.ndarray, np.ndarray]],
        pose_list: list[tuple[np.ndarray, np.ndarray]],
        res: list[np.ndarray],
    ) -> tuple[list, np.ndarray, np.ndarray, float, int]:
        """Per pair (H_pp, H_pc, g_p), the intrinsic H_cc, g_c, and sum(w r^2), count."""
        # Intrinsic Jacobian: central differences through unproject (every pair at once).
        jac_c = [np.zeros((len(r), 2)) for r in res]
        for k, eps in ((0, _EPS_FOCAL), (1, _EPS_DIST)):
            if not free[k]:
                continue
            step = np.eye(2)[k] * eps
            plus = residuals(_rays(model.make(x + step), pairs), pose_list)
            minus = residuals(_rays(model.make(x - step), pairs), pose_list)
            for j, (a, b) in enumerate(zip(plus, minus, strict=True)):
                jac_c[j][:, k] = (a - b) / (2 * eps)
        blocks = []
        H_cc, g_c = np.zeros((2, 2)), np.zeros(2)
        wr2, count = 0.0, 0
        for (f1, f2), (R, t), r, Jc in zip(ray_list, pose_list, res, jac_c, strict=True):
            B = _tangent_basis(t)
            cols = []
            for k in range(5):
                if k < 3:
                    R2, t2 = _so3_exp(_EPS_POSE * np.eye(3)[k]) @ R, t
                else:
                    R2, t2 = R, t + _EPS_POSE * B[:, k - 3]
                    t2 = t2 / np.linalg.norm(t2)
                cols.append((tangent_sampson_error(R2, t2, f1, f2) - r) / _EPS_POSE)
            Jp = np.stack(cols, axis=1)
            w = 1.0 / (1.0 + (r / scale) ** 2)  # IRLS weights of the Cauchy loss
            Jpw, Jcw = Jp * w[:, None], Jc * w[:, None]
            blocks.append((Jp.T @ Jpw, Jpw.T @ Jc, Jp.T @ (w * r)))
            H_cc += Jc.T @ Jcw
            g_c += Jcw.T @ r
            wr2 += float(np.sum(w * r**2))
            count += len(r)
        return blocks, H_cc, g_c, wr2, count

    def reduced(blocks: list, H_cc: np.ndarray, lam: float = 0.0) -> np.ndarray:
        S = H_cc.copy()
        for H_pp, H_pc, _ in blocks:
            A = H_pp + lam * np.diag(np.diag(H_pp) + 1e-12)
            S -= H_pc.T @ np.linalg.solve(A, H_pc)
        return S

    def std_of(blocks: list, H_cc: np.ndarray, wr2: float, count: int) -> np.ndarray:
        """Standard deviations of (s, d) from the reduced undamped Hessian."""
        S = reduced(blocks, H_cc)[np.ix_(free, free)]
        dof = max(1, count - 5 * len(blocks) - int(free.sum()))
        sigma2 = wr2 / dof
        try:
            cov = sigma2 * np.linalg.inv(S)
            diag = np.diag(cov)
        except np.linalg.LinAlgError:
            diag = np.full(int(free.sum()), np.inf)
        out = np.full(2, np.nan)
        out[free] = np.sqrt(np.where(diag > 0, diag, np.inf))
        return out

    def rms_px(res: list[np.ndarray]) -> float:
        flat = np.concatenate(res)
        return float(np.sqrt(np.mean(flat**2)) * focal0)

    res = residuals(rays, poses)
    cost0 = sum(_robust(r, scale) for r in res)
    error0 = rms_px(res)
    blocks, H_cc, g_c, wr2, count = normal_equations(x, rays, poses, res)
    std0 = std_of(blocks, H_cc, wr2, count)
    n_rot = sum(1 for p in pairs if _rotation_deg(p.R) > 1.0)
    settings = {
        "robust_px": robust_px,
        "max_iterations": max_iterations,
        "max_matches_per_pair": max_matches_per_pair,
        "min_pairs": min_pairs,
        "max_focal_std": max_focal_std,
    }

    def report(
        cam: Camera,
        refined: bool,
        reason: str,
        err: float,
        cost: float,
        std: np.ndarray,
        it: int,
        conv: bool,
    ) -> IntrinsicsReport:
        initial, final = values(camera), values(cam)
        return IntrinsicsReport(
            model=str(camera.model),
            params=refined_names,
            refined=refined,
            reason=reason,
            initial=initial,
            final=final,
            focal_change=final["fx"] / initial["fx"] - 1.0,
            error_before_px=error0,
            error_after_px=err,
            cost_before=cost0,
            cost_after=cost,
            focal_std_before=float(std0[0]) if want_focal else float("nan"),
            focal_std=float(std[0]) if want_focal else float("nan"),
            distortion_std=float(std[1]) if want_dist else None,
            pairs_used=len(pairs),
            matches_used=count,
            pairs_rotating=n_rot,
            iterations=it,
            converged=conv,
            settings=settings,
        )

    if want_focal and not std0[0] <= max_focal_std:
        return camera, report(
            camera,
            False,
            f"the matches do not determine the focal: estimated standard deviation "
            f"{std0[0]:.3g} > max_focal_std {max_focal_std:g} ({n_rot} of {len(pairs)} pairs "
            "rotate by more than 1 degree; pure forward translation constrains neither focal "
            "nor radial distortion)",
            error0,
            cost0,
            std0,
            0,
            False,
        )

    lam, cost, converged, iterations = 1e-3, cost0, False, 0
    for _ in range(max_iterations):
        iterations += 1
        improved = False
        for _attempt in range(10):
            try:
                S = reduced(blocks, H_cc, lam)
                b = g_c.copy()
                sols = []
                for H_pp, H_pc, g_p in blocks:
                    A = H_pp + lam * np.diag(np.diag(H_pp) + 1e-12)
                    sol = np.linalg.solve(A, np.stack([g_p, *H_pc.T], axis=1))
                    sols.append(sol)
                    b -= H_pc.T @ sol[:, 0]
                S = S + lam * np.diag(np.diag(S) + 1e-12)
                dx = np.zeros(2)
                dx[free] = -np.linalg.solve(S[np.ix_(free, free)], b[free])
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            new_poses = []
            for (R, t), sol in zip(poses, sols, strict=True):
                # dp = -A^-1 (g_p + H_pc dx)
                dp = -(sol[:, 0] + sol[:, 1:] @ dx)
                t_new = t + _tangent_basis(t) @ dp[3:]
                new_poses.append((_so3_exp(dp[:3]) @ R, t_new / np.linalg.norm(t_new)))
            x_new = x + dx
            try:
                new_rays = _rays(model.make(x_new), pairs)
            except CameraError:  # the step left the model's domain: damp more
                lam *= 10.0
                continue
            new_res = residuals(new_rays, new_poses)
            new_cost = sum(_robust(r, scale) for r in new_res)
            if new_cost < cost:
                converged = cost - new_cost < tolerance * max(cost, 1e-30)
                x, poses, rays, res, cost = x_new, new_poses, new_rays, new_res, new_cost
                lam = max(lam / 10.0, 1e-12)
                improved = True
                break
            lam *= 10.0
        if not improved:
            converged = True  # no damped step lowers the cost: a (local) minimum
            break
        blocks, H_cc, g_c, wr2, count = normal_equations(x, rays, poses, res)
        if converged:
            break

    refined_camera = model.make(x)
    std = std_of(blocks, H_cc, wr2, count)
    if want_focal and not std[0] <= max_focal_std:
        return camera, report(
            camera,
            False,
            f"the fit does not determine the focal: estimated standard deviation {std[0]:.3g} "
            f"> max_focal_std {max_focal_std:g}",
            error0,
            cost0,
            std,
            iterations,
            converged,
        )
    return refined_camera, report(
        refined_camera, True, "", rms_px(res), cost, std, iterations, converged
    )
