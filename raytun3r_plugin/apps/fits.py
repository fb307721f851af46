"""The fit settings the demo, the benchmark and the benchmark scripts use: a recipe
(:mod:`raytun3r_plugin.adaptation.recipes`) at a size and a budget, and its description for their
headers. One home, so the demo and the benchmark cannot drift apart."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any


def adapt_config(
    size: int,
    steps: int,
    *,
    recipe: str = "default",
    pose_weight: float | None = None,
    teacher_weight: float | None = None,
    model=None,
    **changes,
):
    """The recipe ``recipe`` (:mod:`raytun3r_plugin.adaptation.recipes`) at input ``size`` px
    and ``steps`` steps, without intermediate checkpoints: the fits of the demo, the benchmark
    and the benchmark scripts.

    ``pose_weight`` and ``teacher_weight`` change only that loss term's weight
    (``weights={"pose": ...}``); ``changes`` change any other field. Everything not given is the
    recipe's, with the changes ``model``'s backbone family declares for it
    (``BackboneSpec.recipe_changes``) when ``model`` is given, as ``adapt()`` fits it: nothing
    is keyed by a network's name. Without ``model`` it is the recipe alone, its step included
    (:data:`~raytun3r_plugin.adaptation.config.RECIPE_LR` where the recipe leaves the step to the
    backbone).
    """
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.errors import InputError

    terms = {
        name: float(value)
        for name, value in (("pose", pose_weight), ("teacher", teacher_weight))
        if value is not None
    }
    if terms and "weights" in changes:
        raise InputError(
            "adapt_config: give pose_weight or weights, not both (likewise teacher_weight)"
        )
    if terms:
        changes["weights"] = terms
    for key in ("teacher_views", "teacher_view_weights"):
        if key in changes and changes[key] is None:
            del changes[key]  # None: the recipe's
    if "teacher_views" in changes:
        changes["teacher_views"] = tuple(changes["teacher_views"])
    config = AdaptConfig.from_recipe(
        recipe,
        model=model,
        **{"steps": steps, "input_size": size, "checkpoint_every": 0, **changes},
    )
    if model is None:
        # The recipe alone: its own step, not left to a family to resolve at fit time, so an
        # experiment measures again what it measured when its decision was made.
        config = config.resolved_for(None)
    return config


def fit_description(config, model=None) -> str:
    """A fit's settings in one line for the demo's and the benchmark's headers: the recipe, the
    changes ``model``'s backbone family declares for it, what was changed from both, and the
    teacher in words."""
    teacher = teacher_settings(config)
    return (
        recipe_text(config.recipe_record(model), leave_out=("input_size",))
        + f", pose source '{config.pose_source}', pose weight {config.weights.pose:g}"
        + (f", {teacher}" if teacher else "")
    )


def recipe_text(
    record: Mapping[str, Any], *, with_old: bool = False, leave_out: tuple[str, ...] = ()
) -> str:
    """A fit's recipe record (``AdaptConfig.recipe_record``, ``training_info["recipe"]``) in one
    line, in the order the settings apply: ``recipe 'default' v1 (the backbone family's: lr 0.01)
    (changed: steps 100)``. ``with_old`` writes each change as ``old -> new`` and says so when
    nothing changed; ``leave_out`` names changes not to write."""
    changes = {
        key: pair for key, pair in (record.get("changes") or {}).items() if key not in leave_out
    }
    family = record.get("backbone_changes") or {}
    text = f"recipe '{record['name']}' v{record.get('version')}"
    if family:
        text += f" (the backbone family's: {settings_text(family)})"
    if with_old:
        changed = "; ".join(
            f"{key} {setting_text(old)} -> {setting_text(new)}"
            for key, (old, new) in changes.items()
        )
        quiet = "nothing else changed" if family else "as the recipe is"
        return text + f" ({'changed: ' + changed if changed else quiet})"
    changed = settings_text({key: new for key, (_, new) in changes.items()})
    return text + (f" (changed: {changed})" if changed else "")


def setting_text(value: Any) -> str:
    """One fit setting's value in a line: numbers short, lists and mappings written out."""
    if isinstance(value, float):
        return f"{value:.3g}"
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value, sort_keys=True)
    return str(value)


def settings_text(settings: Mapping[str, Any]) -> str:
    """Fit settings in a line of text: ``{"lr": 0.01, "steps": 3}`` -> ``"lr 0.01, steps 3"``."""
    return ", ".join(f"{key} {setting_text(value)}" for key, value in settings.items())


def teacher_settings(config) -> str:
    """The pinhole-view teacher settings of ``config`` (an ``AdaptConfig``) in words, for the
    demo's and the benchmark's headers; ``""`` when its teacher term has no weight."""
    if not config.weights.teacher:
        return ""
    views = config.teacher_views
    weights = config.teacher_view_weights
    return (
        f"pinhole-view teacher weight {config.weights.teacher:g} on the "
        f"{config.teacher_fov_deg:g}-degree {' + '.join(views)} view{'s' if len(views) > 1 else ''}"
        + (
            " (weights " + ", ".join(f"{v} {weights[v]:g}" for v in views) + ")"
            if weights is not None
            else ""
        )
        + f" where each covers at most {config.teacher_max_coverage:.0%} of the lens"
    )


def supervised_config(size: int, steps: int, **changes):
    """The supervised fit (ground-truth depth) the demo and the benchmark report as the upper
    bound: the ``supervised`` recipe at input ``size`` px, the same windows and poses as
    :func:`adapt_config`."""
    return adapt_config(size, steps, recipe="supervised", **changes)
