"""Smooth synthetic camera trajectories, returned as ``cam_from_world`` (N, 4, 4) float64.

World frame as in :mod:`raytun3r_plugin.synthetic.scene` (metres, y down, floor at y = 0).
Camera orientation is ``world_from_cam = R_y(yaw) @ R_x(pitch) @ R_z(roll)``: yaw turns the
optical axis (+z) towards +x, positive pitch looks up (towards -y), roll turns about the optical
axis. All motion components are sums of sinusoids with random frequencies and phases, so the
trajectories are smooth (C-infinity) and deterministic for a seed.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "calibrate_step",
    "driving_trajectory",
    "frame_motion",
    "handheld_trajectory",
    "pose_from_position_angles",
]


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _rot_y(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def pose_from_position_angles(
    position: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray
) -> np.ndarray:
    """``cam_from_world`` (N, 4, 4) from camera centres (N, 3) and yaw/pitch/roll (N,) radians."""
    R = _rot_y(yaw) @ _rot_x(pitch) @ _rot_z(roll)  # world_from_cam; R_x(+a) tilts +z to -y (up)
    n = R.shape[0]
    T = np.zeros((n, 4, 4))
    Rt = np.transpose(R, (0, 2, 1))
    T[:, :3, :3] = Rt
    T[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, position)
    T[:, 3, 3] = 1.0
    return T


def _sines(
    rng: np.random.Generator,
    t: np.ndarray,
    amplitude: float,
    omega: tuple[float, float],
    n: int = 3,
) -> np.ndarray:
    """Sum of ``n`` sinusoids with total amplitude ``amplitude`` and random angular frequencies
    in ``omega`` (rad per time unit), weights 1, 1/2, 1/4, ... (normalised)."""
    w = 0.5 ** np.arange(n)
    w = w / w.sum()
    out = np.zeros_like(t)
    for k in range(n):
        om = rng.uniform(*omega) * (1.0 + 0.9 * k)
        out += amplitude * w[k] * np.sin(om * t + rng.uniform(0, 2 * math.pi))
    return out


def handheld_trajectory(
    n_frames: int,
    seed: int,
    step: float = 1.0,
    center: tuple[float, float, float] = (0.0, -1.5, 0.0),
    amplitude: tuple[float, float, float] = (1.2, 0.2, 1.5),
    yaw_deg: float = 55.0,
    pitch_deg: float = 10.0,
    roll_deg: float = 5.0,
) -> np.ndarray:
    """Hand-held motion: the camera wanders around ``center`` (metres) within ``amplitude`` per
    axis while looking around (yaw within +-``yaw_deg`` of a random heading, pitch and roll
    within +-``pitch_deg``/``roll_deg``). Frame k is at time ``k * step``.

    Returns ``cam_from_world`` (n_frames, 4, 4) float64.
    """
    rng = np.random.default_rng([int(seed), 11])
    t = np.arange(n_frames, dtype=np.float64) * step
    pos = np.stack(
        [center[i] + _sines(rng, t, amplitude[i], (0.25, 0.45)) for i in range(3)], axis=-1
    )
    heading = rng.uniform(-math.pi, math.pi)
    yaw = heading + _sines(rng, t, math.radians(yaw_deg), (0.2, 0.4))
    pitch = _sines(rng, t, math.radians(pitch_deg), (0.3, 0.6))
    roll = _sines(rng, t, math.radians(roll_deg), (0.3, 0.6))
    return pose_from_position_angles(pos, yaw, pitch, roll)


def driving_trajectory(
    n_frames: int,
    seed: int,
    step: float = 1.0,
    start: tuple[float, float, float] = (2.0, -1.6, 0.0),
    heading_deg: float = 3.0,
    mount_yaw_deg: float = 0.0,
    mount_pitch_deg: float = 0.0,
) -> np.ndarray:
    """Driving motion along +z at 1 m per time unit (frame k at time ``k * step``, so ``step`` is
    metres per frame), heading swaying gently within +-``heading_deg``, a small pitch/roll
    wobble (+-0.5/0.3 degrees) and a camera mounted at ``mount_yaw_deg`` from the driving
    direction (90 = looking right) and ``mount_pitch_deg`` (positive up).

    Returns ``cam_from_world`` (n_frames, 4, 4) float64.
    """
    rng = np.random.default_rng([int(seed), 12])
    sub = 16
    n_fine = max(1, (n_frames - 1) * sub + 1)
    tf = np.arange(n_fine, dtype=np.float64) * (step / sub)
    psi = _sines(rng, tf, math.radians(heading_deg), (0.03, 0.08))
    vx, vz = np.sin(psi), np.cos(psi)
    dt = step / sub
    x = start[0] + np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * dt)])
    z = start[2] + np.concatenate([[0.0], np.cumsum(0.5 * (vz[1:] + vz[:-1]) * dt)])
    idx = np.arange(n_frames) * sub
    t = tf[idx]
    y = start[1] + _sines(rng, t, 0.01, (1.0, 2.0))
    pos = np.stack([x[idx], y, z[idx]], -1)
    yaw = psi[idx] + math.radians(mount_yaw_deg)
    pitch = math.radians(mount_pitch_deg) + _sines(rng, t, math.radians(0.5), (0.5, 1.0))
    roll = _sines(rng, t, math.radians(0.3), (0.5, 1.0))
    return pose_from_position_angles(pos, yaw, pitch, roll)


def frame_motion(cam_from_world: np.ndarray, depth_scale: float) -> np.ndarray:
    """Apparent motion between consecutive frames (N-1,) in radians: rotation angle plus camera
    displacement divided by a typical scene depth ``depth_scale`` (metres)."""
    R = cam_from_world[:, :3, :3]
    C = -np.einsum("nji,nj->ni", R, cam_from_world[:, :3, 3])
    dR = np.einsum("nij,nkj->nik", R[1:], R[:-1])
    cos = np.clip((np.trace(dR, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(cos) + np.linalg.norm(C[1:] - C[:-1], axis=1) / depth_scale


def calibrate_step(make, n_frames: int, measure, target: float, iterations: int = 3) -> float:
    """Time step such that ``measure(make(n, step))`` (the median apparent motion between
    consecutive frames, e.g. in pixels) is about ``target``; motion is close to linear in the
    step for smooth trajectories, so a few fixed-point rescalings converge."""
    n = max(int(n_frames), 8)
    step = 1.0
    for _ in range(iterations):
        med = float(measure(make(n, step)))
        if not np.isfinite(med) or med <= 0:
            return step
        step *= target / med
    return step
