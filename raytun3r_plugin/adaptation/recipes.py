"""Named fit recipes: the one home of the settings an adaptation uses.

A recipe is a name, a version and the :class:`~raytun3r_plugin.adaptation.config.AdaptConfig`
fields it sets. ``AdaptConfig()`` *is* the ``default`` recipe (its field defaults are that
recipe's settings); every other recipe lists what it changes from them. ``adapt()`` without a
config, ``raytun3r adapt`` without fit options, the demo, the benchmark and every benchmark
script take their settings from here (``AdaptConfig.from_recipe(name, **changes)``), and an
adapter file records the recipe's name and version and every setting that differs from it
(``training_info["recipe"]``, shown by ``raytun3r inspect``).

Where a backbone family needs other settings, its :class:`~raytun3r_plugin.registry.BackboneSpec`
declares them as data (``recipe_changes``, with the measurement beside it): the DA3 family's
``default`` fits take a larger step where the pinhole-view teacher is on.
Nothing here is keyed by the name of a particular network.

How each recipe was chosen, with the numbers and the rules written before each held-out run:
``docs/decisions.md``. When to choose which: ``docs/recipes.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from raytun3r_plugin.errors import InputError

__all__ = ["BOOKKEEPING_FIELDS", "RECIPES", "Recipe", "get_recipe", "recipe_names"]

#: Fields that say where a run keeps its files, how often it saves or which of the frames it was
#: given it keeps out for the held-out check (the file's segment record says what was fitted),
#: not how it fits: an adapter file does not list them among the settings that differ from its
#: recipe.
BOOKKEEPING_FIELDS = frozenset(
    {"cache_dir", "sequence_id", "checkpoint_every", "recipe", "check_frames"}
)


@dataclass(frozen=True)
class Recipe:
    """One named set of fit settings.

    Attributes:
        name: what users type (``--recipe NAME``, ``AdaptConfig.from_recipe(NAME)``).
        version: raised whenever the settings change, so an adapter file's record
            ``(name, version)`` names exactly one set of settings.
        summary: one line for ``--help``, ``raytun3r inspect`` and the docs.
        changes: the ``AdaptConfig`` fields this recipe sets, relative to the field defaults
            (the ``default`` recipe); ``"weights"`` as a mapping of the loss terms it changes.
        supervised: the recipe fits to ground-truth depth (``adapt(..., depth=...)``).
        needs_poses: the recipe fits to ground-truth poses (``adapt(..., poses=...)``).
        evidence: where the measurement that chose it is written.
    """

    name: str
    version: int
    summary: str
    changes: Mapping[str, Any] = field(default_factory=dict)
    supervised: bool = False
    needs_poses: bool = False
    evidence: str = ""


def _only(term: str) -> dict[str, float]:
    """Loss weights with ``term`` at 1 and every other term of the objective off."""
    terms = ("reproj", "smooth", "l2", "tv", "pose", "depth", "teacher")
    return {name: 1.0 if name == term else 0.0 for name in terms}


#: The pose term alone through the network's own pose head: fitted to ground-truth relative
#: poses it is the pose oracle, to the MAGSAC++ targets of the matches the trajectory recipe.
_POSE_ONLY = {
    "pose_source": "model",
    "lr": 1e-2,
    "weights": _only("pose"),
    "min_parallax_px": 0.0,
    "guard": False,
}


#: The recipes, by name. ``default``'s settings are ``AdaptConfig``'s field defaults.
RECIPES: dict[str, Recipe] = {
    recipe.name: recipe
    for recipe in (
        Recipe(
            "default",
            1,
            "the fit that works by default: reprojection through the MAGSAC++ targets, the "
            "paper's pose term at 0.3, and on lenses wider than about 160 degrees the "
            "pinhole-view teacher (weight 10, centre view and side views at 0.3)",
            evidence="docs/decisions.md: 'Pose source and pose weight', 'The lens-gated "
            "teacher', 'The teacher, fourth round', 'One default recipe for every network'",
        ),
        Recipe(
            "paper",
            1,
            "the paper's objective as written: reprojection through the network's own pose, "
            "weights 1 / 10 / 2 / 20 / 1 in absolute PE units, plain L1, Adam lr 1e-3, "
            "no parallax gate, no teacher",
            changes={
                "pose_source": "model",
                "weights": {
                    "reproj": 1.0,
                    "smooth": 10.0,
                    "l2": 2.0,
                    "tv": 20.0,
                    "pose": 1.0,
                    "teacher": 0.0,
                },
                "pe_regulariser": "absolute",
                "robust_px": None,
                "lr": 1e-3,
                "min_parallax_px": 0.0,
            },
            evidence="the paper, 'Adapter training'; docs/adaptation.md, 'Choosing the defaults'",
        ),
        Recipe(
            "matches",
            1,
            "matches alone: reprojection through the network's own pose with the pose term, "
            "the regularisers relative to the backbone's PE energy, no teacher (the "
            "library's self-supervised fit before recipes)",
            changes={
                "pose_source": "model",
                "weights": {"pose": 1.0, "teacher": 0.0},
            },
            evidence="docs/adaptation.md, 'Choosing the defaults'",
        ),
        Recipe(
            "targets",
            1,
            "for a pose head no better than 'no rotation': reprojection through the MAGSAC++ "
            "targets alone, no pose term, no teacher",
            changes={
                "pose_source": "targets",
                "weights": {"pose": 1.0, "teacher": 0.0},
            },
            evidence="docs/decisions.md, 'The default built-in network and the pose source "
            "of its fits'",
        ),
        Recipe(
            "rig",
            1,
            "the default recipe without the teacher term, which the joint rig fit does not "
            "support: the rig fit's default",
            changes={
                "weights": {"teacher": 0.0},
            },
            evidence="docs/rigs.md",
        ),
        Recipe(
            "supervised",
            1,
            "the same tables fitted to ground-truth depth: the scale-invariant log depth loss "
            "alone, Adam lr 3e-2, no regulariser, no collapse guard",
            changes={
                "lr": 3e-2,
                "weights": _only("depth"),
                "guard": False,
            },
            supervised=True,
            evidence="docs/adaptation.md, 'Supervised fit'",
        ),
        Recipe(
            "pose-oracle",
            1,
            "the tables fitted to ground-truth relative poses (adapt(..., poses=...)): the pose "
            "term on the network's own pose alone, Adam lr 1e-2, no parallax gate, no guard; "
            "what the tables can do for pose",
            changes=_POSE_ONLY,
            needs_poses=True,
            evidence="docs/decisions.md, 'Rotation: the pose oracle and the components'",
        ),
        Recipe(
            "trajectory",
            1,
            "for camera trajectories rather than depth: the pose term alone, through the "
            "network's own pose head towards the MAGSAC++ relative poses of the matches (the "
            "pose oracle's settings without ground truth): Adam lr 1e-2, no parallax gate, no "
            "guard. Lowers rotation error where the default recipe does not; depth gets worse "
            "indoors",
            changes=_POSE_ONLY,
            evidence="docs/decisions.md, 'A trajectory recipe'",
        ),
        Recipe(
            "teacher-only",
            1,
            "the pinhole-view teacher alone (no match term): Adam lr 3e-2, no regulariser, no "
            "collapse guard, the 110-degree centre view",
            changes={
                "lr": 3e-2,
                "weights": _only("teacher"),
                "guard": False,
                "teacher_views": ("centre",),
                "teacher_view_weights": None,
            },
            evidence="docs/decisions.md, 'The pinhole-view teacher'",
        ),
    )
}


def recipe_names() -> list[str]:
    """The recipes' names, ``default`` first."""
    return sorted(RECIPES, key=lambda name: (name != "default", name))


def get_recipe(name: str) -> Recipe:
    """The recipe ``name``; :class:`InputError` naming the known ones otherwise."""
    try:
        return RECIPES[name]
    except (KeyError, TypeError):
        raise InputError(
            f"unknown fit recipe {name!r}; known recipes: {', '.join(recipe_names())}"
        ) from None
