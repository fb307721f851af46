"""Which lens an export writes: the camera's own model where the target format has it, else a
Kannala-Brandt (``OPENCV_FISHEYE``) lens fitted over the valid image, with its error stated.

COLMAP (4.1 and later) has PINHOLE, OPENCV, OPENCV_FISHEYE, THIN_PRISM_FISHEYE, FOV, EUCM and
RAD_TAN_THIN_PRISM_FISHEYE (= Fisheye624) with raytun3r's parameter order; UCM is EUCM with
beta = 1. Double sphere and MEI have no COLMAP model: they are fitted (docs/decisions.md,
"Exports"). nerfstudio reads OPENCV (radial-tangential), OPENCV_FISHEYE and FISHEYE624; every
other lens is fitted for it too.

Every writer adds 0.5 to cx, cy: COLMAP and nerfstudio put the centre of the top-left pixel at
(0.5, 0.5), raytun3r at (0, 0) (docs/conventions.md section 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.cameras.formats.colmap import COLMAP_EXPORT_MODEL
from raytun3r_plugin.errors import InputError

__all__ = [
    "COLMAP_MODEL_IDS",
    "WrittenLens",
    "colmap_lens",
    "fit_kb4",
    "kb4_project",
    "nerfstudio_lens",
]

#: COLMAP's numeric model ids (``cameras.bin``), as in COLMAP's ``sensor/models.h``.
COLMAP_MODEL_IDS = {
    "SIMPLE_PINHOLE": 0,
    "PINHOLE": 1,
    "OPENCV": 4,
    "OPENCV_FISHEYE": 5,
    "FULL_OPENCV": 6,
    "FOV": 7,
    "THIN_PRISM_FISHEYE": 10,
    "RAD_TAN_THIN_PRISM_FISHEYE": 11,
    "EUCM": 16,
}


#: COLMAP projects through x / z: no ray at or beyond 90 degrees from the axis has a pixel.
#: Observations and fits stop a degree short of it.
COLMAP_MAX_ANGLE_DEG = 89.0

#: Default refusal threshold of a fitted lens: worst reprojection error over the fitted region.
DEFAULT_MAX_FIT_ERROR_PX = 2.0


def kb4_project(points: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Kannala-Brandt projection (COLMAP ``OPENCV_FISHEYE``, theta = atan2(r, z)).

    points: (N, 3) camera-frame points; params: fx, fy, cx, cy, k1..k4 (raytun3r pixels).
    Returns (N, 2) pixels in raytun3r's convention.
    """
    fx, fy, cx, cy, k1, k2, k3, k4 = (float(v) for v in params)
    x, y, z = np.asarray(points, dtype=np.float64).T
    r = np.hypot(x, y)
    theta = np.arctan2(r, z)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-300), 1.0 / np.maximum(z, 1e-300))
    return np.stack([fx * x * scale + cx, fy * y * scale + cy], -1)


def _kb4_residual_and_jacobian(
    params: np.ndarray, direction: np.ndarray, powers: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) of the Kannala-Brandt projection against ``uv`` and their (2N, 8)
    Jacobian in fx, fy, cx, cy, k1..k4; ``direction`` (N, 2) = (x, y) / r, ``powers`` (N, 5) =
    theta, theta^3, ..., theta^9."""
    fx, fy, cx, cy = params[:4]
    theta_d = powers @ np.concatenate([[1.0], params[4:]])
    u = fx * direction[:, 0] * theta_d + cx
    v = fy * direction[:, 1] * theta_d + cy
    count = len(uv)
    jac = np.zeros((2 * count, 8))
    jac[:count, 0] = direction[:, 0] * theta_d
    jac[:count, 2] = 1.0
    jac[:count, 4:] = fx * direction[:, :1] * powers[:, 1:]
    jac[count:, 1] = direction[:, 1] * theta_d
    jac[count:, 3] = 1.0
    jac[count:, 4:] = fy * direction[:, 1:] * powers[:, 1:]
    return np.concatenate([u - uv[:, 0], v - uv[:, 1]]), jac


def _samples(camera: Camera, max_angle_deg: float, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (every ``step``-th, float64) with a valid ray at most ``max_angle_deg`` off-axis."""
    rays, valid = camera.ray_table(device="cpu", dtype=torch.float64)
    rays, valid = rays[::step, ::step].reshape(-1, 3), valid[::step, ::step].reshape(-1)
    grid = camera.pixel_grid("cpu", torch.float64)[::step, ::step].reshape(-1, 2)
    keep = valid & (rays[:, 2] > math.cos(math.radians(max_angle_deg)))
    return grid[keep].numpy(), rays[keep].numpy()


def fit_kb4(camera: Camera, max_angle_deg: float, iterations: int = 30) -> tuple[np.ndarray, dict]:
    """The Kannala-Brandt lens closest to ``camera`` in pixels, over its valid image up to
    ``max_angle_deg`` from the axis.

    Linear least squares for fx, fy and k1..k4 with the principal point held at the camera's,
    then Levenberg-Marquardt over all eight parameters on every pixel (every second pixel on
    images above 512 px). Returns the (8,) parameters (raytun3r pixels) and a record with the
    ``worst_px`` and ``median_px`` reprojection errors over every valid pixel in the region.
    """
    step = max(1, math.ceil(max(camera.width, camera.height) / 256))
    uv, rays = _samples(camera, max_angle_deg, step)
    if len(uv) < 16:
        raise InputError(
            f"{camera.model} camera: too few valid pixels within {max_angle_deg} degrees of the axis to fit a lens"
        )
    cx, cy = camera.values["cx"], camera.values["cy"]
    r = np.hypot(rays[:, 0], rays[:, 1])
    theta = np.arctan2(r, rays[:, 2])
    direction = rays[:, :2] / np.maximum(r, 1e-12)[:, None]
    basis = np.stack([theta ** (2 * i + 1) for i in range(5)], -1)  # theta, theta^3, ..., theta^9
    coef_u = np.linalg.lstsq(basis * direction[:, :1], uv[:, 0] - cx, rcond=None)[0]
    coef_v = np.linalg.lstsq(basis * direction[:, 1:], uv[:, 1] - cy, rcond=None)[0]
    ks = 0.5 * (coef_u[1:] / coef_u[0] + coef_v[1:] / coef_v[0])
    params = np.array([coef_u[0], coef_v[0], cx, cy, *ks])
    residual, jac = _kb4_residual_and_jacobian(params, direction, basis, uv)
    cost, damping = float(residual @ residual), 1e-6
    for _ in range(iterations):
        normal = jac.T @ jac
        step_p = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), -jac.T @ residual)
        trial = params + step_p
        trial_residual, trial_jac = _kb4_residual_and_jacobian(trial, direction, basis, uv)
        trial_cost = float(trial_residual @ trial_residual)
        if trial_cost < cost:
            converged = cost - trial_cost < 1e-14 * max(cost, 1e-30)
            params, residual, jac, cost = trial, trial_residual, trial_jac, trial_cost
            damping = max(damping / 10, 1e-12)
            if converged:
                break
        else:
            damping *= 10
    fitted = params
    uv_all, rays_all = _samples(camera, max_angle_deg, 1)
    error = np.linalg.norm(kb4_project(rays_all, fitted) - uv_all, axis=-1)
    record = {
        "model": "OPENCV_FISHEYE",
        "fitted_to": camera.model,
        "max_angle_deg": float(max_angle_deg),
        "pixels": int(len(error)),
        "worst_px": float(error.max()),
        "median_px": float(np.median(error)),
    }
    return fitted, record


@dataclass(frozen=True)
class WrittenLens:
    """The lens as a format stores it.

    Attributes:
        model: the format's model name (``OPENCV_FISHEYE``, ``EUCM``, ...).
        params: parameters in the format's order, principal point in raytun3r pixels (the
            writers add 0.5).
        camera: the scene's camera (projections of an exact lens are its own).
        fit: None for an exact lens; else :func:`fit_kb4`'s record.
        max_angle_deg: rays further off-axis than this are not given to the format (COLMAP:
            :data:`COLMAP_MAX_ANGLE_DEG`); None = the camera's whole valid region.
    """

    model: str
    params: tuple[float, ...]
    camera: Camera
    fit: dict | None = None
    max_angle_deg: float | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def exact(self) -> bool:
        return self.fit is None

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) camera-frame points -> (N, 2) raytun3r pixels through the written lens, and
        (N,) bool: valid in the camera and within ``max_angle_deg``."""
        points = np.asarray(points, dtype=np.float64)
        norm = np.linalg.norm(points, axis=-1)
        ok = norm > 0
        if self.max_angle_deg is not None:
            ok &= points[:, 2] > math.cos(math.radians(self.max_angle_deg)) * norm
        uv, valid = self.camera.project(torch.from_numpy(points))
        ok &= valid.numpy()
        if self.fit is not None:
            return kb4_project(points, np.asarray(self.params)), ok
        return uv.numpy(), ok


def _fitted(camera: Camera, max_angle_deg: float, max_error_px: float, target: str) -> WrittenLens:
    params, record = fit_kb4(camera, max_angle_deg)
    if record["worst_px"] > max_error_px:
        raise InputError(
            f"{target} has no {camera.model!r} lens; the closest OPENCV_FISHEYE lens misses by up to "
            f"{record['worst_px']:.3g} px (median {record['median_px']:.3g} px) over the valid image, "
            f"more than the allowed {max_error_px:g} px. Alternatives: --export glb or rerun (they keep "
            "the exact lens as 3-D points), a larger --max-fit-error-px, --colmap-lens native (COLMAP "
            "4.1+ models), or calibrate the camera as kb4"
        )
    note = (
        f"{target}: {camera.model} lens written as a fitted OPENCV_FISHEYE: worst {record['worst_px']:.3g} px, "
        f"median {record['median_px']:.3g} px over {record['pixels']} pixels within {max_angle_deg:g} deg"
    )
    return WrittenLens(
        "OPENCV_FISHEYE", tuple(float(v) for v in params), camera, record, max_angle_deg, [note]
    )


#: What ``--colmap-lens`` accepts: ``native`` = COLMAP's own model where it has one;
#: ``opencv-fisheye`` = only the models readers that know the first six COLMAP models read
#: (PINHOLE, OPENCV, OPENCV_FISHEYE; gsplat's COLMAP loader, COLMAP before 4.1), every other
#: lens fitted as OPENCV_FISHEYE.
COLMAP_LENS_CHOICES = ("native", "opencv-fisheye")
_BASIC_COLMAP = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE")


def colmap_lens(
    camera: Camera,
    max_fit_error_px: float = DEFAULT_MAX_FIT_ERROR_PX,
    choice: str = "native",
) -> WrittenLens:
    """The lens ``camera`` is written with in a COLMAP model: exact where COLMAP has the model
    (``choice="native"``; with ``"opencv-fisheye"`` only PINHOLE, OPENCV and OPENCV_FISHEYE are
    exact), else a fitted OPENCV_FISHEYE (:func:`fit_kb4`).

    Raises:
        InputError: an unknown ``choice``, or a fit worse than ``max_fit_error_px``.
    """
    if choice not in COLMAP_LENS_CHOICES:
        raise InputError(f"COLMAP lens must be one of {list(COLMAP_LENS_CHOICES)}, got {choice!r}")
    values = camera.values
    native = COLMAP_EXPORT_MODEL.get(camera.model, "EUCM" if camera.model == "ucm" else None)
    if choice == "opencv-fisheye" and native not in _BASIC_COLMAP:
        native = None
    if native is None:
        span = min(COLMAP_MAX_ANGLE_DEG, math.degrees(camera.max_angle))
        return _fitted(camera, span, max_fit_error_px, "COLMAP")
    if camera.model in COLMAP_EXPORT_MODEL:
        params = tuple(values[n] for n in camera.param_names)
        model = COLMAP_EXPORT_MODEL[camera.model]
    else:  # UCM(alpha) = EUCM(alpha, beta = 1), the same formula
        params, model = (*(values[n] for n in camera.param_names), 1.0), "EUCM"
    notes = []
    if camera.fov_deg > 2 * COLMAP_MAX_ANGLE_DEG:
        notes.append(
            f"COLMAP: the lens sees {camera.fov_deg:.0f} deg but COLMAP projects only rays within "
            f"{COLMAP_MAX_ANGLE_DEG:g} deg of the axis; observations beyond are left out"
        )
    if model in ("EUCM", "RAD_TAN_THIN_PRISM_FISHEYE"):
        notes.append(f"COLMAP: {model} needs COLMAP 4.1 or later")
    return WrittenLens(model, params, camera, None, COLMAP_MAX_ANGLE_DEG, notes)


def nerfstudio_lens(
    camera: Camera, max_fit_error_px: float = DEFAULT_MAX_FIT_ERROR_PX
) -> WrittenLens:
    """The lens ``camera`` is written with in nerfstudio's ``transforms.json``."""
    values = camera.values
    exact = {"pinhole": "OPENCV", "opencv": "OPENCV", "kb4": "OPENCV_FISHEYE"}
    if camera.model in exact:
        names = camera.param_names
        params = tuple(values[n] for n in names) + (0.0,) * (8 - len(names))
        return WrittenLens(exact[camera.model], params, camera)
    if camera.model == "fisheye624":
        return WrittenLens("FISHEYE624", tuple(values[n] for n in camera.param_names), camera)
    # nerfstudio's fisheye rays use theta itself, so the fit may span the whole valid image.
    return _fitted(camera, math.degrees(camera.max_angle), max_fit_error_px, "nerfstudio")
