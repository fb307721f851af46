"""Analytic ray-cast rendering of procedural scenes through any raytun3r camera model.

Per frame the renderer casts one ray per pixel centre (the camera's ``ray_table``, so fields of
view beyond 180 degrees work) and returns:

* ``rgb`` (H, W, 3) float32 in [0, 1], anti-aliased, black outside the valid region;
* ``range`` (H, W) float32 metres along the unit ray of the pixel centre (0 = invalid);
* ``z_depth`` (H, W) float32 = range * ray_z (0 where invalid or ray_z <= 0);
* ``valid`` (H, W) bool = lens valid & hit;
* ``cam_from_world`` (4, 4) float64.

Anti-aliasing: texture detail is pre-filtered (each noise octave fades to its mean where a
sample's footprint on the surface exceeds half its cell size); geometry is supersampled with
``supersample`` x ``supersample`` sub-pixel rays (``camera.unproject`` at offsets
((i + 0.5) / s - 0.5) px). With ``adaptive=True`` (default) only pixels on a silhouette, a face
change, a depth jump or the lens border are supersampled; ``adaptive=False`` supersamples every
pixel. Depth is always the exact value at the pixel centre, so ground-truth correspondences are
exact.

Shading is Lambertian (directional light + ambient), hence view-independent: a surface point
has the same colour in every frame.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from raytun3r_plugin.errors import InputError
from raytun3r_plugin.synthetic.noise import SolidNoise, band_weight, smoothstep
from raytun3r_plugin.synthetic.raycast import Hit, RayTiles, intersect
from raytun3r_plugin.synthetic.scene import (
    MAT_BASE,
    MAT_COLOUR_VAR,
    MAT_CONTRAST,
    MAT_EMISSIVE,
    MAT_FREQ,
    MAT_OFFSET,
    MAT_SPOT,
    MAT_SPOT_THRESHOLD,
    Scene,
)
from raytun3r_plugin.threads import torch_threads

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

__all__ = ["RenderedFrame", "Renderer", "render_frame"]

_OCTAVE_GAIN = (0.32, 0.26, 0.2, 0.13, 0.09)


@dataclass
class RenderedFrame:
    """One rendered frame; see the module docstring for units. ``material`` (H, W) int32 is the
    object/material id per pixel (-1 = invalid), ``sky`` (H, W) bool marks sky pixels."""

    rgb: np.ndarray
    range: np.ndarray
    z_depth: np.ndarray
    valid: np.ndarray
    cam_from_world: np.ndarray
    material: np.ndarray
    sky: np.ndarray


class _CameraRays:
    """Per-camera cached rays: centre rays, sub-pixel rays and angular pixel size."""

    def __init__(self, camera: Camera, supersample: int) -> None:
        h, w = int(camera.height), int(camera.width)
        # float64 table (the camera's authoritative validity, as valid_mask()), float32 rays
        rays, valid = camera.ray_table(dtype=torch.float64)
        rays, valid = rays.detach().to(torch.float32), valid.detach().to(torch.bool)
        valid = valid & torch.isfinite(rays).all(-1)
        self.height, self.width = h, w
        self.rays = rays.reshape(-1, 3).contiguous()
        self.valid = valid.reshape(-1)
        vv, uu = torch.meshgrid(
            torch.arange(h, dtype=torch.float64),
            torch.arange(w, dtype=torch.float64),
            indexing="ij",
        )
        uv = torch.stack([uu, vv], -1).reshape(-1, 2)

        def unproject(offset: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
            shifted = uv + torch.tensor(offset, dtype=torch.float64)
            r, ok = camera.unproject(shifted.to(torch.float32))
            r = r.reshape(-1, 3).to(torch.float32)
            ok = ok.reshape(-1).to(torch.bool) & torch.isfinite(r).all(-1)
            r = torch.where(ok[:, None], r, torch.zeros_like(r))
            return r, ok

        # Angular size of a pixel (radians): the larger of the horizontal and vertical angles to
        # the neighbouring pixel centres (the larger side where both neighbours are valid).
        self.pixel_angle = self._pixel_angle(rays, valid)
        s = int(supersample)
        self.supersample = s
        offs = [(i + 0.5) / s - 0.5 for i in range(s)]
        sub_r, sub_ok = [], []
        for dv in offs:
            for du in offs:
                r, ok = unproject((du, dv))
                sub_r.append(r)
                sub_ok.append(ok)
        self.sub_rays = torch.stack(sub_r)  # (S, HW, 3)
        self.sub_valid = torch.stack(sub_ok)  # (S, HW)
        self.index = self.valid.nonzero().squeeze(1)  # valid pixels (the rays cast per frame)
        self.tiles = self._tiles(16)

    @staticmethod
    def _pixel_angle(rays: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        h, w = valid.shape
        ang = torch.zeros(h, w)
        for dim in (0, 1):
            n = rays.shape[dim]
            if n < 2:
                continue
            a, b = rays.narrow(dim, 0, n - 1), rays.narrow(dim, 1, n - 1)
            step = (b - a).norm(dim=-1)
            ok = valid.narrow(dim, 0, n - 1) & valid.narrow(dim, 1, n - 1)
            step = torch.where(ok, step, torch.zeros_like(step))
            pad_shape = list(step.shape)
            pad_shape[dim] = 1
            zero = torch.zeros(pad_shape)
            before = torch.cat([zero, step], dim=dim)  # step to the previous pixel
            after = torch.cat([step, zero], dim=dim)  # step to the next pixel
            ang = torch.maximum(ang, torch.maximum(before, after))
        known = valid & (ang > 0)
        fallback = float(ang[known].median()) if bool(known.any()) else 1e-2
        return torch.where(known, ang, torch.full_like(ang, fallback)).reshape(-1)

    def _tiles(self, size: int) -> RayTiles:
        """Square pixel tiles of the valid rays (members index ``self.index``), for culling."""
        h, w = self.height, self.width
        pos = torch.full((h * w,), -1, dtype=torch.long)
        pos[self.index] = torch.arange(self.index.numel())
        th, tw = -(-h // size), -(-w // size)
        grid = torch.full((th * size, tw * size), -1, dtype=torch.long)
        grid[:h, :w] = pos.view(h, w)
        members = grid.view(th, size, tw, size).permute(0, 2, 1, 3).reshape(th * tw, size * size)
        members = members[(members >= 0).any(dim=1)]
        if members.shape[0] == 0:
            return RayTiles(torch.zeros(0, 3), torch.zeros(0), members)
        rays = self.rays[self.index].double()
        m = rays[members.clamp(min=0)]  # (T, S, 3); padding reads ray 0, masked below
        real = (members >= 0)[..., None]
        axes = (m * real).sum(1)
        axes = axes / axes.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        cos = ((m * axes[:, None, :]).sum(-1)).clamp(-1.0, 1.0)
        cos = torch.where(real[..., 0], cos, torch.ones_like(cos))
        radius = torch.arccos(cos.min(dim=1).values) + 1e-4
        return RayTiles(axes.float(), radius.float(), members)


_RAY_CACHE: OrderedDict[tuple, _CameraRays] = OrderedDict()
_RAY_CACHE_SIZE = 4


def _camera_rays(camera: Camera, supersample: int) -> _CameraRays:
    """Cached :class:`_CameraRays` per (camera, supersample); cameras are immutable and hashable
    (a few most recent ones are kept)."""
    try:
        key = (camera.key(), supersample)
    except (AttributeError, TypeError):
        return _CameraRays(camera, supersample)
    hit = _RAY_CACHE.get(key)
    if hit is None:
        hit = _CameraRays(camera, supersample)
        _RAY_CACHE[key] = hit
        while len(_RAY_CACHE) > _RAY_CACHE_SIZE:
            _RAY_CACHE.popitem(last=False)
    else:
        _RAY_CACHE.move_to_end(key)
    return hit


class Renderer:
    """Renders scenes through one camera; caches the camera's rays between frames.

    Args:
        camera: any ``raytun3r_plugin.cameras`` model.
        supersample: sub-pixel rays per axis for anti-aliasing (1 disables supersampling).
        adaptive: supersample only edge pixels (fast, default) or every pixel.
        num_threads: torch intra-op threads while rendering (set process-wide for the duration
            of a call and restored). Default 1: the work is many short memory-bound ops, and on a
            shared, loaded CPU OpenMP barriers make 2 threads up to 10x slower than 1. ``None``
            keeps torch's setting.
    """

    def __init__(
        self,
        camera: Camera,
        supersample: int = 2,
        adaptive: bool = True,
        num_threads: int | None = 1,
    ) -> None:
        if supersample < 1:
            raise InputError("supersample must be >= 1")
        self.camera = camera
        self.adaptive = adaptive
        self.num_threads = num_threads
        with torch_threads(num_threads):
            self._rays = _camera_rays(camera, int(supersample))
        self._noise: dict[int, SolidNoise] = {}

    def _noise_for(self, scene: Scene) -> SolidNoise:
        key = int(scene.seed)
        if key not in self._noise:
            self._noise[key] = SolidNoise(seed=key * 7 + 3)
        return self._noise[key]

    # ------------------------------------------------------------------------------------
    def _colour(
        self,
        scene: Scene,
        origin: np.ndarray,
        dirs: torch.Tensor,
        hit: Hit,
        pixel_angle: torch.Tensor,
    ) -> torch.Tensor:
        """Shaded colour (N, 3) of hits (all entries of ``hit`` must be finite)."""
        n = dirs.shape[0]
        if n == 0:
            return torch.zeros(0, 3)
        noise = self._noise_for(scene)
        mt = torch.from_numpy(scene.materials)[hit.material]  # (N, MAT_DIM)
        t = hit.t
        org = torch.from_numpy(np.asarray(origin, dtype=np.float32))
        pos = org + t[:, None] * dirs  # world position (m)
        cos_inc = (hit.normal * dirs).sum(-1).abs().clamp(min=0.25)
        footprint = t * pixel_angle / cos_inc  # metres per sample on the surface
        freq = mt[:, MAT_FREQ]
        octs = noise.octave_stack(pos * freq[:, None], offset=mt[:, MAT_OFFSET])  # (O, N, 4)
        # band-limiting weight of each octave (O, N), see noise.band_weight
        fq = torch.tensor(noise.frequencies, dtype=torch.float32)[:, None]
        w = band_weight(fq, (footprint * freq)[None, :])
        c0 = (octs[0, :, :3] - 0.5) * (0.65 * w[0])[:, None]
        c1 = (octs[1, :, :3] - 0.5) * (0.35 * w[1])[:, None]
        gain = torch.tensor(_OCTAVE_GAIN[: noise.octaves], dtype=torch.float32)[:, None]
        lum = ((octs[..., 3] - 0.5) * (w * gain)).sum(0)
        # Crisp spots (blobs with sharp edges) from two octaves; their edge width grows with the
        # footprint so they stay anti-aliased.
        f1, f2 = noise.frequencies[1], noise.frequencies[2]
        thr = mt[:, MAT_SPOT_THRESHOLD]
        sw1 = 0.02 + 0.6 * footprint * freq * f1
        sw2 = 0.02 + 0.6 * footprint * freq * f2
        spot = torch.maximum(
            smoothstep(thr - sw1, thr + sw1, octs[1, :, 1]),
            smoothstep(thr + 0.05 - sw2, thr + 0.05 + sw2, octs[2, :, 2]),
        )[:, None]
        base = mt[:, MAT_BASE]
        factor = (1.0 + 2.0 * mt[:, MAT_COLOUR_VAR, None] * (c0 + c1)) * (
            1.0 + 2.0 * mt[:, MAT_CONTRAST, None] * lum[:, None]
        )
        albedo = torch.lerp(base * factor, mt[:, MAT_SPOT], 0.85 * spot)
        light = torch.from_numpy(np.asarray(scene.light_dir, dtype=np.float32))
        diffuse = (-(hit.normal @ light)).clamp(min=0.0)
        shade = scene.ambient + (1.0 - scene.ambient) * diffuse
        rgb = albedo * shade[:, None]
        emissive = (mt[:, MAT_EMISSIVE] > 0.5).nonzero().squeeze(1)
        if emissive.numel() and scene.sky is not None:
            e = emissive
            ve = 0.5 + w[:3, e, None] * (octs[:3, e] - 0.5)  # band-limited octaves 0..2 (3, M, 4)
            sky_c = torch.from_numpy(scene.sky[:3].astype(np.float32))
            dirn = (pos[e] - sky_c) / float(scene.sky[3])
            elev = (-dirn[:, 1]).clamp(min=-1.0, max=1.0)
            horizon = torch.tensor([0.93, 0.94, 0.96])
            sky = horizon + (base[e] - horizon) * smoothstep(0.0, 0.5, elev)[:, None]
            cloud = smoothstep(0.45, 0.7, 0.6 * ve[0, :, 3] + 0.4 * ve[1, :, 3] + 0.35 * lum[e])
            sky = sky + (torch.tensor([0.97, 0.97, 0.98]) - sky) * cloud[:, None] * 0.9
            sky = sky * (0.92 + 0.25 * (ve[2, :, :3] - 0.5))
            rgb[e] = sky
        return rgb.clamp(0.0, 1.0)

    # ------------------------------------------------------------------------------------
    def render(self, scene: Scene, cam_from_world: np.ndarray) -> RenderedFrame:
        """Render ``scene`` from the pose ``cam_from_world`` (4, 4) (world-to-camera)."""
        with torch_threads(self.num_threads):
            return self._render(scene, cam_from_world)

    def _render(self, scene: Scene, cam_from_world: np.ndarray) -> RenderedFrame:
        T = np.asarray(cam_from_world, dtype=np.float64)
        R = T[:3, :3]
        origin = -R.T @ T[:3, 3]
        Rcw = torch.from_numpy(R.astype(np.float32))  # d_world = d_cam @ R_cw (row vectors)
        cr = self._rays
        h, w = cr.height, cr.width
        npx = h * w
        lens = cr.valid
        idx = cr.index
        dirs = cr.rays[idx] @ Rcw
        hit = intersect(scene, origin, dirs, cr.tiles.rotated(Rcw))
        ok = hit.hit
        t_full = torch.zeros(npx)
        t_full[idx[ok]] = hit.t[ok]
        valid = torch.zeros(npx, dtype=torch.bool)
        valid[idx[ok]] = True
        mat_full = torch.full((npx,), -1, dtype=torch.long)
        mat_full[idx[ok]] = hit.material[ok]
        face_full = torch.zeros(npx, dtype=torch.long)
        face_full[idx[ok]] = hit.face[ok]
        rgb = torch.zeros(npx, 3)
        s = cr.supersample
        if s == 1 or self.adaptive:
            good = idx[ok]
            sub = Hit(hit.t[ok], hit.normal[ok], hit.material[ok], hit.face[ok])
            rgb[good] = self._colour(scene, origin, dirs[ok], sub, cr.pixel_angle[good])
        if s > 1:
            if self.adaptive:
                sel = self._edges(valid, lens, mat_full * 8 + face_full, t_full)
            else:
                sel = lens.clone()
            sel_idx = sel.nonzero().squeeze(1)
            if sel_idx.numel() > 0:
                rgb[sel_idx] = self._supersampled(scene, origin, Rcw, sel_idx)
        rgb = torch.where(valid[:, None], rgb, torch.zeros_like(rgb))
        rz = cr.rays[:, 2]
        z = torch.where(valid & (rz > 0), t_full * rz, torch.zeros_like(t_full))
        sky = (
            (mat_full == scene.sky_material) & valid
            if scene.sky is not None
            else torch.zeros_like(valid)
        )
        return RenderedFrame(
            rgb=rgb.reshape(h, w, 3).numpy().astype(np.float32),
            range=t_full.reshape(h, w).numpy().astype(np.float32),
            z_depth=z.reshape(h, w).numpy().astype(np.float32),
            valid=valid.reshape(h, w).numpy(),
            cam_from_world=T.copy(),
            material=mat_full.reshape(h, w).numpy().astype(np.int32),
            sky=sky.reshape(h, w).numpy(),
        )

    def _edges(
        self, valid: torch.Tensor, lens: torch.Tensor, surface: torch.Tensor, t: torch.Tensor
    ) -> torch.Tensor:
        """Pixels (HW,) bool to supersample: a lens pixel whose 8-neighbourhood shows another
        surface (object or face), an invalid pixel, or a depth jump of more than 5%."""
        h, w = self._rays.height, self._rays.width
        sid = torch.where(valid, surface, torch.full_like(surface, -1)).reshape(1, 1, h, w).double()
        tt = torch.where(valid, t, torch.zeros_like(t)).reshape(1, 1, h, w).double()
        # max/min filters over 3x3 of the id (ids differ <=> max != min) and of the depth.
        smax = F.max_pool2d(F.pad(sid, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        smin = -F.max_pool2d(F.pad(-sid, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        tmax = F.max_pool2d(F.pad(tt, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        tmin = -F.max_pool2d(F.pad(-tt, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        edge = (smax != smin) | (tmax - tmin > 0.05 * tmin.clamp(min=1e-6))
        return edge.reshape(-1) & lens

    def _supersampled(
        self, scene: Scene, origin: np.ndarray, Rcw: torch.Tensor, sel: torch.Tensor
    ) -> torch.Tensor:
        """Mean colour (len(sel), 3) of the sub-pixel rays of pixels ``sel`` (lens-valid ones)."""
        cr = self._rays
        S = cr.sub_rays.shape[0]
        rays = cr.sub_rays[:, sel].reshape(-1, 3)
        okv = cr.sub_valid[:, sel].reshape(-1)
        ang = (cr.pixel_angle[sel] / cr.supersample).repeat(S)
        cols = torch.zeros(rays.shape[0], 3)
        use = okv.nonzero().squeeze(1)
        dirs = rays[use] @ Rcw
        hit = intersect(scene, origin, dirs)
        good = hit.hit
        sub = Hit(hit.t[good], hit.normal[good], hit.material[good], hit.face[good])
        cols[use[good]] = self._colour(scene, origin, dirs[good], sub, ang[use[good]])
        cols = cols.reshape(S, -1, 3)
        cnt = okv.reshape(S, -1).sum(0).clamp(min=1).to(cols.dtype)
        return cols.sum(0) / cnt[:, None]


def render_frame(
    scene: Scene,
    camera: Camera,
    cam_from_world: np.ndarray,
    supersample: int = 2,
    adaptive: bool = True,
    num_threads: int | None = 1,
) -> RenderedFrame:
    """Render one frame (convenience wrapper; build a :class:`Renderer` to render many)."""
    return Renderer(
        camera, supersample=supersample, adaptive=adaptive, num_threads=num_threads
    ).render(scene, cam_from_world)
