"""Does the network's own relative pose agree with the matches, and does it turn at all? The
measurement behind the pose gate (``AdaptConfig.pose_gate``).

The pose term pulls the network's relative pose towards the MAGSAC++ estimates from the matches.
On a network whose pose output is no better than "no rotation" (the built-in v2) that pull is
noise for the tables to fit, so a fit measures first, on its own adaptation set and with its
starting tables, how far the network's relative rotations are from the targets and how far "no
rotation" is; the recipe keeps the pose term only where the network is clearly closer
(docs/decisions.md, "The pose gate").
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

import torch

from raytun3r_plugin import poses
from raytun3r_plugin.adaptation.evaluation import patched_for_evaluation
from raytun3r_plugin.adaptation.settings_check import POSE_TERM_SOURCES
from raytun3r_plugin.prediction import predict

if TYPE_CHECKING:
    from torch import nn

    from raytun3r_plugin.adaptation.config import AdaptConfig
    from raytun3r_plugin.adaptation.problem import AdaptationProblem
    from raytun3r_plugin.adapter import Adapter

__all__ = ["gate_pose_term", "pose_agreement"]


def pose_agreement(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> dict[str, Any]:
    """Median rotation error of the network's relative poses and of "no rotation" against the
    pairs' MAGSAC++ targets, over every pair with a target in ``problem``'s windows.

    Each window is one forward of ``model`` patched with ``adapter`` (frozen, in eval mode,
    restored afterwards), as the fit runs it.

    Returns:
        ``{"pairs": n, "network_deg": median error of the network, "no_rotation_deg": median
        rotation angle of the targets, "ratio": network / no rotation, "network_rotation_deg":
        median angle of the network's own relative rotations, "responsiveness": that angle /
        the targets' median angle}``, angles in degrees; a head that answers "no rotation"
        whatever the input has responsiveness near 0. NaN without a pair.
    """
    network, identity, own = [], [], []
    with patched_for_evaluation(model, adapter, problem, config):
        for index, (_window, pairs) in enumerate(problem.windows):
            targets = [(pair, pair.rotation) for pair in pairs if pair.rotation is not None]
            if not targets:
                continue
            cam_from_world = predict(model, problem.batch(index)[None]).cam_from_world[0]
            cam_from_world = cam_from_world.detach().double().cpu()
            for pair, target in targets:
                relative = poses.relative_pose(cam_from_world, pair.a, pair.b)
                rotation = target.detach().double().cpu()
                network.append(float(poses.rotation_angle(rotation, relative[:3, :3])))
                identity.append(float(poses.rotation_angle(rotation, torch.eye(3).double())))
                own.append(float(poses.rotation_angle(relative[:3, :3], torch.eye(3).double())))
    if not network:
        nan = math.nan
        return {
            "pairs": 0,
            "network_deg": nan,
            "no_rotation_deg": nan,
            "ratio": nan,
            "network_rotation_deg": nan,
            "responsiveness": nan,
        }
    net = math.degrees(float(torch.tensor(network).median()))
    none = math.degrees(float(torch.tensor(identity).median()))
    turned = math.degrees(float(torch.tensor(own).median()))
    return {
        "pairs": len(network),
        "network_deg": round(net, 4),
        "no_rotation_deg": round(none, 4),
        "ratio": round(net / none, 4) if none > 0 else math.inf,
        "network_rotation_deg": round(turned, 4),
        "responsiveness": round(turned / none, 4) if none > 0 else math.inf,
    }


def gate_pose_term(
    model: nn.Module, adapter: Adapter, problem: AdaptationProblem, config: AdaptConfig
) -> tuple[AdaptConfig, dict[str, Any] | None]:
    """The settings a self-supervised fit runs with after the pose gate, and the gate's record.

    With ``config.pose_gate`` set and a pose term in the objective, the network's
    responsiveness is measured on ``problem`` with ``adapter``'s (starting) tables; below the
    gate the returned settings reproject through the targets alone (``pose_source="targets"``:
    no pose term). A NaN measurement (no pair with a target) is no evidence: the pose term stays.

    Returns:
        ``(settings, record)``; the record is None when the gate does not apply, else
        :func:`pose_agreement`'s measurement with ``"threshold"`` and ``"pose_term"`` (kept).
    """
    if (
        config.pose_gate is None
        or config.pose_source not in POSE_TERM_SOURCES
        or config.weights.pose <= 0
    ):
        return config, None
    agreement = pose_agreement(model, adapter, problem, config)
    switch = bool(agreement["responsiveness"] < config.pose_gate)  # NaN < x is False
    record = {**agreement, "threshold": config.pose_gate, "pose_term": not switch}
    if switch:
        config = dataclasses.replace(config, pose_source="targets", pose_windows="all")
    return config, record
