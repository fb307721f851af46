"""The checks ``apply`` runs before it changes anything: each adapter against the backbone, the
camera and the other branches; the masks; the per-view (rig) arguments; and whether a model is
already patched for the same views. Everything here reads, nothing writes
(:mod:`raytun3r_plugin.patching` installs)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from raytun3r_plugin.adapter import Adapter, normalise_components, pe_fingerprint
from raytun3r_plugin.errors import (
    AdapterError,
    CameraError,
    InputError,
)
from raytun3r_plugin.geometry import (
    map_is_identity,
    resize_mask,
)
from raytun3r_plugin.patch_state import (
    PatchState,
    View,
    _same_camera,
    _same_mask,
)
from raytun3r_plugin.registry import (
    HOOK_COMPONENTS,
    BackboneInfo,
    BackboneSpec,
)

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera


def _check_adapter(adapter: Adapter, info: BackboneInfo, camera: Camera, strict: bool) -> None:
    if adapter.backbone != info.name:
        raise AdapterError(
            f"adapter was made for backbone {adapter.backbone!r}, this model is {info.name!r}"
        )
    if adapter.embed_dim != info.embed_dim:
        raise AdapterError(
            f"adapter has embed_dim {adapter.embed_dim}, this model has {info.embed_dim}"
        )
    if adapter.patch_size != info.patch_size:
        raise AdapterError(
            f"adapter has patch_size {adapter.patch_size}, this model has {info.patch_size}"
        )
    if bool(adapter.n_r_rope) and not info.has_rope:
        raise AdapterError(f"adapter has a RoPE table but {info.name!r} has no RoPE")
    if strict:
        found = pe_fingerprint(info.pos_embed)
        if adapter.pe_fingerprint and adapter.pe_fingerprint != found:
            raise AdapterError(
                f"adapter was fitted on other weights of {info.name!r} (pe_fingerprint {adapter.pe_fingerprint}, "
                f"this model has {found}); pass strict=False to apply it anyway"
            )
        if (
            adapter.camera is not None
            and camera is not None
            and not _same_camera(adapter.camera, camera)
        ):
            raise AdapterError(
                f"adapter was fitted on {adapter.camera!r}, not on {camera!r}; pass strict=False to apply it anyway"
            )


def _components_for(components, adapter: Adapter | None) -> dict[str, bool]:
    if components is None and adapter is not None:
        return dict(adapter.components)
    return normalise_components(components)


def _checked_mask(mask: Any, camera: Camera) -> torch.Tensor:
    """The scene mask as (H, W) bool, refused when it cannot belong to ``camera``.

    It may be at the camera's size or at another size of the same aspect ratio (it is resized
    with the camera to every input); a different aspect ratio or nothing left inside the lens is
    a mistake that would otherwise show only as worse depth.
    """
    mask = torch.as_tensor(mask).bool()
    if mask.ndim != 2:
        raise CameraError(f"mask must be (H, W), got shape {tuple(mask.shape)}")
    height, width = mask.shape
    if abs(height * camera.width - width * camera.height) > 0.01 * width * camera.height:
        raise CameraError(
            f"mask is {width}x{height} px but the camera is {camera.width}x{camera.height}: the aspect ratios differ"
        )
    valid = camera.valid_mask().cpu()
    if not bool((resize_mask(mask, (int(valid.shape[0]), int(valid.shape[1]))) & valid).any()):
        raise CameraError("mask leaves no pixel inside the camera's valid region")
    return mask


def _views_of(camera, adapter, mask) -> tuple[list, list, list]:
    """Per-view (cameras, adapters, masks) of ``apply``'s arguments, each checked; no model read."""
    from raytun3r_plugin.cameras import Camera

    def one_adapter(item):
        if isinstance(item, str) or hasattr(item, "__fspath__"):
            item = Adapter.load(item)
        if item is not None and not isinstance(item, Adapter):
            raise AdapterError(
                f"adapter must be an Adapter, a path or None, got {type(item).__name__}"
            )
        return item

    rig = isinstance(camera, (list, tuple)) or isinstance(adapter, (list, tuple))
    if not rig:
        adapters = [one_adapter(adapter)]
        cameras = [camera if camera is not None or adapters[0] is None else adapters[0].camera]
        masks = [mask]
    else:
        given = (
            [one_adapter(item) for item in adapter] if isinstance(adapter, (list, tuple)) else None
        )
        if camera is None:  # then the adapters are a list (a rig needs a list of either)
            cameras = [item.camera if item is not None else None for item in given or []]
        elif isinstance(camera, (list, tuple)):
            cameras = list(camera)
        else:
            cameras = [camera] * len(given or [None])
        if not cameras:
            raise CameraError("apply got an empty camera list: a rig needs at least one camera")
        if given is None:
            adapters = [one_adapter(adapter)] * len(cameras)
        elif len(given) != len(cameras):
            raise AdapterError(
                f"apply got {len(cameras)} cameras and {len(given)} adapters: give one adapter "
                "per camera (None for a camera without one) or a single adapter"
            )
        else:
            adapters = given
        if isinstance(mask, (list, tuple)):
            masks = list(mask)
            if len(masks) != len(cameras):
                raise CameraError(
                    f"apply got {len(cameras)} cameras and {len(masks)} masks: give one per camera"
                )
        else:
            if mask is not None and len(cameras) > 1:
                raise CameraError(
                    "a rig takes one mask per camera (a list, None for a camera without one)"
                )
            masks = [mask] * len(cameras)
    for index, view_camera in enumerate(cameras):
        where = f"camera {index} of the rig" if rig else "camera"
        if view_camera is None:
            raise CameraError(
                f"apply needs a camera (or an adapter that carries one): {where} has none"
            )
        if not isinstance(view_camera, Camera):
            raise CameraError(
                f"{where} must be a raytun3r_plugin.cameras.Camera, got {type(view_camera).__name__}"
            )
    first = cameras[0]
    for index, view_camera in enumerate(cameras[1:], start=1):
        aspect, expected = view_camera.width / view_camera.height, first.width / first.height
        if abs(aspect - expected) / expected > 0.01:
            raise CameraError(
                f"camera {index} of the rig is {view_camera.width}x{view_camera.height} px (aspect "
                f"{aspect:.4f}), camera 0 is {first.width}x{first.height} (aspect {expected:.4f}): "
                "a rig's views share one network input size, so its cameras need one aspect "
                "ratio (crop with camera.cropped(...) first)"
            )
    masks = [
        None if view_mask is None else _checked_mask(view_mask, view_camera)
        for view_mask, view_camera in zip(masks, cameras, strict=True)
    ]
    return cameras, adapters, masks


def _check_branch_width(adapter: Adapter, spec: BackboneSpec, branches: list) -> None:
    """Refuse, naming the branches, an adapter that is not sized for a branched model's main one.

    Its learned tables have the width of one network; they are applied to the main branch only.
    """
    main_path, _spec, _root, main = branches[0]
    if adapter.embed_dim == main.embed_dim:
        return
    widths = ", ".join(f"'{path}' {info.embed_dim}" for path, _s, _r, info in branches)
    other = [path for path, _s, _r, info in branches[1:] if info.embed_dim == adapter.embed_dim]
    why = (
        f"that is the width of the branch '{other[0]}', but"
        if other
        else "which matches none of its branches; and"
    )
    raise AdapterError(
        f"adapter has embed_dim {adapter.embed_dim} and this {spec.family} model's branches have "
        f"{widths}: {why} the adapter of a {spec.family} model is fitted for and applied to its "
        f"main branch '{main_path}' (the other branches take the parameter-free corrections only)"
    )


def _same_views(existing: tuple[View, ...], views: tuple) -> bool:
    """True when ``views`` (camera, adapter, mask per position) are what ``existing`` holds."""
    if len(existing) != len(views):
        return False
    for view, (camera, adapter, mask) in zip(existing, views, strict=True):
        if not _same_camera(view.camera, camera) or not _same_mask(view.mask, mask):
            return False
        if (view.adapter is None) != (adapter is None):
            return False
        if view.adapter is not None and not view.adapter.same_as(adapter):
            return False
    return True


def _check_per_view(spec: BackboneSpec, found: list, branch_path: str, state: PatchState) -> None:
    """Refuse a rig where a hook in use computes one value for every view (``per_view=False``).

    Passed where the one value would be right for every view anyway: a RoPE hook without any
    RoPE table among the views' adapters, another hook when every camera's map is the identity
    (pinhole cameras inside the knee, whose corrections are upstream's own values).
    """
    identity = all(map_is_identity(view.camera, state.knee_deg) for view in state.views)
    for target, path, _owner in found:
        if target.hook == "rope" and not state.uses("rope"):
            continue
        if target.hook != "rope" and identity:
            continue
        if not target.per_view:
            where = f"{branch_path}.{path}" if branch_path else path
            served = sorted(HOOK_COMPONENTS.get(target.hook, ()))
            raise InputError(
                f"{spec.family}: a rig of different cameras needs every hook per view, but "
                f"{where}.{target.attribute} ({target.name!r}) computes one value for all views "
                f"upstream; apply with components that leave {served} off, or one camera"
            )
