"""The backbone as a fit runs it: frozen, in eval mode, and (for measurements) patched with an
adapter without gradients; everything restored afterwards.

Used by the optimisation loop, the objective, the parallax and pose gates.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import torch
from torch import nn

from raytun3r_plugin.patching import RaytunHandle, apply

if TYPE_CHECKING:
    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.problem import AdaptationProblem
    from raytun3r_plugin.adapter import Adapter

__all__ = ["frozen_backbone", "patched_as_fitted", "patched_for_evaluation"]


def patched_as_fitted(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> RaytunHandle:
    """``model`` patched with ``adapter`` for ``problem``'s camera, components and scene mask, as
    a fit patches it (a handle that is also a context manager: ``with ...:`` removes it)."""
    return apply(
        model,
        problem.layout.native_camera,
        adapter,
        components=config.components,
        strict=False,
        mask=problem.mask,
    )


@contextmanager
def frozen_backbone(model: nn.Module) -> Iterator[None]:
    """Backbone parameters without gradients and every module in eval mode; restored after."""
    flags = [(parameter, parameter.requires_grad) for parameter in model.parameters()]
    modes = [(module, module.training) for module in model.modules()]
    try:
        for parameter, _ in flags:
            parameter.requires_grad_(False)
        model.eval()
        yield
    finally:
        for parameter, flag in flags:
            parameter.requires_grad_(flag)
        for module, mode in modes:
            module.training = mode


@contextmanager
def patched_for_evaluation(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> Iterator[None]:
    """``model`` frozen, in eval mode, without gradients and patched with ``adapter`` as the fit
    patches it; everything restored afterwards."""
    with (
        frozen_backbone(model),
        torch.no_grad(),
        patched_as_fitted(model, adapter, problem, config),
    ):
        yield
