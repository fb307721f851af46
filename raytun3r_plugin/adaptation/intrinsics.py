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

from raytun3r_plugin.adaptation.intrinsics_solver import (
    JointIntrinsicsProblem,
    LMState,
    NormalEquations,
    _collect_pairs,
    _Intrinsics,
    _PairData,
    _rotation_deg,
)
from raytun3r_plugin.adaptation.pose_targets import (
    camera_focal_px,
)
from raytun3r_plugin.errors import InputError

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
    dist_name = distortion_term(camera)
    want_focal, want_dist = _parse_params(camera, params)
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
    focal0 = camera_focal_px(camera)
    problem = JointIntrinsicsProblem(
        _Intrinsics(camera, dist_index),
        pairs,
        np.array([want_focal, want_dist]),
        robust_px / focal0,  # the Cauchy scale, radians
    )
    start = problem.start()
    system = problem.normal_equations(start)
    std0 = problem.std_of(system)
    report = _Reporter(
        camera,
        refined_names,
        dist_name,
        start,
        std0,
        focal0,
        pairs,
        {
            "robust_px": robust_px,
            "max_iterations": max_iterations,
            "max_matches_per_pair": max_matches_per_pair,
            "min_pairs": min_pairs,
            "max_focal_std": max_focal_std,
        },
    )
    if want_focal and not std0[0] <= max_focal_std:
        return camera, report(
            camera,
            start,
            system,
            std0,
            0,
            False,
            reason=f"the matches do not determine the focal: estimated standard deviation "
            f"{std0[0]:.3g} > max_focal_std {max_focal_std:g} ({report.rotating} of "
            f"{len(pairs)} pairs rotate by more than 1 degree; pure forward translation "
            "constrains neither focal nor radial distortion)",
        )
    state, system, iterations, converged = problem.solve(start, system, max_iterations, tolerance)
    std = problem.std_of(system)
    if want_focal and not std[0] <= max_focal_std:
        return camera, report(
            camera,
            start,
            system,
            std,
            iterations,
            converged,
            reason=f"the fit does not determine the focal: estimated standard deviation "
            f"{std[0]:.3g} > max_focal_std {max_focal_std:g}",
        )
    refined = problem.intrinsics.make(state.x)
    return refined, report(refined, state, system, std, iterations, converged)


def _parse_params(camera: Camera, params: tuple[str, ...] | list[str]) -> tuple[bool, bool]:
    """``(refine the focal, refine the distortion term)`` from ``params``; refuses the rest."""
    dist_name = distortion_term(camera)
    want_focal, want_dist = False, False
    for name in (str(p) for p in params):
        if name == "focal":
            want_focal = True
        elif name == "k1" or name == dist_name:
            if dist_name is None:
                raise InputError(
                    f"camera model {camera.model!r} has no distortion term to refine; "
                    "use params=('focal',)"
                )
            want_dist = True
        else:
            raise InputError(
                f"refine_intrinsics: unknown parameter {name!r}; expected 'focal' and/or 'k1' "
                f"(this model's first distortion term is {dist_name!r})"
            )
    if not (want_focal or want_dist):
        raise InputError("refine_intrinsics: params is empty")
    return want_focal, want_dist


class _Reporter:
    """Builds the :class:`IntrinsicsReport` of a refinement from its start and its end."""

    def __init__(
        self,
        camera: Camera,
        refined_names: list[str],
        dist_name: str | None,
        start: LMState,
        std0: np.ndarray,
        focal0: float,
        pairs: list[_PairData],
        settings: dict[str, Any],
    ) -> None:
        self.camera, self.names, self.dist_name = camera, refined_names, dist_name
        self.start, self.std0, self.focal0 = start, std0, focal0
        self.pairs, self.settings = pairs, settings
        self.rotating = sum(1 for p in pairs if _rotation_deg(p.R) > 1.0)

    def values(self, camera: Camera) -> dict[str, float]:
        out = {"fx": float(camera.params[0]), "fy": float(camera.params[1])}
        if self.dist_name is not None:
            out[self.dist_name] = float(
                camera.params[list(camera.param_names).index(self.dist_name)]
            )
        return out

    def rms_px(self, res: list[np.ndarray]) -> float:
        flat = np.concatenate(res)
        return float(np.sqrt(np.mean(flat**2)) * self.focal0)

    def __call__(
        self,
        camera: Camera,
        state: LMState,
        system: NormalEquations,
        std: np.ndarray,
        iterations: int,
        converged: bool,
        reason: str = "",
    ) -> IntrinsicsReport:
        """The report; ``reason`` non-empty: the camera was left unchanged (errors and costs
        are then the start's)."""
        refined = not reason
        end = state if refined else self.start
        initial, final = self.values(self.camera), self.values(camera)
        want_focal = "focal" in self.names
        want_dist = self.dist_name is not None and self.dist_name in self.names
        return IntrinsicsReport(
            model=str(self.camera.model),
            params=self.names,
            refined=refined,
            reason=reason,
            initial=initial,
            final=final,
            focal_change=final["fx"] / initial["fx"] - 1.0,
            error_before_px=self.rms_px(self.start.res),
            error_after_px=self.rms_px(end.res),
            cost_before=self.start.cost,
            cost_after=end.cost,
            focal_std_before=float(self.std0[0]) if want_focal else float("nan"),
            focal_std=float(std[0]) if want_focal else float("nan"),
            distortion_std=float(std[1]) if want_dist else None,
            pairs_used=len(self.pairs),
            matches_used=system.count,
            pairs_rotating=self.rotating,
            iterations=iterations,
            converged=converged,
            settings=self.settings,
        )
