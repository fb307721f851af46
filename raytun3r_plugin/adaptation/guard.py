"""The collapse guard of a self-supervised fit and the one-word verdict of a finished fit.

Part of :mod:`raytun3r_plugin.adaptation.train` (which re-exports the public names here).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn

from raytun3r_plugin.adaptation.losses import pe_correction_grid, pe_l2
from raytun3r_plugin.adaptation.problem import AdaptationProblem
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.prediction import predict

__all__ = ["GUARD_MIN_CORRELATION", "GUARD_SPREAD_RANGE", "depth_health", "fit_verdict"]

#: A fit is collapsing when the log-depth of the guard window correlates less than this with the
#: zero adapter's (structure lost) ...
GUARD_MIN_CORRELATION = 0.5
#: ... or when its spread (std of log depth) leaves this range of the zero adapter's.
GUARD_SPREAD_RANGE = (0.5, 2.0)


def depth_health(reference: torch.Tensor, current: torch.Tensor) -> tuple[float, float]:
    """(Pearson correlation, spread ratio) of two log-depth samples over the same pixels.

    The spread ratio is ``std(current) / std(reference)``. Together they catch the failure seen
    when the regularisers are off: an outdoor fit whose depth lost its structure (held-out
    AbsRel 0.22 -> 1.05) while its data terms still fell.
    """
    a = reference - reference.mean()
    b = current - current.mean()
    correlation = float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-12))
    spread = float(b.std() / a.std().clamp_min(1e-12))
    return correlation, spread


class _CollapseGuard:
    """Every ``guard_every`` steps: predict window 0 (of every camera, for a rig), compare its log-depth with the zero
    adapter's (:func:`depth_health`), keep a copy of the tables while healthy and restore the
    last healthy copy when not.

    ``min_correlation`` and ``spread_range`` default to :data:`GUARD_MIN_CORRELATION` and
    :data:`GUARD_SPREAD_RANGE`; :func:`~raytun3r_plugin.adaptation.train.adapt` passes the values
    its own module holds, so a test can tighten them there.
    """

    def __init__(
        self,
        problem: AdaptationProblem | None,
        min_correlation: float | None = None,
        spread_range: tuple[float, float] | None = None,
        *,
        images: torch.Tensor | None = None,
        valid: torch.Tensor | None = None,
    ) -> None:
        self.min_correlation = (
            GUARD_MIN_CORRELATION if min_correlation is None else float(min_correlation)
        )
        self.spread_range = tuple(GUARD_SPREAD_RANGE if spread_range is None else spread_range)
        # The views of one forward, (S, 3, H, W), and where their depth counts: (H, W) for one
        # camera's views, (S, H, W) per view (a rig forward lays several cameras' views out).
        if images is None or valid is None:
            if problem is None:
                raise InputError("_CollapseGuard needs a problem, or images and valid")
            images, valid = problem.batch(0), problem.valid
        self.images: torch.Tensor = images
        self.valid: torch.Tensor = valid
        self.reference: torch.Tensor | None = None
        self.snapshot: dict[str, torch.Tensor] | None = None
        self.healthy_step = 0
        self.tripped: dict[str, Any] | None = None
        self.checks: list[dict[str, float]] = []
        self.usable: torch.Tensor | None = None

    def _depth(self, model: nn.Module) -> torch.Tensor:
        with torch.no_grad():
            return predict(model, self.images[None]).depth[0].float().cpu()

    def check(self, model: nn.Module, adapter: Adapter | nn.Module, step: int) -> bool:
        """True when healthy (the tables are kept); False after restoring the last healthy ones.

        ``adapter``: what is being fitted, the adapter or (tune mode) the module fitted instead
        (LoRA factors, calibration tokens); its parameters are what is kept and restored.
        """
        depth = self._depth(model)
        if self.reference is None:
            self.usable = self.valid.expand_as(depth) & torch.isfinite(depth) & (depth > 0)
            self.reference = torch.log(depth[self.usable])
            self.snapshot = {name: p.detach().clone() for name, p in adapter.named_parameters()}
            self.healthy_step = step
            return True
        current = torch.log(depth[self.usable].clamp_min(1e-12))
        correlation, spread = (
            depth_health(self.reference, current)
            if torch.isfinite(current).all()
            else (float("nan"), float("nan"))
        )
        self.checks.append(
            {"step": step, "correlation": round(correlation, 4), "spread": round(spread, 4)}
        )
        low, high = self.spread_range
        if correlation >= self.min_correlation and low <= spread <= high:
            self.snapshot = {name: p.detach().clone() for name, p in adapter.named_parameters()}
            self.healthy_step = step
            return True
        assert self.snapshot is not None  # taken at the first check
        with torch.no_grad():
            for name, parameter in adapter.named_parameters():
                parameter.copy_(self.snapshot[name])
        self.tripped = {
            "step": step,
            "correlation": correlation,
            "spread": spread,
            "restored_step": self.healthy_step,
        }
        return False

    def report(self) -> dict[str, Any]:
        return {
            "tripped": self.tripped,
            "checks": self.checks[-12:],
            "min_correlation": self.min_correlation,
            "spread_range": list(self.spread_range),
        }


def fit_verdict(
    adapter: Adapter,
    history: list[dict[str, Any]],
    problem: AdaptationProblem,
    guard: _CollapseGuard | None,
    parallax: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """What a finished fit did, in one word and one sentence.

    ``status``: ``"no signal"`` (the parallax gate, ``parallax``, dropped every window: the
    matches cannot tell near from far, so no step was taken), ``"collapsed"`` (the guard stopped it and restored earlier tables),
    ``"diverged"`` (non-finite losses, more than 10 % skipped steps, or a last pass with a loss
    above twice the first pass's), ``"did nothing"`` (the PE correction stayed below 1 % of the
    backbone's PE rms and the RoPE table below 0.01 token) or ``"ok"``.
    """
    correction = pe_correction_grid(adapter, problem.geometry).detach()
    relative = (
        math.sqrt(float(pe_l2(correction)) / problem.pe_scale)
        if problem.pe_scale > 0
        else float("nan")
    )
    rope = float(adapter.rope["radial"].detach().abs().max()) if adapter.rope else 0.0
    window = max(1, len(problem.windows))
    first = [r["loss"] for r in history[:window]]
    last = [r["loss"] for r in history[-window:]]
    skipped = sum(bool(r["skipped"]) for r in history)
    finite = all(math.isfinite(v) for v in last)
    first_mean = float(np.mean(first)) if first else float("nan")
    last_mean = float(np.mean(last)) if last else float("nan")
    size = f"PE correction {100 * relative:.1f} % of the PE rms, RoPE shift up to {rope:.3f} token"
    if parallax is not None and parallax["windows_kept"] == 0:
        status = "no signal"
        medians = [m for m in parallax["window_median_px"] if m is not None]
        summary = (
            f"NO SIGNAL: the matches of all {parallax['windows_dropped']} windows move less than "
            f"{parallax['min_parallax_px']} px per unit log depth (largest window median "
            f"{max(medians, default=0.0):.3f} px; far points only, or no translation), so they "
            "cannot tell near from far; no step taken, tables left as they started"
        )
    elif guard is not None and guard.tripped is not None:
        status = "collapsed"
        summary = (
            f"COLLAPSED at step {guard.tripped['step']} (log-depth correlation {guard.tripped['correlation']:.2f}, "
            f"spread x{guard.tripped['spread']:.2f}); tables of step {guard.tripped['restored_step']} restored; {size}"
        )
    elif history and (not finite or skipped > 0.1 * len(history) or last_mean > 2 * first_mean):
        status = "diverged"
        summary = f"DIVERGED: loss {first_mean:.4g} -> {last_mean:.4g}, {skipped} of {len(history)} steps skipped; {size}"
    elif relative < 0.01 and rope < 0.01:
        status = "did nothing"
        summary = f"DID NOTHING: the tables stayed at zero ({size}); loss {first_mean:.4g} -> {last_mean:.4g}"
    else:
        status = "ok"
        summary = f"ok: loss {first_mean:.4g} -> {last_mean:.4g} over {len(history)} steps; {size}"
    return {
        "status": status,
        "summary": summary,
        "pe_correction_relative_rms": relative,
        "rope_max_token": rope,
        "first_pass_loss": first_mean,
        "last_pass_loss": last_mean,
        "skipped_steps": skipped,
    }
