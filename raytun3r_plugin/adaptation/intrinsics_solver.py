"""The least-squares problem behind :func:`~raytun3r_plugin.adaptation.intrinsics.refine_intrinsics`:
the pairs' matches, the camera as a function of ``(s, d)`` (focal factor ``exp(s)``, distortion
value ``d``), the robust tangent-Sampson residuals, the Schur-reduced normal equations and the
damped (Levenberg-Marquardt) steps. All float64 numpy, deterministic in its inputs; the method
is described in :mod:`raytun3r_plugin.adaptation.intrinsics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from raytun3r_plugin.adaptation.pose_targets import (
    _so3_exp,
    _tangent_basis,
    tangent_sampson_error,
    unproject_pixels,
)
from raytun3r_plugin.errors import CameraError

if TYPE_CHECKING:
    from raytun3r_plugin.adaptation.windows import AdaptationSet
    from raytun3r_plugin.cameras.base import Camera

# Finite-difference steps: relative focal (log units) and the distortion parameter.
_EPS_FOCAL = 1e-6
_EPS_DIST = 1e-6
_EPS_POSE = 1e-7

Rays = list[tuple[np.ndarray, np.ndarray]]
Poses = list[tuple[np.ndarray, np.ndarray]]


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


@dataclass
class NormalEquations:
    """Gauss-Newton system at one point: per pair ``(H_pp, H_pc, g_p)``, the intrinsic block
    ``H_cc`` (2, 2) and gradient ``g_c`` (2,), ``sum(w r^2)`` and the residual count."""

    blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    H_cc: np.ndarray
    g_c: np.ndarray
    wr2: float
    count: int


@dataclass
class LMState:
    """Where the solve is: intrinsics ``x`` (2,), poses, rays, residuals and robust cost."""

    x: np.ndarray
    poses: Poses
    rays: Rays
    res: list[np.ndarray]
    cost: float


class JointIntrinsicsProblem:
    """Focal and first distortion term with every pair's relative pose (5 dof each).

    Args:
        intrinsics: the camera as a function of ``(s, d)``.
        pairs: the pairs' inlier matches and start poses.
        free: (2,) bool, which of ``(s, d)`` are refined.
        scale: the Cauchy loss scale, radians.
    """

    def __init__(
        self, intrinsics: _Intrinsics, pairs: list[_PairData], free: np.ndarray, scale: float
    ) -> None:
        self.intrinsics = intrinsics
        self.pairs = pairs
        self.free = free
        self.scale = scale

    def start(self) -> LMState:
        """The state at the given camera and the targets' poses."""
        x = self.intrinsics.start()
        poses = [(p.R.copy(), p.t.copy()) for p in self.pairs]
        rays = _rays(self.intrinsics.camera, self.pairs)
        res = self.residuals(rays, poses)
        return LMState(x, poses, rays, res, self.cost(res))

    def residuals(self, rays: Rays, poses: Poses) -> list[np.ndarray]:
        """Per pair, (M,) tangent-Sampson errors in radians (non-finite ones clamped to 1)."""
        return [
            np.nan_to_num(tangent_sampson_error(R, t, f1, f2), nan=1.0, posinf=1.0, neginf=-1.0)
            for (f1, f2), (R, t) in zip(rays, poses, strict=True)
        ]

    def cost(self, res: list[np.ndarray]) -> float:
        """The robust (Cauchy) objective of residuals ``res``."""
        return sum(_robust(r, self.scale) for r in res)

    def normal_equations(self, state: LMState) -> NormalEquations:
        """The IRLS-weighted Gauss-Newton system at ``state``."""
        # Intrinsic Jacobian: central differences through unproject (every pair at once).
        jac_c = [np.zeros((len(r), 2)) for r in state.res]
        for k, eps in ((0, _EPS_FOCAL), (1, _EPS_DIST)):
            if not self.free[k]:
                continue
            step = np.eye(2)[k] * eps
            plus = self.residuals(
                _rays(self.intrinsics.make(state.x + step), self.pairs), state.poses
            )
            minus = self.residuals(
                _rays(self.intrinsics.make(state.x - step), self.pairs), state.poses
            )
            for j, (a, b) in enumerate(zip(plus, minus, strict=True)):
                jac_c[j][:, k] = (a - b) / (2 * eps)
        blocks = []
        H_cc, g_c = np.zeros((2, 2)), np.zeros(2)
        wr2, count = 0.0, 0
        for (f1, f2), (R, t), r, Jc in zip(state.rays, state.poses, state.res, jac_c, strict=True):
            Jp = _pose_jacobian(R, t, f1, f2, r)
            w = 1.0 / (1.0 + (r / self.scale) ** 2)  # IRLS weights of the Cauchy loss
            Jpw, Jcw = Jp * w[:, None], Jc * w[:, None]
            blocks.append((Jp.T @ Jpw, Jpw.T @ Jc, Jp.T @ (w * r)))
            H_cc += Jc.T @ Jcw
            g_c += Jcw.T @ r
            wr2 += float(np.sum(w * r**2))
            count += len(r)
        return NormalEquations(blocks, H_cc, g_c, wr2, count)

    @staticmethod
    def reduced(system: NormalEquations, lam: float = 0.0) -> np.ndarray:
        """The Schur complement on the intrinsics, pose blocks damped by ``lam``."""
        S = system.H_cc.copy()
        for H_pp, H_pc, _ in system.blocks:
            A = H_pp + lam * np.diag(np.diag(H_pp) + 1e-12)
            S -= H_pc.T @ np.linalg.solve(A, H_pc)
        return S

    def std_of(self, system: NormalEquations) -> np.ndarray:
        """(2,) standard deviations of ``(s, d)`` from the reduced undamped Hessian (NaN where
        not refined, inf where singular)."""
        free = self.free
        S = self.reduced(system)[np.ix_(free, free)]
        dof = max(1, system.count - 5 * len(system.blocks) - int(free.sum()))
        sigma2 = system.wr2 / dof
        try:
            diag = np.diag(sigma2 * np.linalg.inv(S))
        except np.linalg.LinAlgError:
            diag = np.full(int(free.sum()), np.inf)
        out = np.full(2, np.nan)
        out[free] = np.sqrt(np.where(diag > 0, diag, np.inf))
        return out

    def damped_step(self, state: LMState, system: NormalEquations, lam: float) -> LMState | None:
        """The state after one step damped by ``lam``; None when the system is singular or the
        step leaves the camera model's domain (the caller damps more)."""
        try:
            b = system.g_c.copy()
            sols = []
            for H_pp, H_pc, g_p in system.blocks:
                A = H_pp + lam * np.diag(np.diag(H_pp) + 1e-12)
                sol = np.linalg.solve(A, np.stack([g_p, *H_pc.T], axis=1))
                sols.append(sol)
                b -= H_pc.T @ sol[:, 0]
            S = self.reduced(system, lam)
            S = S + lam * np.diag(np.diag(S) + 1e-12)
            dx = np.zeros(2)
            free = self.free
            dx[free] = -np.linalg.solve(S[np.ix_(free, free)], b[free])
        except np.linalg.LinAlgError:
            return None
        poses = []
        for (R, t), sol in zip(state.poses, sols, strict=True):
            dp = -(sol[:, 0] + sol[:, 1:] @ dx)  # dp = -A^-1 (g_p + H_pc dx)
            t_new = t + _tangent_basis(t) @ dp[3:]
            poses.append((_so3_exp(dp[:3]) @ R, t_new / np.linalg.norm(t_new)))
        x = state.x + dx
        try:
            rays = _rays(self.intrinsics.make(x), self.pairs)
        except CameraError:
            return None
        res = self.residuals(rays, poses)
        return LMState(x, poses, rays, res, self.cost(res))

    def solve(
        self, state: LMState, system: NormalEquations, max_iterations: int, tolerance: float
    ) -> tuple[LMState, NormalEquations, int, bool]:
        """Levenberg-Marquardt from ``state``: ``(state, its system, iterations, converged)``."""
        lam, converged, iterations = 1e-3, False, 0
        for _ in range(max_iterations):
            iterations += 1
            improved = False
            for _attempt in range(10):
                candidate = self.damped_step(state, system, lam)
                if candidate is None or not candidate.cost < state.cost:
                    lam *= 10.0
                    continue
                converged = state.cost - candidate.cost < tolerance * max(state.cost, 1e-30)
                state, lam, improved = candidate, max(lam / 10.0, 1e-12), True
                break
            if not improved:
                converged = True  # no damped step lowers the cost: a (local) minimum
                break
            system = self.normal_equations(state)
            if converged:
                break
        return state, system, iterations, converged


def _pose_jacobian(
    R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray, r: np.ndarray
) -> np.ndarray:
    """(M, 5) forward-difference Jacobian of one pair's residuals in its rotation (3) and unit
    translation (2, in the tangent plane)."""
    B = _tangent_basis(t)
    cols = []
    for k in range(5):
        if k < 3:
            R2, t2 = _so3_exp(_EPS_POSE * np.eye(3)[k]) @ R, t
        else:
            R2, t2 = R, t + _EPS_POSE * B[:, k - 3]
            t2 = t2 / np.linalg.norm(t2)
        cols.append((tangent_sampson_error(R2, t2, f1, f2) - r) / _EPS_POSE)
    return np.stack(cols, axis=1)
