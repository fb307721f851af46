"""Solid (3-D) procedural noise for the synthetic renderer.

The texture of every synthetic surface is a function of the 3-D world position of the surface
point, so a point has the same colour in every view (brightness constancy for matchers).

3-D value noise is evaluated with a single bilinear 2-D texture fetch per octave, the
"z-slices in a 2-D texture" construction: lattice slice ``k`` (integer z) is the periodic 2-D
random texture read at an offset ``k * (OX, OY)`` texels; a second copy of the texture, rolled by
one slice offset, is stored in the extra channels, so one ``grid_sample`` returns slices ``k``
and ``k + 1`` and a smoothstep blend in z gives the 3-D value. In x and y the fractional
coordinate is warped by the smoothstep before the bilinear fetch, which turns bilinear into
smoothstep-interpolated value noise. The lattice repeats every ``size`` cells along each axis
(256 by default); octaves use different random rotations and offsets, so sums of octaves do not
repeat visibly.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["SolidNoise", "band_weight", "random_rotations", "smoothstep"]

# Texel offset between consecutive z-slices (coprime with the texture size, so the slice pattern
# only repeats after ``size`` slices).
_SLICE_OFFSET = (37, 17)


def smoothstep(
    edge0: torch.Tensor | float, edge1: torch.Tensor | float, x: torch.Tensor
) -> torch.Tensor:
    """Hermite smoothstep: 0 below ``edge0``, 1 above ``edge1``, C1 in between (elementwise)."""
    t = torch.clamp((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` random rotation matrices (n, 3, 3) float64 from normalised Gaussian quaternions."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


class SolidNoise:
    """Multi-octave 3-D value noise with ``channels`` independent fields, values in [0, 1].

    Args:
        seed: seed of the random lattice, the per-octave rotations and offsets.
        octaves: number of octaves; octave ``o`` has frequency ``lacunarity ** o`` lattice cells
            per input unit.
        channels: independent noise fields returned per octave.
        lacunarity: frequency ratio between octaves (not a power of two, so octaves do not align).
        size: lattice period in cells (texture is ``size`` x ``size`` texels).
    """

    def __init__(
        self,
        seed: int,
        octaves: int = 5,
        channels: int = 4,
        lacunarity: float = 2.07,
        size: int = 256,
    ) -> None:
        gen = torch.Generator().manual_seed(int(seed) & 0x7FFFFFFF)
        base = torch.rand(channels, size, size, generator=gen, dtype=torch.float32)
        ox, oy = _SLICE_OFFSET
        # shifted[c, y, x] = base[c, y + oy, x + ox]: the next z-slice at the same texel.
        shifted = torch.roll(base, shifts=(-oy, -ox), dims=(1, 2))
        tex = torch.cat([base, shifted], dim=0)
        # One wrapped texel on the right/bottom edge makes bilinear fetches periodic.
        tex = torch.cat([tex, tex[:, :1, :]], dim=1)
        tex = torch.cat([tex, tex[:, :, :1]], dim=2)
        self.texture = tex.unsqueeze(0).contiguous()  # (1, 2C, S+1, S+1)
        self.channels = channels
        self.size = size
        self.octaves = octaves
        self.frequencies = [lacunarity**o for o in range(octaves)]
        rng = np.random.default_rng(int(seed) + 7919)
        rots = random_rotations(octaves, rng)
        offs = rng.uniform(0.0, size, size=(octaves, 3))
        # All octaves in one matmul: column block o of _mat is f_o R_o^T.
        mat = np.concatenate([rots[o].T * self.frequencies[o] for o in range(octaves)], axis=1)
        self._mat = torch.from_numpy(mat).to(torch.float32)  # (3, 3 O)
        self._off_flat = torch.from_numpy(offs.reshape(-1)).to(torch.float32)  # (3 O,)
        self._slice = torch.tensor(_SLICE_OFFSET, dtype=torch.float32)

    def lattice(self, p: torch.Tensor) -> torch.Tensor:
        """Single-octave value noise at lattice coordinates ``p`` (N, 3) -> (N, C) in [0, 1]."""
        n = p.shape[0]
        if n == 0:
            return p.new_zeros((0, self.channels))
        i = torch.floor(p)
        f = p - i
        fs = f * f * (3.0 - 2.0 * f)
        # texel position of slice floor(z): smoothstepped x, y plus the slice offset
        xy = torch.addcmul(i[:, :2] + fs[:, :2], i[:, 2:3], self._slice)
        s = float(self.size)
        grid = torch.remainder(xy, s).mul_(2.0 / s).sub_(1.0)
        v = F.grid_sample(
            self.texture,
            grid.view(1, 1, n, 2),
            mode="bilinear",
            padding_mode="border",
            align_corners=True,
        ).view(2 * self.channels, n)
        return torch.lerp(v[: self.channels], v[self.channels :], fs[:, 2]).t()

    def octave_stack(self, p: torch.Tensor, offset: torch.Tensor | None = None) -> torch.Tensor:
        """Noise of all octaves at points ``p`` (N, 3) -> (O, N, C) in [0, 1] (a strided view).

        ``p`` is in noise units (one lattice cell of octave 0 per unit); octave ``o`` reads the
        lattice at ``R_o p f_o + b_o``. ``offset`` (N, 3) is an optional per-point shift (in
        lattice cells, added to every octave) used to decorrelate materials.
        """
        n, o = p.shape[0], self.octaves
        q = torch.addmm(self._off_flat, p, self._mat)  # (N, 3 O)
        q = q.view(n, o, 3)
        if offset is not None:
            q = q + offset[:, None, :]
        v = self.lattice(q.reshape(n * o, 3))
        return v.view(n, o, self.channels).transpose(0, 1)


def band_weight(frequency: torch.Tensor | float, footprint: torch.Tensor) -> torch.Tensor:
    """Pre-filter weight of a noise octave: 1 when a cell spans >= 2 samples, 0 at <= 1 sample.

    ``frequency`` is in cells per metre, ``footprint`` the width (metres) one sample covers on
    the surface. Fading an octave to its mean where it would alias is the texture anti-aliasing
    of the renderer (geometry edges are handled by supersampling).
    """
    x = frequency * footprint
    return torch.clamp(2.0 - 2.0 * x, 0.0, 1.0)
