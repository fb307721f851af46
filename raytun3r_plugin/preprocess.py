"""Native frames -> network input: the one preparation shared by adapt, infer and eval.

Every path that feeds frames to a network (``raytun3r adapt`` through
:func:`raytun3r_plugin.adaptation.train.prepare_problem`, ``raytun3r infer``, ``raytun3r eval``
through :func:`raytun3r_plugin.apps.evaluation.fit_sequence`, and the examples) builds one
:class:`InputLayout` and lets it prepare frames, masks, depth maps and pixel coordinates. There is
no second policy: an adapter fitted on some frames sees, at use time, pixels prepared exactly as
at fit time, and its camera (the layout's ``native_camera``) is the one ``apply`` is given again
(LightGlue's single ``ImagePreprocessor``; COLMAP's single ``Rescale``).

The rule (:data:`RULE` version :data:`RULE_VERSION`), for native frames of ``W x H`` pixels, a long
side ``L`` and the patch size ``p``:

1. ``s = L / max(W, H)``; each side of the input is rounded to a whole number of patches,
   ``w = max(p, round(W * s / p) * p)`` and ``h = max(p, round(H * s / p) * p)`` (Python's
   ``round``).
2. If ``w / h`` differs from ``W / H`` by at most 1% (:data:`~raytun3r_plugin.geometry.ASPECT_TOLERANCE`),
   the native frame is resized to ``w x h``: a pure resize, which the camera describes exactly
   with ``camera.resized(w, h)`` (``fx`` and ``fy`` scale separately), so no crop is needed.
3. Otherwise the native frame is first centre-cropped to the input's aspect ratio (``crop_w =
   round(H * w / h)`` when the frame is too wide, ``crop_h = round(W * h / w)`` when too tall;
   ``x0 = (W - crop_w) // 2``, ``y0 = (H - crop_h) // 2``), the crop is stated on the camera
   (``camera.cropped(x0, y0, crop_w, crop_h)``, docs/conventions.md section 3), and the crop is
   resized to ``w x h`` as in 2.

Resampling: frames bilinear with antialiasing (``torch.nn.functional.interpolate``), clamped to
[0, 1]; masks nearest neighbour through :func:`raytun3r_plugin.geometry.resize_mask` (the resize
the patched model itself applies to ``apply(mask=...)``); depth maps nearest neighbour (no depth
is invented across an edge, 0 = unknown stays 0). A frame already at ``w x h`` with no crop is
passed through untouched, so square cameras whose side is a multiple of ``p`` used at that size
(the benchmark's 112 x 112 and 84 x 84) are bit-identical to feeding the frames directly.

Why this rule and not "resize the long side, then crop to patch multiples": it crops nothing for
the usual calibrations (1400 x 1400, 752 x 480, 1280 x 1024 all resize purely at 504), it keeps
crops in integer *native* pixels (so the camera given to ``apply`` is the calibration itself, or
an exactly stated crop of it), and it is the rule adaptation always used, so adapters fitted
before this module existed keep their meaning.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from raytun3r_plugin.cameras.base import Camera
from raytun3r_plugin.errors import AdapterError, InputError
from raytun3r_plugin.geometry import ASPECT_TOLERANCE, camera_for_input, resize_mask

__all__ = [
    "DEFAULT_LONG_SIDE",
    "RULE",
    "RULE_VERSION",
    "InputLayout",
    "fitted_source_camera",
    "input_layout",
    "layout_for_inference",
    "to_input_pixels",
]

#: Name of the rule in the module docstring, recorded in ``adapter.training_info["input"]["rule"]``.
RULE = "patch-rounded-sides, centre-crop beyond 1% aspect change"
#: Bumped whenever the rule would give another input for the same camera and long side.
RULE_VERSION = 1
#: Long side (px) of the command line's ``--size`` when neither the user nor an adapter gives one.
DEFAULT_LONG_SIDE = 504


def to_input_pixels(
    uv: torch.Tensor,
    native_size: tuple[int, int],
    input_size: tuple[int, int],
    offset: tuple[float, float] = (0.0, 0.0),
) -> torch.Tensor:
    """Map native-image pixels to network-input pixels (pure resize, after an optional crop).

    Args:
        uv: (..., 2) pixel positions ``(u, v)`` in the native image.
        native_size: ``(width, height)`` of the (cropped) native image the input was resized from.
        input_size: ``(width, height)`` of the network input.
        offset: ``(x0, y0)`` top-left pixel of the crop in the native image (0, 0 for none).

    Returns:
        (..., 2) positions in input pixels: ``u' = (u - x0 + 0.5) * W_in / W - 0.5`` (same for v),
        the mapping of :meth:`raytun3r_plugin.cameras.Camera.scaled`.
    """
    scale = uv.new_tensor([input_size[0] / native_size[0], input_size[1] / native_size[1]])
    shift = uv.new_tensor([float(offset[0]), float(offset[1])])
    return (uv - shift + 0.5) * scale - 0.5


def _positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise InputError(f"{name} must be a positive integer (pixels), got {value!r}")
    return int(value)


@dataclass(frozen=True)
class InputLayout:
    """How native frames of one camera become the network input (the rule of the module docstring).

    Build it with :meth:`for_camera` (or :func:`input_layout`); the fields are the rule's result.

    Attributes:
        width, height: network input size in pixels (multiples of ``patch``).
        crop: ``(x0, y0, w, h)`` centred crop of the native frame, in native pixels, applied
            before resizing; None for a pure resize.
        native_camera: camera of the (cropped) native frame, ``w x h`` of the crop; what the
            model is patched with and what an adapter records as its camera.
        camera: the same camera at the network input size, ``width x height``
            (``native_camera.resized(width, height)``).
        long_side: the requested long side ``L`` (px), before rounding to patches.
        patch: the patch size ``p`` (px).
        source_size: ``(W, H)`` of the uncropped native frames (the camera given to :meth:`for_camera`).
    """

    width: int
    height: int
    crop: tuple[int, int, int, int] | None
    native_camera: Camera
    camera: Camera
    long_side: int
    patch: int
    source_size: tuple[int, int]

    @classmethod
    def for_camera(cls, camera: Camera, long_side: int, patch: int = 14) -> InputLayout:
        """The layout of frames of ``camera`` (``camera.width x camera.height`` px) for a network
        input of long side ``long_side`` px and patches of ``patch`` px.

        Raises:
            InputError: ``long_side`` or ``patch`` is not a positive integer.
        """
        long_side, patch = _positive_int("long side", long_side), _positive_int("patch size", patch)
        width, height = int(camera.width), int(camera.height)
        scale = long_side / max(width, height)
        in_w = max(patch, round(width * scale / patch) * patch)
        in_h = max(patch, round(height * scale / patch) * patch)
        native_aspect, input_aspect = width / height, in_w / in_h
        crop = None
        native = camera
        # Beyond the tolerance a pure resize would be a silent stretch (docs/conventions.md
        # section 3): the crop is stated on the camera instead.
        if abs(input_aspect - native_aspect) / native_aspect > ASPECT_TOLERANCE:
            if native_aspect > input_aspect:
                crop_w, crop_h = round(height * input_aspect), height
            else:
                crop_w, crop_h = width, round(width / input_aspect)
            crop = ((width - crop_w) // 2, (height - crop_h) // 2, crop_w, crop_h)
            native = camera.cropped(*crop)
        return cls(
            in_w, in_h, crop, native, native.resized(in_w, in_h), long_side, patch, (width, height)
        )

    # ------------------------------------------------------------------ geometry
    @property
    def native_size(self) -> tuple[int, int]:
        """``(width, height)`` of the cropped native frame (px)."""
        return int(self.native_camera.width), int(self.native_camera.height)

    @property
    def input_size(self) -> tuple[int, int]:
        """``(width, height)`` of the network input (px)."""
        return self.width, self.height

    @property
    def offset(self) -> tuple[int, int]:
        """``(x0, y0)`` of the crop in native pixels; (0, 0) without one."""
        return (0, 0) if self.crop is None else (self.crop[0], self.crop[1])

    def to_input_pixels(self, uv: torch.Tensor) -> torch.Tensor:
        """(..., 2) native pixel positions ``(u, v)`` (of the uncropped frame, pixel-centre
        convention) -> (..., 2) network-input pixel positions; see :func:`to_input_pixels`."""
        return to_input_pixels(uv, self.native_size, self.input_size, self.offset)

    # ------------------------------------------------------------------ data
    def _check_frame_size(self, what: str, height: int, width: int) -> None:
        if (width, height) != self.source_size:
            raise InputError(
                f"{what} {width}x{height} px but the camera describes {self.source_size[0]}x{self.source_size[1]} px; "
                "rescale the camera to the frames first (camera.resized(w, h)) or state a crop (camera.cropped(...))"
            )

    def _crop(self, tensor: torch.Tensor) -> torch.Tensor:
        if self.crop is None:
            return tensor
        x0, y0, w, h = self.crop
        return tensor[..., y0 : y0 + h, x0 : x0 + w]

    def frames(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) native RGB frames in [0, 1] -> (N, 3, h, w) float32 network input in [0, 1].

        Crop (if any), then bilinear antialiased resize (skipped when the size already matches),
        then clamp to [0, 1] (the antialiasing filter can overshoot slightly at edges).

        Raises:
            InputError: not (N, H, W, 3), or frames of another size than the camera.
        """
        array = (
            images.detach().cpu()
            if isinstance(images, torch.Tensor)
            else torch.from_numpy(np.ascontiguousarray(images))
        )
        if array.ndim != 4 or array.shape[-1] != 3:
            raise InputError(
                f"frames must be (N, H, W, 3) RGB in [0, 1], got shape {tuple(array.shape)}"
            )
        self._check_frame_size("frames are", int(array.shape[1]), int(array.shape[2]))
        tensor = self._crop(array.permute(0, 3, 1, 2).float())
        if tuple(tensor.shape[-2:]) != (self.height, self.width):
            tensor = F.interpolate(
                tensor,
                size=(self.height, self.width),
                mode="bilinear",
                align_corners=False,
                antialias=True,
            )
        return tensor.clamp(0.0, 1.0).contiguous()

    def native_mask(self, mask: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(H, W) mask of the native frames -> (H', W') bool of the cropped native frame (the crop
        only): the form ``apply(model, layout.native_camera, mask=...)`` takes.

        Raises:
            InputError: not (H, W) at the camera's size.
        """
        tensor = (
            mask.detach().cpu()
            if isinstance(mask, torch.Tensor)
            else torch.from_numpy(np.ascontiguousarray(mask))
        )
        if tensor.ndim != 2:
            raise InputError(f"mask must be (H, W), got shape {tuple(tensor.shape)}")
        self._check_frame_size("mask is", int(tensor.shape[0]), int(tensor.shape[1]))
        return self._crop(tensor.bool()).contiguous()

    def mask(self, mask: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(H, W) or (N, H, W) mask of the native frames -> (h, w) or (N, h, w) bool at the
        network input: crop, then nearest neighbour (:func:`~raytun3r_plugin.geometry.resize_mask`,
        so it stays binary and agrees with what the patched model excludes).

        Raises:
            InputError: neither (H, W) nor (N, H, W) at the camera's size.
        """
        tensor = (
            mask.detach().cpu()
            if isinstance(mask, torch.Tensor)
            else torch.from_numpy(np.ascontiguousarray(mask))
        )
        if tensor.ndim == 3:
            return (
                torch.stack([self.mask(m) for m in tensor])
                if len(tensor)
                else torch.zeros((0, self.height, self.width), dtype=torch.bool)
            )
        return resize_mask(self.native_mask(tensor), (self.height, self.width))

    def depth(self, maps: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(N, H, W) ground-truth depth of the native frames -> (N, h, w) float32 at the network
        input: crop, then nearest neighbour (a depth is never blended across an edge; 0 or NaN,
        "no value", stays as it is).

        Raises:
            InputError: not (N, H, W) at the camera's size.
        """
        tensor = (
            maps.detach().cpu()
            if isinstance(maps, torch.Tensor)
            else torch.from_numpy(np.ascontiguousarray(maps))
        )
        if tensor.ndim != 3:
            raise InputError(f"depth maps must be (N, H, W), got shape {tuple(tensor.shape)}")
        self._check_frame_size("depth maps are", int(tensor.shape[1]), int(tensor.shape[2]))
        tensor = self._crop(tensor.float())
        if tuple(tensor.shape[-2:]) != (self.height, self.width):
            tensor = F.interpolate(tensor[:, None], size=(self.height, self.width), mode="nearest")[
                :, 0
            ]
        return tensor.contiguous()

    # ------------------------------------------------------------------ record
    def record(self) -> dict[str, Any]:
        """JSON-able description for ``adapter.training_info["input"]``: the rule (name, version),
        its arguments (long side, patch, native size) and its result (input size, crop)."""
        return {
            "rule": RULE,
            "rule_version": RULE_VERSION,
            "long_side": self.long_side,
            "patch": self.patch,
            "source": list(self.source_size),
            "width": self.width,
            "height": self.height,
            "crop": list(self.crop) if self.crop else None,
        }


def input_layout(camera: Camera, long_side: int, patch: int = 14) -> InputLayout:
    """:meth:`InputLayout.for_camera`: the layout of frames of ``camera`` for a long side of
    ``long_side`` px and patches of ``patch`` px."""
    return InputLayout.for_camera(camera, long_side, patch)


def fitted_source_camera(adapter: Any) -> Camera | None:
    """The camera of the uncropped native frames ``adapter`` was fitted on, or None.

    An adapter carries the layout's ``native_camera``, which is the calibration cropped when the
    rule cropped; with the crop and the source size recorded in ``training_info["input"]`` the
    crop is undone exactly (``cropped`` with a negative offset only shifts the principal point
    back), so the rule applied to the result reproduces the adapter's camera.
    """
    camera = getattr(adapter, "camera", None)
    if camera is None:
        return None
    recorded = (getattr(adapter, "training_info", None) or {}).get("input") or {}
    crop, source = recorded.get("crop"), recorded.get("source")
    if (
        not crop
        or not source
        or (int(crop[2]), int(crop[3])) != (int(camera.width), int(camera.height))
    ):
        return camera
    return camera.cropped(-int(crop[0]), -int(crop[1]), int(source[0]), int(source[1]))


def layout_for_inference(
    camera: Camera | None,
    frame_size: tuple[int, int],
    adapter: Any = None,
    long_side: int | None = None,
    patch: int | None = None,
    strict: bool = True,
) -> InputLayout:
    """The layout that prepares frames at use time as ``adapter`` was fitted (``raytun3r infer``).

    Args:
        camera: camera of the calibration; None: the adapter's (with its crop undone,
            :func:`fitted_source_camera`). When ``frame_size`` differs from the camera's size,
            the camera is rescaled to the frames by a pure resize (docs/conventions.md section 3);
            an aspect change beyond 1% is refused, a crop must be stated on the camera.
        frame_size: ``(W, H)`` of the frames to be prepared (px).
        adapter: optional :class:`~raytun3r_plugin.adapter.Adapter`; its recorded input
            (``training_info["input"]``) gives the long side and the patch size when they are
            not given.
        long_side: network input long side (px); default: the adapter's, else
            :data:`DEFAULT_LONG_SIDE`.
        patch: patch size (px); default: the adapter's, else 14.
        strict: refuse an adapter whose recorded rule is not this module's, or whose recorded
            input this layout does not reproduce for the same native size and long side.

    Raises:
        InputError: no camera, or frames whose aspect ratio the camera cannot describe by a pure
            resize.
        AdapterError: (strict) the adapter's input was prepared by another rule.
    """
    recorded: Mapping[str, Any] = (
        ((getattr(adapter, "training_info", None) or {}).get("input") or {})
        if adapter is not None
        else {}
    )
    if (
        strict
        and "rule" in recorded
        and (recorded.get("rule"), recorded.get("rule_version")) != (RULE, RULE_VERSION)
    ):
        raise AdapterError(
            f"adapter's input was prepared by rule {recorded.get('rule')!r} version {recorded.get('rule_version')}, "
            f"this version prepares frames by {RULE!r} version {RULE_VERSION}; pass strict=False (--no-strict) to use it anyway"
        )
    if long_side is None:
        long_side = int(recorded.get("long_side") or DEFAULT_LONG_SIDE)
    if patch is None:
        patch = int(recorded.get("patch") or getattr(adapter, "patch_size", None) or 14)
    if camera is None:
        camera = fitted_source_camera(adapter)
    if not isinstance(camera, Camera):
        raise InputError(
            f"camera must be a raytun3r_plugin.cameras.Camera (or an adapter that carries one), got {type(camera).__name__}"
        )
    width, height = (int(v) for v in frame_size)
    layout = InputLayout.for_camera(camera_for_input(camera, height, width), long_side, patch)
    # Same rule, same native size and long side: the input must be what the fit saw; a
    # difference means the record and this code disagree, which no camera check would notice.
    same_question = (
        recorded.get("source") == list(layout.source_size)
        and recorded.get("long_side") == layout.long_side
    )
    if strict and "rule" in recorded and same_question:
        found = layout.record()
        if any(recorded.get(key) != found[key] for key in ("width", "height", "crop")):
            raise AdapterError(
                f"adapter was fitted on a {recorded.get('width')}x{recorded.get('height')} px input (crop {recorded.get('crop')}), "
                f"these frames give {found['width']}x{found['height']} px (crop {found['crop']}) under the same rule"
            )
    return layout
