"""``AdaptConfig.lr_without_teacher``: the step size of a fit whose teacher term is off.

Where the lens gate turns the teacher off (or its weight is 0) the fit runs with
``lr_without_teacher`` in place of ``lr``, table for table the fit with that ``lr``; where the
teacher is on the field changes nothing. None by default and out of the identity when None.
"""

from __future__ import annotations

import pytest
import torch
from raytun3r_plugin.patches.da3_networks import build_tiny_network

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.errors import InputError
from tests.helpers import small_fit_config, small_kb4


@pytest.fixture(scope="module")
def room():
    camera = small_kb4()
    return camera, synthetic.render_sequence("indoor", camera, n_frames=6, seed=7)


def _fit(room, config):
    camera, seq = room
    return adapt(build_tiny_network(), camera, seq.images, config, progress=False)


def _same_tables(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters(), strict=True))


def test_lr_without_teacher_is_validated_and_out_of_the_identity_when_none():
    assert "lr_without_teacher" not in AdaptConfig().to_dict()
    on = AdaptConfig(lr_without_teacher=1e-3)
    assert on.to_dict()["lr_without_teacher"] == 1e-3
    assert on.identity() != AdaptConfig().identity()
    for bad in (0.0, -1e-3, float("nan"), "fast"):
        with pytest.raises(InputError, match="AdaptConfig.lr_without_teacher"):
            AdaptConfig(lr_without_teacher=bad)


@pytest.mark.parametrize("teacher_off", ["lens gate", "weight 0"])
def test_a_fit_without_the_teacher_runs_with_lr_without_teacher(room, tmp_path, teacher_off):
    # The lens gate: a 190-degree lens whose views may cover at most 0 % of it.
    off = (
        {"teacher_max_coverage": 0.0}
        if teacher_off == "lens gate"
        else {"weights": {"teacher": 0.0}}
    )
    gated = _fit(
        room, small_fit_config(tmp_path, "default", lr=3e-2, lr_without_teacher=1e-3, **off)
    )
    plain = _fit(room, small_fit_config(tmp_path, "default", lr=1e-3, **off))
    larger = _fit(room, small_fit_config(tmp_path, "default", lr=3e-2, **off))
    assert _same_tables(gated, plain) and not _same_tables(gated, larger)
    assert gated.training_info["config"]["lr"] == 1e-3
    if teacher_off == "lens gate":
        assert gated.training_info["teacher"]["used"] is False


def test_a_fit_with_the_teacher_keeps_lr(room, tmp_path):
    on = {"teacher_max_coverage": 1.0}
    gated = _fit(
        room, small_fit_config(tmp_path, "default", lr=3e-2, lr_without_teacher=1e-3, **on)
    )
    plain = _fit(room, small_fit_config(tmp_path, "default", lr=3e-2, **on))
    assert gated.training_info["teacher"]["used"] is True
    assert _same_tables(gated, plain) and gated.training_info["config"]["lr"] == 3e-2
