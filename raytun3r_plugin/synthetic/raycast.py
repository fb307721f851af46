"""Vectorised ray casting against an analytic :class:`~raytun3r_plugin.synthetic.scene.Scene`.

:func:`intersect` casts rays from one origin: primitives are culled per ray with bounding cones
(one matmul), the remaining (ray, primitive) pairs are intersected in one vectorised pass per
primitive type, and the nearest hit wins (scatter-min). The result is a :class:`Hit` (distance,
normal, material and face per ray); :class:`RayTiles` groups nearby rays for coarser culling.
World frame and primitive layout as in :mod:`raytun3r_plugin.synthetic.scene`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # annotations only: scene.py re-exports this module's names
    from raytun3r_plugin.synthetic.scene import Scene

__all__ = ["Hit", "RayTiles", "intersect"]

_EPS = 1e-4  # minimum hit distance (m)


@dataclass
class Hit:
    """Nearest hits of N rays: ``t`` (N,) distance along the unit ray in metres (inf = miss),
    ``normal`` (N, 3) world-frame unit normal (outward for objects, inward for room and sky),
    ``material`` (N,) long (-1 = miss), ``face`` (N,) long face index within the object."""

    t: torch.Tensor
    normal: torch.Tensor
    material: torch.Tensor
    face: torch.Tensor

    @property
    def hit(self) -> torch.Tensor:
        """(N,) bool: the ray hit something."""
        return torch.isfinite(self.t)


_ROOM, _GROUND, _SKY, _BOX, _SPHERE, _CYL = range(6)


class _Best:
    """Nearest hit so far per ray: distance, primitive type and index within the type."""

    def __init__(self, n: int) -> None:
        self.t = torch.full((n,), math.inf)
        self.kind = torch.full((n,), -1, dtype=torch.long)
        self.prim = torch.zeros(n, dtype=torch.long)

    def fold_all(self, t: torch.Tensor, kind: int) -> None:
        """One candidate per ray (primitives tested against every ray)."""
        win = t < self.t
        self.t = torch.where(win, t, self.t)
        self.kind = torch.where(win, torch.full_like(self.kind, kind), self.kind)
        self.prim = torch.where(win, torch.zeros_like(self.prim), self.prim)

    def fold_pairs(self, ray: torch.Tensor, prim: torch.Tensor, t: torch.Tensor, kind: int) -> None:
        """Candidates for (ray, primitive) pairs; the nearest per ray wins (scatter-min)."""
        ok = t < self.t[ray]
        if not bool(ok.any()):
            return
        ray, prim, t = ray[ok], prim[ok], t[ok]
        cur = self.t.clone()
        cur.scatter_reduce_(0, ray, t, reduce="amin")
        win = t <= cur[ray]  # ties: any of the tied candidates is a correct winner
        r = ray[win]
        self.t[r] = t[win]
        self.kind[r] = kind
        self.prim[r] = prim[win]


@dataclass
class RayTiles:
    """Groups of nearby rays for coarse culling: ``axes`` (T, 3) unit axis of each group (same
    frame as the rays), ``radius`` (T,) its angular radius (radians, every member ray lies within
    it), ``members`` (T, S) indices into the ray array, -1 = padding."""

    axes: torch.Tensor
    radius: torch.Tensor
    members: torch.Tensor

    def rotated(self, R: torch.Tensor) -> RayTiles:
        """The tiles with axes mapped like the rays, ``axes @ R`` (row vectors)."""
        return RayTiles(self.axes @ R, self.radius, self.members)


def _bounding_cones(centres: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit axis (K, 3) and angular radius (K,) (pi when the origin is inside) of the cones from
    the origin around bounding spheres (centres relative to the origin)."""
    dist = np.linalg.norm(centres, axis=1)
    inside = dist <= radii * 1.001 + 1e-6
    ang = np.arcsin(np.clip(radii / np.maximum(dist, 1e-9), 0.0, 1.0)) + 1e-4
    ang[inside] = math.pi
    axis = centres / np.maximum(dist, 1e-9)[:, None]
    return axis, ang


def _cone_pairs(
    dirs: torch.Tensor, centres: np.ndarray, radii: np.ndarray, tiles: RayTiles | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ray, primitive) index pairs whose ray may hit the bounding sphere of the primitive, and
    the gathered ray directions of the pairs. With ``tiles``, whole tiles are culled first."""
    e = torch.zeros(0, dtype=torch.long)
    if centres.shape[0] == 0 or dirs.shape[0] == 0:
        return e, e, torch.zeros(0, 3)
    axis_np, ang_np = _bounding_cones(centres, radii)
    axis = _f32(axis_np)
    cos_th = _f32(np.where(ang_np >= math.pi, -2.0, np.cos(np.minimum(ang_np, math.pi))))
    if tiles is None:
        mask = (dirs @ axis.t()) >= cos_th
        r, k = mask.nonzero(as_tuple=True)
        return r, k, dirs[r]
    # tile level: the angle between the axes must not exceed the sum of the radii
    cos_tk = (tiles.axes @ axis.t()).clamp(-1.0, 1.0)
    reach = tiles.radius[:, None] + _f32(ang_np)[None, :]
    ti, k = (cos_tk >= torch.cos(reach.clamp(max=math.pi))).nonzero(as_tuple=True)
    s = tiles.members.shape[1]
    r = tiles.members[ti].reshape(-1)
    k = k.repeat_interleave(s)
    real = r >= 0
    r, k = r[real], k[real]
    d = dirs[r]
    ok = (d * axis[k]).sum(-1) >= cos_th[k]
    return r[ok], k[ok], d[ok]


def _f32(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def _box_table(scene: Scene, origin: np.ndarray) -> torch.Tensor:
    """Per box (K, 11): cos, sin of yaw, origin in the box frame (3), -h - o_l (3), h - o_l (3)."""
    b = scene.boxes
    cs, sn = np.cos(b[:, 6]), np.sin(b[:, 6])
    c = b[:, :3] - origin
    # world_from_box = R_y(yaw) = [[c, 0, s], [0, 1, 0], [-s, 0, c]]; local = R^T world.
    ol = -np.stack([cs * c[:, 0] - sn * c[:, 2], c[:, 1], sn * c[:, 0] + cs * c[:, 2]], -1)
    h = b[:, 3:6]
    return _f32(np.concatenate([cs[:, None], sn[:, None], ol, -h - ol, h - ol], axis=1))


def _to_box(tab: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    cs, sn = tab[:, 0], tab[:, 1]
    return torch.stack([cs * d[:, 0] - sn * d[:, 2], d[:, 1], sn * d[:, 0] + cs * d[:, 2]], -1)


def _box_t(tab: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    inv = 1.0 / _to_box(tab, d)
    t1 = tab[:, 5:8] * inv
    t2 = tab[:, 8:11] * inv
    tn = torch.minimum(t1, t2).amax(dim=1)
    tf = torch.maximum(t1, t2).amin(dim=1)
    ok = (tf >= tn) & (tn > _EPS)
    return torch.where(ok, tn, torch.full_like(tn, math.inf))


def _box_normal(
    tab: torch.Tensor, d: torch.Tensor, t: torch.Tensor, half: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    pl = tab[:, 2:5] + t[:, None] * _to_box(tab, d)  # hit point in the box frame
    axis = (pl.abs() / half).argmax(dim=1)
    sgn = torch.sign(pl.gather(1, axis[:, None]).squeeze(1))
    nl = torch.zeros_like(pl)
    nl.scatter_(1, axis[:, None], sgn[:, None])
    cs, sn = tab[:, 0], tab[:, 1]
    n = torch.stack([cs * nl[:, 0] + sn * nl[:, 2], nl[:, 1], -sn * nl[:, 0] + cs * nl[:, 2]], -1)
    return n, 2 * axis + (sgn > 0).long()


def _sphere_t(p: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    c, rad = p[:, :3], p[:, 3]
    b = (d * c).sum(-1)
    c2 = (c * c).sum(-1) - rad * rad
    disc = b * b - c2
    t0 = b - torch.sqrt(torch.clamp(disc, min=0.0))
    ok = (disc >= 0) & (t0 > _EPS) & (c2 > 0)
    return torch.where(ok, t0, torch.full_like(t0, math.inf))


def _cyl_table(scene: Scene, origin: np.ndarray) -> torch.Tensor:
    """Per cylinder (K, 5) relative to the origin: axis x, axis z, y_top, y_bottom, radius."""
    c = scene.cylinders
    rel = np.stack(
        [
            c[:, 0] - origin[0],
            c[:, 1] - origin[2],
            c[:, 2] - origin[1],
            c[:, 3] - origin[1],
            c[:, 4],
        ],
        -1,
    )
    return _f32(rel)


def _cyl_t(p: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    cx, cz, y0, y1, rad = p.unbind(-1)
    dx, dy, dz = d.unbind(-1)
    a = dx * dx + dz * dz
    b = -(cx * dx + cz * dz)
    cc = cx * cx + cz * cz - rad * rad
    disc = b * b - a * cc
    ts = (-b - torch.sqrt(torch.clamp(disc, min=0.0))) / torch.clamp(a, min=1e-12)
    ys = ts * dy
    side = (disc >= 0) & (a > 1e-12) & (ts > _EPS) & (ys >= y0) & (ys <= y1) & (cc > 0)
    inf = torch.full_like(ts, math.inf)
    t = torch.where(side, ts, inf)
    inv_dy = 1.0 / dy
    r2 = rad * rad
    for yc in (y0, y1):
        tc = yc * inv_dy
        px = tc * dx - cx
        pz = tc * dz - cz
        okc = (tc > _EPS) & (px * px + pz * pz <= r2)
        t = torch.minimum(t, torch.where(okc, tc, inf))
    return t


def _cyl_normal(
    p: torch.Tensor, d: torch.Tensor, t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    cx, cz, y0, y1, rad = p.unbind(-1)
    px = t * d[:, 0] - cx
    py = t * d[:, 1]
    pz = t * d[:, 2] - cz
    dist = torch.stack(
        [(torch.sqrt(px * px + pz * pz) - rad).abs(), (py - y0).abs(), (py - y1).abs()], -1
    )
    face = dist.argmin(dim=1)
    zero = torch.zeros_like(px)
    n_side = torch.stack([px / rad, zero, pz / rad], -1)
    n_top = torch.stack([zero, -torch.ones_like(px), zero], -1)
    n = torch.where((face == 0)[:, None], n_side, torch.where((face == 1)[:, None], n_top, -n_top))
    return n, face


def _room_t(scene: Scene, origin: np.ndarray, dirs: torch.Tensor) -> torch.Tensor:
    lo = _f32(scene.room[:3] - origin)
    hi = _f32(scene.room[3:] - origin)
    ta = torch.where(dirs > 0, hi, lo) / dirs
    t = torch.where(dirs == 0, math.inf, ta).amin(dim=1)  # exit distance
    return torch.where(t > _EPS, t, torch.full_like(t, math.inf))


def _sky_t(scene: Scene, origin: np.ndarray, dirs: torch.Tensor) -> torch.Tensor:
    # float64: the sky is ~2 km away and float32 would cost millimetres of consistency.
    c = torch.from_numpy(scene.sky[:3] - origin)
    rad = float(scene.sky[3])
    b = dirs.double() @ c
    disc = b * b - (float((c * c).sum()) - rad * rad)
    t = b + torch.sqrt(torch.clamp(disc, min=0.0))
    return torch.where((disc >= 0) & (t > _EPS), t, torch.full_like(t, math.inf)).float()


def intersect(
    scene: Scene, origin: np.ndarray, dirs: torch.Tensor, tiles: RayTiles | None = None
) -> Hit:
    """Nearest hit of rays from one world-frame ``origin`` (3,) along unit ``dirs`` (N, 3).

    Distances are float32 metres along the ray. Rays are cast relative to the origin, so far-away
    cameras keep full float32 precision. Normals, materials and faces are computed for the
    winning primitive of each ray only. ``tiles`` (optional, world frame, indexing ``dirs``)
    groups nearby rays for faster culling; the result does not depend on it.
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    dirs = dirs.to(torch.float32).contiguous()
    n = dirs.shape[0]
    best = _Best(n)
    if scene.room is not None:
        best.fold_all(_room_t(scene, origin, dirs), _ROOM)
    if scene.ground and origin[1] < 0:
        dy = dirs[:, 1]
        t = torch.where(dy > 1e-9, float(-origin[1]) / dy, torch.full_like(dy, math.inf))
        best.fold_all(t, _GROUND)
    nb, ns, nc = scene.boxes.shape[0], scene.spheres.shape[0], scene.cylinders.shape[0]
    boxes = _box_table(scene, origin) if nb else None
    spheres = (
        _f32(np.concatenate([scene.spheres[:, :3] - origin, scene.spheres[:, 3:]], 1))
        if ns
        else None
    )
    cyls = _cyl_table(scene, origin) if nc else None
    if nb + ns + nc:
        cyl = scene.cylinders
        centres = (
            np.concatenate(
                [
                    scene.boxes[:, :3],
                    scene.spheres[:, :3],
                    np.stack([cyl[:, 0], 0.5 * (cyl[:, 2] + cyl[:, 3]), cyl[:, 1]], -1),
                ]
            )
            - origin
        )
        radii = np.concatenate(
            [
                np.linalg.norm(scene.boxes[:, 3:6], axis=1),
                scene.spheres[:, 3],
                np.sqrt(cyl[:, 4] ** 2 + (0.5 * (cyl[:, 3] - cyl[:, 2])) ** 2),
            ]
        )
        r, k, dr = _cone_pairs(dirs, centres, radii, tiles)
        for kind, lo, hi, tab, fn in (
            (_BOX, 0, nb, boxes, _box_t),
            (_SPHERE, nb, nb + ns, spheres, _sphere_t),
            (_CYL, nb + ns, nb + ns + nc, cyls, _cyl_t),
        ):
            if hi == lo:
                continue
            sel = (k >= lo) & (k < hi) if (lo > 0 or hi < nb + ns + nc) else None
            rr, kk, dd = (r, k - lo, dr) if sel is None else (r[sel], k[sel] - lo, dr[sel])
            if rr.numel():
                best.fold_pairs(rr, kk, fn(tab[kk], dd), kind)
    if scene.sky is not None:
        miss = torch.isinf(best.t).nonzero().squeeze(1)
        if miss.numel():
            t = _sky_t(scene, origin, dirs[miss])
            best.t[miss] = t
            best.kind[miss] = torch.where(torch.isfinite(t), _SKY, -1)
            best.prim[miss] = 0
    return _finish(scene, origin, dirs, best, boxes, spheres, cyls)


def _finish(scene, origin, dirs, best, boxes, spheres, cyls) -> Hit:
    n = dirs.shape[0]
    normal = torch.zeros(n, 3)
    material = torch.full((n,), -1, dtype=torch.long)
    face = torch.zeros(n, dtype=torch.long)
    t_all = best.t
    for kind in torch.unique(best.kind).tolist():
        if kind < 0:
            continue
        sel = (best.kind == kind).nonzero().squeeze(1)
        d, t, k = dirs[sel], t_all[sel], best.prim[sel]
        if kind == _ROOM:
            p = t[:, None] * d
            lo = _f32(scene.room[:3] - origin)
            hi = _f32(scene.room[3:] - origin)
            gap = torch.stack([(p - lo).abs(), (p - hi).abs()], -1).reshape(
                -1, 6
            )  # -x,+x,-y,+y,-z,+z
            f = gap.argmin(dim=1)
            nl = torch.zeros_like(d)
            nl.scatter_(1, (f // 2)[:, None], (1.0 - 2.0 * (f % 2)).to(d.dtype)[:, None])
            nrm, mat = nl, torch.from_numpy(scene.room_materials.astype(np.int64))[f]
        elif kind == _GROUND:
            pave = ((origin[0] + t * d[:, 0]).abs() >= scene.road_half_width).long()
            nrm = torch.zeros_like(d)
            nrm[:, 1] = -1.0
            f = pave
            mat = torch.from_numpy(scene.ground_materials.astype(np.int64))[pave]
        elif kind == _SKY:
            c = _f32(scene.sky[:3] - origin)
            nrm = -(t[:, None] * d - c) / float(scene.sky[3])
            f = torch.zeros_like(k)
            mat = torch.full_like(k, scene.sky_material)
        elif kind == _BOX:
            nrm, f = _box_normal(boxes[k], d, t, _f32(scene.boxes[:, 3:6])[k])
            mat = torch.from_numpy(scene.box_materials.astype(np.int64))[k]
        elif kind == _SPHERE:
            sp = spheres[k]
            nrm = (t[:, None] * d - sp[:, :3]) / sp[:, 3:4]
            f = torch.zeros_like(k)
            mat = torch.from_numpy(scene.sphere_materials.astype(np.int64))[k]
        else:
            nrm, f = _cyl_normal(cyls[k], d, t)
            mat = torch.from_numpy(scene.cylinder_materials.astype(np.int64))[k]
        normal[sel] = nrm
        material[sel] = mat
        face[sel] = f
    return Hit(t=t_all, normal=normal, material=material, face=face)
