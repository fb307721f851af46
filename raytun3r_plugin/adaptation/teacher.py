"""The frozen model as its own teacher: its depth on virtual pinhole views of the fisheye frames.

A pinhole-trained network is in its training distribution on a pinhole view, and a virtual
pinhole view of a fisheye frame (the Center-PH view of the baselines, docs/baselines.md) loses
only the periphery. On the development sequences, the unpatched network's depth on the 110-degree
centre view was closer to the ground truth over the pixels that view covers than the patched
network's fisheye depth over the same pixels (docs/adaptation.md section 6, "The pinhole-view
teacher"). So the fit can ask the patched fisheye forward to agree, up to one scale per view, with
what the same frozen network says about the same rays through a pinhole: a depth signal that needs
no match and no parallax, and that holds where the matches have none (the outdoor windows that
the parallax gate drops).

Targets are computed once per fit, before the patch is applied: for every window, each view's
frames go through the *unpatched* model together (the multi-view forward the network was trained
for), and its z-depth is mapped back to the fisheye pixels the view covers as range along the ray
(:func:`~raytun3r_plugin.baselines.multi_ph.view_depth_to_fisheye`). The term is
:func:`~raytun3r_plugin.adaptation.losses.grouped_silog_loss` over those pixels, one group per
view (each view has its own scale).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.errors import AlreadyAppliedError, InputError
from raytun3r_plugin.pinhole_views import (
    VIEW_NAMES,
    multi_pinhole_views,
    resample_to_view,
    view_coverage,
    view_depth_to_fisheye,
)
from raytun3r_plugin.prediction import predict

if TYPE_CHECKING:
    from raytun3r_plugin.adaptation.problem import AdaptationProblem

__all__ = [
    "MAX_TEACHER_SAMPLES",
    "TeacherTargets",
    "teacher_coverage",
    "teacher_targets",
    "teacher_views",
    "view_range",
]

#: Most teacher samples kept per frame and view (a seeded subset; 112 px views have fewer).
MAX_TEACHER_SAMPLES = 4096

#: Per window index: per frame of the window, ``(uv (K, 2) input pixels, range (K,), view (K,))``
#: with ``view`` the index of the sample's view in the fit's ``teacher_views``.
TeacherTargets = dict[int, list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]]


def teacher_views(camera: Any, names: tuple[str, ...], fov_deg: float) -> list:
    """The virtual pinhole views ``names`` (of :data:`VIEW_NAMES`) of ``camera``, each
    ``fov_deg`` across its width; the side views are turned by the Multi-PH tilt rule.

    Raises:
        InputError: an unknown or repeated view name, or none.
    """
    if not names or len(set(names)) != len(names) or not set(names) <= set(VIEW_NAMES):
        raise InputError(
            f"teacher views must be distinct names out of {VIEW_NAMES}, got {tuple(names)!r}"
        )
    # The tilt rule searches coverage; the centre view alone does not need it.
    tilt = 0.0 if tuple(names) == ("centre",) else None
    views = multi_pinhole_views(camera, tilt_deg=tilt, fov_deg=fov_deg)
    return [view for view in views if view.name in names]


def teacher_coverage(camera: Any, names: tuple[str, ...], fov_deg: float) -> float:
    """The largest fraction of ``camera``'s valid pixels that one of the teacher views ``names``
    covers.

    A lens that a view covers almost entirely gives the network nearly the same image through it
    as through the fisheye itself, only resampled: there is little to teach, and on the
    development sequences the term then made depth worse (docs/adaptation.md section 6; the
    trainer's gate :attr:`AdaptConfig.teacher_max_coverage`). Each view counts on its own: views
    that together cover most of a wide lens each still show a part of it as a pinhole would.
    """
    return max(view_coverage(camera, [view]) for view in teacher_views(camera, names, fov_deg))


def view_range(
    model: nn.Module, images: torch.Tensor, camera: Any, view: Any
) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's depth on one virtual pinhole ``view`` of fisheye ``images``, as fisheye range.

    Args:
        model: the backbone as it is (the teacher calls it unpatched).
        images: (S, 3, H, W) fisheye frames in [0, 1], predicted together as one multi-view input.
        camera: their fisheye camera; view: a :class:`~raytun3r_plugin.baselines.multi_ph.
            PinholeView` of it.

    Returns:
        (S, H, W) range along each fisheye pixel's ray (CPU, float32) and the (H, W) bool mask of
        the pixels the view covers.
    """
    virtual = resample_to_view(images, camera, view.camera, view.rotation)
    depth_z = predict(model, virtual[None]).depth[0].float().cpu()
    return view_depth_to_fisheye(depth_z, camera, view.camera, view.rotation)


def teacher_targets(
    model: nn.Module,
    problem: AdaptationProblem,
    names: tuple[str, ...],
    fov_deg: float,
    seed: int,
    max_samples: int = MAX_TEACHER_SAMPLES,
) -> TeacherTargets:
    """The teacher's depth for every window of ``problem``.

    Args:
        model: the backbone, *unpatched* (the teacher is the frozen model on pinhole images).
        problem: the prepared problem (its windows' network inputs and valid region).
        names: views of :func:`teacher_views`; fov_deg: their field of view, degrees.
        seed: seeds the subset of at most ``max_samples`` pixels per frame and view.

    Returns:
        :data:`TeacherTargets`: per window, per frame, the covered valid pixels (input-pixel
        centres), the teacher's range there and the index in ``names`` of the view each one
        came from (the order of ``AdaptConfig.teacher_view_weights``, :meth:`AdaptConfig.
        view_weights`).

    Raises:
        AlreadyAppliedError: the model carries a raytun3r patch.
        InputError: no view covers a valid pixel of the input.
    """
    from raytun3r_plugin.patching import handle_of

    if handle_of(model) is not None:
        raise AlreadyAppliedError("the teacher is the unpatched model; remove the patch first")
    camera = problem.layout.camera
    views = teacher_views(camera, names, fov_deg)
    valid = problem.valid.cpu().bool()
    generator = torch.Generator().manual_seed(int(seed))
    targets: TeacherTargets = {}
    with torch.no_grad():
        for index in range(len(problem.windows)):
            images = problem.batch(index)
            per_frame: list[list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]] = [
                [] for _ in range(images.shape[0])
            ]
            for view in views:
                # Indexed by the caller's order, which is the order of its per-view weights.
                number = list(names).index(view.name)
                ranges, inside = view_range(model, images, camera, view)
                for k in range(images.shape[0]):
                    usable = inside & valid & torch.isfinite(ranges[k]) & (ranges[k] > 0)
                    rows, cols = torch.nonzero(usable, as_tuple=True)
                    if rows.numel() > max_samples:
                        keep = torch.randperm(rows.numel(), generator=generator)[:max_samples]
                        keep = keep.sort().values
                        rows, cols = rows[keep], cols[keep]
                    uv = torch.stack((cols, rows), dim=-1).float()
                    per_frame[k].append((uv, ranges[k][rows, cols], torch.full_like(rows, number)))
            targets[index] = [
                (
                    torch.cat([uv for uv, _, _ in parts]),
                    torch.cat([value for _, value, _ in parts]),
                    torch.cat([group for _, _, group in parts]),
                )
                for parts in per_frame
            ]
    if not any(uv.shape[0] for frames in targets.values() for uv, _, _ in frames):
        raise InputError(
            f"no teacher view ({', '.join(names)}, {fov_deg:g} deg) covers a valid pixel"
        )
    return targets
