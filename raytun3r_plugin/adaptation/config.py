"""Settings of an adaptation run: :class:`AdaptConfig` and the default loss weights.

Part of :mod:`raytun3r_plugin.adaptation.train` (which re-exports every name here).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from raytun3r_plugin.adaptation.losses import LossWeights
from raytun3r_plugin.adaptation.settings_check import (
    PE_REGULARISERS,
    POSE_SOURCES,
    POSE_WINDOWS,
    SCALES,
    TEACHER_VIEWS,
    TERMS,
    check_settings,
)
from raytun3r_plugin.errors import InputError

if TYPE_CHECKING:
    from torch import nn

__all__ = [
    "DEFAULT_TEACHER_VIEW_WEIGHTS",
    "DEFAULT_WEIGHTS",
    "PE_REGULARISERS",
    "POSE_SOURCES",
    "POSE_WINDOWS",
    "RECIPE_LR",
    "SCALES",
    "SELF_SUPERVISED_WEIGHTS",
    "SUPERVISED_WEIGHTS",
    "TEACHER_VIEWS",
    "TEACHER_WEIGHTS",
    "TERMS",
    "AdaptConfig",
]


#: Default loss weights of the self-supervised fit. The paper's (reproj 1, smooth 10, L2 2, TV
#: 20, pose 1) were set in absolute PE units; here L2 and TV count relative to the backbone's own
#: PE energy (``pe_regulariser="relative"``), and at the paper's weights even that prices the
#: correction that ground-truth depth finds (0.7-1.1 rms on a PE of std 0.5) at about 110
#: against data terms of about 2, so the tables stay at zero. These weights were chosen on the
#: three development sequences of docs/adaptation.md ("Choosing the defaults"), never on the
#: benchmark's held-out seeds.
SELF_SUPERVISED_WEIGHTS = {
    "reproj": 1.0,
    "smooth": 1.0,
    "l2": 0.02,
    "tv": 0.2,
    "pose": 1.0,
    "depth": 0.0,
}
#: Loss weights of the ``default`` recipe (:mod:`~raytun3r_plugin.adaptation.recipes`), which are
#: ``AdaptConfig``'s: the self-supervised weights with the pose term at 0.3 (docs/decisions.md,
#: "Pose source and pose weight") and the lens-gated pinhole-view teacher at 10 ("The lens-gated
#: teacher").
DEFAULT_WEIGHTS = {**SELF_SUPERVISED_WEIGHTS, "pose": 0.3, "teacher": 10.0}
#: The default recipe's teacher views and their weights: the 110-degree centre view, and the left
#: and right views counted at 0.3 (docs/decisions.md, "The teacher, fourth round").
DEFAULT_TEACHER_VIEWS = ("centre", "left", "right")
DEFAULT_TEACHER_VIEW_WEIGHTS = {"centre": 1.0, "left": 0.3, "right": 0.3}
#: Loss weights of the supervised fit (:func:`adapt` with ``depth=``): the scale-invariant depth
#: term alone, no regulariser (the ground truth decides the correction).
SUPERVISED_WEIGHTS = {"reproj": 0.0, "smooth": 0.0, "l2": 0.0, "tv": 0.0, "pose": 0.0, "depth": 1.0}
#: Loss weights of the teacher-only fit (:meth:`AdaptConfig.teacher_only`): the pinhole-view
#: teacher term alone (:mod:`~raytun3r_plugin.adaptation.teacher`), no match term.
TEACHER_WEIGHTS = {**SUPERVISED_WEIGHTS, "depth": 0.0, "teacher": 1.0}

#: The ``default`` recipe's Adam step where the backbone's family declares none (docs/adaptation.md,
#: "Choosing the defaults"); ``AdaptConfig.lr`` None resolves to it or to the family's.
RECIPE_LR = 3e-3

# Configuration fields that may change between an interrupted run and its resumption.
_RESUMABLE_CHANGES = {"steps", "checkpoint_every", "cache_dir"}


@dataclass
class AdaptConfig:
    """Settings of :func:`adapt`. The field defaults are the ``default`` recipe
    (:mod:`~raytun3r_plugin.adaptation.recipes`, docs/recipes.md): ``AdaptConfig()`` is the fit
    that works by default, and :meth:`from_recipe` gives another named recipe.

    Attributes:
        steps: optimisation steps, one 3-frame window each (300 = 10 passes over 30 windows).
        lr: Adam step size. None (the ``default`` recipe's): the recipe's step as the model's
            backbone family declares it, resolved when the fit starts
            (:meth:`resolved_for`): the family's ``lr`` (and with it its
            ``lr_without_teacher``, unless one is given) where it declares one (the DA3 family:
            1e-2 where the teacher is on, 3e-3 where it is off), else :data:`RECIPE_LR`. So
            ``AdaptConfig(steps=100)`` fits any backbone with its family's step, as ``adapt()``
            without a config does; a number is the step of every fit of this config.
        clip: gradient-norm clipping threshold (None = no clipping).
        weights: loss weights (:data:`DEFAULT_WEIGHTS`; the paper's are the ``paper`` recipe's).
        input_size: long side of the network input in pixels (rounded to the patch size);
            None (the default): the backbone's own (:func:`~raytun3r_plugin.registry.native_input_size`:
            504 for DA3 and Pi3, 518 for VGGT, 512 for VGGT-Omega, 112 for the built-in networks),
            resolved by :func:`adapt`.
        n_windows: number of 3-frame windows spread over the segment.
        window_size: frames per window.
        stride: frame step inside a window.
        min_motion_px: windows whose mean correspondence displacement is below this (native
            pixels) are static and skipped.
        matcher: name of a registered matcher (``"dis"``, ``"sift"``, ...).
        matcher_options: keyword arguments of the matcher factory.
        max_matches: matches per ordered pair used in one step (a seeded random subset, drawn
            again every step); 0 = all.
        seed: seeds the window order, the match subsets and the MAGSAC++ estimation.
        checkpoint_every: write a checkpoint every this many steps (0 = only at the end and
            on interruption); needs ``out_path``.
        cache_dir: folder of the adaptation-set cache (matches + targets); None = no cache.
        sequence_id: identity of the frames for the cache key (None hashes the image bytes).
        pose_source: ``"model"`` uses the network's predicted relative poses (the paper);
            ``"targets"`` takes them from the MAGSAC++ targets instead, for backbones whose pose
            head is unusable: the unit translation is scaled per pair in closed form to agree
            with the predicted depth, only pairs with a usable target contribute to the
            reprojection term, and the pose term is dropped (it would compare the targets with
            themselves); ``"hybrid"`` reprojects through the targets as ``"targets"`` does (the
            scale-correct depth signal of issue 12) and keeps the paper's pose term on the
            network's own relative pose, so the fit can move the pose head towards the same
            targets (for backbones whose pose head works; issue 13, docs/adaptation.md);
            ``"both"`` adds the two reprojections (through the network's pose and through the
            targets, one mean over both) and keeps the pose term, so the depth signal of the
            targets and the rotation signal of the network's own reprojection act together.
        depth_convention: ``"range"`` (depth = distance along the unit ray, the fisheye
            default) or ``"z"`` (z-depth; FOV below 180 degrees only).
        components: corrections switched on during adaptation (None = all).
        scale: with ``pose_source="targets"``, how the unit target translation is scaled to the
            predicted depth: ``"pixel"`` (default, :func:`~raytun3r_plugin.adaptation.losses.pixel_optimal_scale`:
            the scale that minimises the robust pixel residual, held fixed for the gradient) or
            ``"least_squares"`` (the 3-D least-squares scale, dominated by far points) or
            ``"photometric"`` (:func:`~raytun3r_plugin.adaptation.photometric.photometric_optimal_scale`:
            the length that best aligns the frames densely, near road included, on
            ``photo_pixels`` pixels blurred by ``photo_sigma``; detached).
        robust_px: scale ``c`` of the log-L1 reprojection penalty ``c log(1 + e / c)`` in input
            pixels; None = the paper's plain L1.
        pe_regulariser: ``"relative"`` (default): L2 and TV of the PE correction divided by the
            backbone's PE energy ``mean_k ||P_A[k]||^2`` (:func:`~raytun3r_plugin.adaptation.losses.pe_energy`),
            so the weights need no retuning per backbone; ``"absolute"``: in PE units, as the paper.
        guard: stop a fit whose depth collapses and roll the tables back to the last healthy
            check (:func:`depth_health`), every ``guard_every`` steps.
        guard_every: steps between two collapse checks.
        min_parallax_px: self-supervised fit only: before fitting, drop every window whose
            matches move less than this many input pixels per unit log depth (median over the
            window, at the fit's own translation scale and the starting adapter's depth;
            :func:`~raytun3r_plugin.adaptation.parallax.window_parallax`): such matches cannot tell
            near from far, and fitting to them moved the tables by noise and smoothness alone
            (outdoors at 112 px: d_reproj rose on every sequence). When no window is left the
            fit stops at once with the verdict "no signal" and the tables stay as they started.
            0 keeps every window. docs/adaptation.md section 6.
        pose_gate: self-supervised fit with a pose term only: before fitting, measure the
            network's *responsiveness* on the adaptation set with the starting tables (the
            median angle of its own relative rotations over the MAGSAC++ targets' median
            angle, :func:`~raytun3r_plugin.adaptation.pose_gate.pose_agreement`); below this
            value the head answers "no rotation" whatever the input, and the fit runs with
            ``pose_source="targets"`` (no pose term) instead of bending the tables towards
            making a head at chance reproduce the targets. ``training_info["pose_gate"]``
            records the measurement. None: no gate (left out of :meth:`to_dict`, so existing
            identities are unchanged). docs/decisions.md, "The pose gate, second form".
        pose_windows: ``"all"`` (default): the pose term scores every window's pairs;
            ``"unreprojected"`` (only with ``pose_source="hybrid"``): only the windows whose
            matches the parallax gate leaves out of the reprojection term (kept for the
            teacher), so the term stands in for the reprojection where the matches carry no
            depth signal and leaves the tables to the targets' reprojection where they do.
            Left out of :meth:`to_dict` when ``"all"``. docs/decisions.md, "The pose term where
            the matches carry no depth".
        check_frames: trailing frames of the last segment kept out of the fit and scored after
            it with the starting and the fitted tables (the held-out reprojection check,
            ``training_info["check"]``; :mod:`~raytun3r_plugin.adaptation.check`); ``"auto"``: a
            fifth of the segment (at least 3) when it has at least 15 frames, else none; 0 (the
            default): none. Left out of :meth:`to_dict` when 0.
        check_veto: with check frames: put the starting tables back when the fit raises the
            check's error by more than this fraction (0.02 = 2 %; verdict ``"not kept"``); a check
            that cannot be scored keeps the fit. None: the fit is kept whatever the check says.
            Left out of :meth:`to_dict` when None. docs/decisions.md, "A held-out check that
            decides whether a fit is kept".
        lr_without_teacher: the Adam step size of a self-supervised fit whose teacher term is
            off (the lens gate turned it off, or its weight is 0), in place of ``lr``; the
            fit's recorded settings show the step it ran with. A larger ``lr`` can then be
            used where the teacher's dense targets anchor the fit while the matches alone keep
            a smaller one. None (the default): ``lr`` whatever the teacher; left out of
            :meth:`to_dict` when None. The DA3 family's ``default`` fits set it (3e-3, with
            ``lr`` 1e-2); :meth:`from_recipe` given an ``lr`` without it drops it, so a step
            the user chooses is the step everywhere. docs/decisions.md, "The step size where
            the teacher is on".
        refine_intrinsics: before fitting, refine the camera's focal and first distortion term
            jointly with the pairs' relative poses from the adaptation set's matches
            (:func:`~raytun3r_plugin.adaptation.intrinsics.refine_intrinsics`, docs/intrinsics.md)
            and fit (and save) the adapter with the refined camera. Off by default; when off it
            is left out of :meth:`to_dict` so existing identities and checkpoints are unchanged.
        photo_sigma: with ``weights.photo > 0`` (the dense photometric term,
            :func:`~raytun3r_plugin.adaptation.photometric.photometric_loss`): the Gaussian blur of
            both frames, in input pixels. With the term on, the parallax gate records its window
            medians but drops no window: the photometric term carries the depth signal that
            far-only matches lack.
        photo_pixels: with ``weights.photo > 0``: pixels of frame ``i`` warped per ordered pair
            and step (a seeded random subset of the valid region, drawn again every step).
        teacher_views: with ``weights.teacher > 0`` (the pinhole-view teacher,
            :mod:`~raytun3r_plugin.adaptation.teacher`): which virtual pinhole views of each
            window the unpatched model predicts, out of ``"centre"``, ``"right"``, ``"left"``,
            ``"down"``, ``"up"`` (the Multi-PH views). With the term on, the parallax gate keeps
            every window for it and drops only the reprojection of the windows below the gate.
        teacher_view_weights: with ``weights.teacher > 0``: each teacher view's share of the
            term, ``{view name: weight >= 0}`` naming exactly the views of ``teacher_views``;
            the term is then the weighted *sum* of the views' losses (not renormalised), which
            ``weights.teacher`` scales. None (the default) is the mean over the views (a weight
            of ``1 / len(teacher_views)`` each). On the development sequences the side views'
            depth fixed the far field and hurt the near one, so a fit can keep them but count
            them less (docs/decisions.md, "The teacher, fourth round"). Left out of
            :meth:`to_dict` when None, so existing identities are unchanged.
        teacher_fov_deg: the views' field of view across their width, degrees.
        recipe: the name of the recipe these settings start from (:meth:`from_recipe` sets it;
            ``"default"`` otherwise). The adapter file records it with its version and every
            setting that differs from it (:meth:`recipe_record`); it takes no part in
            :meth:`identity`.
        teacher_max_coverage: the teacher term is used only when none of its views covers more
            than this fraction of the lens's valid pixels (0.5: lenses wider than about 160
            degrees for the 110-degree centre view); on a lens a view covers almost entirely it
            shows the network what the fisheye shows it, resampled, and the term made depth
            worse on the development sequences (docs/adaptation.md section 6). The fit then runs
            without it; ``training_info["teacher"]`` records the coverage and the choice.
    """

    steps: int = 300
    lr: float | None = None
    clip: float | None = 1.0
    weights: LossWeights = field(default_factory=lambda: LossWeights(**DEFAULT_WEIGHTS))
    input_size: int | None = None
    n_windows: int = 30
    window_size: int = 3
    stride: int = 1
    min_motion_px: float = 2.0
    matcher: str = "dis"
    matcher_options: dict = field(default_factory=dict)
    max_matches: int = 4096
    seed: int = 0
    checkpoint_every: int = 50
    cache_dir: str | None = None
    sequence_id: str | None = None
    pose_source: str = "hybrid"
    depth_convention: str = "range"
    components: list[str] | None = None
    scale: str = "pixel"
    robust_px: float | None = 1.0
    pe_regulariser: str = "relative"
    guard: bool = True
    guard_every: int = 25
    min_parallax_px: float = 0.3
    pose_gate: float | None = None
    pose_windows: str = "all"
    check_frames: int | str = 0
    check_veto: float | None = None
    lr_without_teacher: float | None = None
    refine_intrinsics: bool = False
    photo_sigma: float = 1.0
    photo_pixels: int = 4096
    teacher_views: tuple[str, ...] = DEFAULT_TEACHER_VIEWS
    teacher_view_weights: dict[str, float] | None = field(
        default_factory=lambda: dict(DEFAULT_TEACHER_VIEW_WEIGHTS)
    )
    teacher_fov_deg: float = 110.0
    teacher_max_coverage: float = 0.5
    recipe: str = "default"

    def __post_init__(self) -> None:
        if isinstance(self.weights, Mapping):
            self.weights = LossWeights(**self.weights)
        if isinstance(self.teacher_views, str):
            self.teacher_views = (self.teacher_views,)
        self.teacher_views = tuple(self.teacher_views)
        if isinstance(self.teacher_view_weights, Mapping):
            self.teacher_view_weights = dict(self.teacher_view_weights)
        if (
            self.teacher_view_weights == DEFAULT_TEACHER_VIEW_WEIGHTS
            and self.teacher_views != DEFAULT_TEACHER_VIEWS
        ):
            # The default weights name the default views: other views, given without weights
            # of their own, count equally.
            self.teacher_view_weights = None
        if self.cache_dir is not None:
            self.cache_dir = str(self.cache_dir)
        self.check_frames = check_settings(vars(self))

    def view_weights(self) -> tuple[float, ...] | None:
        """The teacher views' weights in the order of :attr:`teacher_views` (the order of the
        teacher targets' view index), or None for the mean over the views."""
        if self.teacher_view_weights is None:
            return None
        return tuple(float(self.teacher_view_weights[name]) for name in self.teacher_views)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (``AdaptConfig(**d)`` rebuilds it)."""
        out = asdict(self)
        # Only recorded when on: the identity (and so every checkpoint and adapter file) of a
        # configuration that does not use it stays what it was before the field existed.
        if not self.refine_intrinsics:
            del out["refine_intrinsics"]
        if self.pose_gate is None:
            del out["pose_gate"]
        if self.pose_windows == "all":
            del out["pose_windows"]
        if self.check_frames == 0:
            del out["check_frames"]
        if self.check_veto is None:
            del out["check_veto"]
        if self.lr_without_teacher is None:
            del out["lr_without_teacher"]
        out["weights"] = self.weights.as_dict()
        if not self.weights.photo and self.scale != "photometric":
            del out["photo_sigma"], out["photo_pixels"]
        if self.weights.teacher:
            out["teacher_views"] = list(self.teacher_views)
        else:
            del out["teacher_views"], out["teacher_fov_deg"], out["teacher_max_coverage"]
        if not self.weights.teacher or self.teacher_view_weights is None:
            out.pop("teacher_view_weights", None)
        return out

    @classmethod
    def from_recipe(
        cls, name: str = "default", *, model: nn.Module | None = None, **changes: Any
    ) -> AdaptConfig:
        """The settings of the named recipe (:data:`~raytun3r_plugin.adaptation.recipes.RECIPES`),
        with ``changes`` on top.

        Args:
            name: a recipe name (``raytun3r_plugin.adaptation.recipes.recipe_names()``).
            model: the backbone to fit, when known: its family's declared changes to this recipe
                (``BackboneSpec.recipe_changes``) apply between the recipe and ``changes``.
            changes: any field. ``weights`` given as a mapping changes only the terms it names
                (``weights={"pose": 1.0}``); a :class:`LossWeights` replaces them all. An ``lr``
                without ``lr_without_teacher`` is the step of every fit: the recipe's or the
                family's ``lr_without_teacher`` is dropped with it.

        Raises:
            InputError: an unknown recipe or field, or a value the fields refuse.
        """
        from raytun3r_plugin.adaptation.recipes import get_recipe

        recipe = get_recipe(name)
        settings: dict[str, Any] = {}
        for layer in (recipe.changes, _family_changes(model, name), changes):
            for key, value in layer.items():
                if key not in _FIELDS:
                    raise InputError(
                        f"AdaptConfig has no field {key!r} (recipe {name!r}); fields: "
                        f"{', '.join(sorted(_FIELDS))}"
                    )
                if key == "weights" and isinstance(value, Mapping):
                    base = settings.get("weights", DEFAULT_WEIGHTS)
                    base = base.as_dict() if isinstance(base, LossWeights) else dict(base)
                    value = {**base, **value}
                settings[key] = value
        if "lr" in changes and "lr_without_teacher" not in changes:
            # A step the user chose is not to be undone, where the teacher is off, by a
            # smaller one the family declared beside its own larger ``lr``.
            settings.pop("lr_without_teacher", None)
        return cls(**{**settings, "recipe": recipe.name})

    @classmethod
    def supervised(cls, **changes: Any) -> AdaptConfig:
        """The ``supervised`` recipe (:func:`adapt` with ``depth=``): the scale-invariant log
        depth loss alone, Adam lr 3e-2, no regularisers, no collapse guard (the ground truth
        cannot collapse); ``changes`` override any field."""
        return cls.from_recipe("supervised", **changes)

    @classmethod
    def teacher_only(cls, **changes: Any) -> AdaptConfig:
        """The ``teacher-only`` recipe: :data:`TEACHER_WEIGHTS`, the supervised fit's optimiser
        (Adam lr 3e-2, no regulariser, no collapse guard: the targets hold the depth in place),
        the 110-degree centre view; ``changes`` override any field. No match enters the
        objective (windows are still chosen from the matches)."""
        return cls.from_recipe("teacher-only", **changes)

    def resolved_for(self, model: nn.Module | None) -> AdaptConfig:
        """These settings with what they leave to the backbone resolved for ``model``: an
        ``input_size`` of None to its own (:func:`~raytun3r_plugin.registry.native_input_size`),
        an ``lr`` of None to its family's step for this recipe (:attr:`lr`); unchanged
        otherwise. :func:`adapt` fits, records and checkpoints the resolved settings. Without a
        model the step is the recipe's own (:data:`RECIPE_LR`) and the size stays None."""
        resolved: dict[str, Any] = {}
        if self.input_size is None and model is not None:
            from raytun3r_plugin.registry import native_input_size

            resolved["input_size"] = native_input_size(model)
        if self.lr is None:
            family = _family_changes(model, self.recipe)
            resolved["lr"] = family.get("lr", RECIPE_LR)
            if self.lr_without_teacher is None and "lr" in family:
                resolved["lr_without_teacher"] = family.get("lr_without_teacher")
        return dataclasses.replace(self, **resolved) if resolved else self

    def step_size(self) -> float:
        """The Adam step of a fit with these (resolved) settings.

        Raises:
            InputError: ``lr`` is still left to the backbone (call :meth:`resolved_for` first).
        """
        if self.lr is None:
            raise InputError(
                "AdaptConfig.lr is left to the backbone: resolve it with resolved_for(model)"
            )
        return float(self.lr)

    def recipe_record(self, model: nn.Module | None = None) -> dict[str, Any]:
        """What an adapter file records about the recipe: ``{"name", "version", "changes"}``,
        where ``changes`` maps every fit setting that differs from the recipe (a loss weight as
        ``"weights.<term>"``), both sides with ``model``'s family changes and resolved for it
        (:meth:`resolved_for`: its input size, its step), to ``[recipe's value, this value]``;
        ``backbone_changes`` lists the family's declared changes when there are any. Where files
        go and how often checkpoints are written
        (:data:`~raytun3r_plugin.adaptation.recipes.BOOKKEEPING_FIELDS`) are not settings."""
        from raytun3r_plugin.adaptation.recipes import BOOKKEEPING_FIELDS, get_recipe

        recipe = get_recipe(self.recipe)
        # What either side leaves to the backbone (its size, its step) is the backbone's.
        ours = self.resolved_for(model)
        reference = AdaptConfig.from_recipe(recipe.name, model=model).resolved_for(model)
        ours_flat, theirs = _flat(ours.to_dict()), _flat(reference.to_dict())
        changed = {
            key: [theirs.get(key), ours_flat.get(key)]
            for key in sorted(set(ours_flat) | set(theirs))
            if key not in BOOKKEEPING_FIELDS and ours_flat.get(key) != theirs.get(key)
        }
        record: dict[str, Any] = {
            "name": recipe.name,
            "version": recipe.version,
            "changes": changed,
        }
        family = _family_changes(model, recipe.name)
        if family:
            record["backbone_changes"] = {key: _jsonable(v) for key, v in family.items()}
        return record

    def identity(self) -> str:
        """Hash of the settings that must not change when a checkpoint is resumed."""
        kept = {
            k: v for k, v in self.to_dict().items() if k not in _RESUMABLE_CHANGES and k != "recipe"
        }
        return hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest()[
            :16
        ]


_FIELDS = frozenset(AdaptConfig.__dataclass_fields__)


def _family_changes(model: nn.Module | None, recipe: str) -> Mapping[str, Any]:
    """The changes ``model``'s backbone family declares for ``recipe`` (empty without a model)."""
    if model is None:
        return {}
    from raytun3r_plugin.registry import spec_for

    spec, _ = spec_for(model)
    return spec.recipe_changes.get(recipe, {})


def _jsonable(value: Any) -> Any:
    if isinstance(value, LossWeights):
        return value.as_dict()
    if isinstance(value, tuple):
        return list(value)
    return value


def _flat(settings: dict[str, Any]) -> dict[str, Any]:
    """``to_dict()`` with the loss weights as ``weights.<term>`` entries (a term that is off is 0)."""
    out = {k: v for k, v in settings.items() if k != "weights"}
    for term, weight in settings.get("weights", {}).items():
        out[f"weights.{term}"] = weight
    for term in ("photo", "teacher"):
        out.setdefault(f"weights.{term}", 0.0)
    return out
