"""Matchers: DIS flow, SIFT, the flow-network wrapper and the registry."""

from __future__ import annotations

from fractions import Fraction

import cv2
import numpy as np
import pytest
import torch

from raytun3r_plugin.adaptation.matchers import (
    MATCHERS,
    DISFlowMatcher,
    Matcher,
    Matches,
    SIFTMatcher,
    TorchFlowMatcher,
    get_matcher,
    matches_from_flows,
    register_matcher,
)
from raytun3r_plugin.errors import InputError, WeightsError

SIZE = 160


def _texture(size: int, seed: int) -> np.ndarray:
    """Multi-scale smooth noise, (size, size, 3) float32 in [0, 1]."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size, 3), np.float32)
    for cell, amp in ((4, 0.5), (8, 0.3), (16, 0.2)):
        noise = rng.random((size // cell + 3, size // cell + 3, 3)).astype(np.float32)
        big = cv2.resize(noise, ((size // cell + 3) * cell,) * 2, interpolation=cv2.INTER_CUBIC)
        img += amp * big[cell : cell + size, cell : cell + size]
    return np.clip(img, 0.0, 1.0)


# Small similarity-like homography: rotation ~1 deg, scale 1%, shift (3, -2) px, mild perspective.
HOMOGRAPHY = np.array([[1.01, 0.02, 3.0], [-0.015, 0.995, -2.0], [1e-5, 2e-5, 1.0]])


def _apply_h(h: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = np.c_[uv, np.ones(len(uv))] @ h.T
    return p[:, :2] / p[:, 2:]


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    img_i = _texture(SIZE, 0)
    img_j = cv2.warpPerspective(
        img_i, HOMOGRAPHY, (SIZE, SIZE), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    img_j = np.clip(img_j, 0.0, 1.0).astype(np.float32)
    vv, uu = np.mgrid[0:SIZE, 0:SIZE]
    c = (SIZE - 1) / 2
    valid = (uu - c) ** 2 + (vv - c) ** 2 < (0.47 * SIZE) ** 2  # a lens circle
    return img_i, img_j, valid


def _inside(uv: np.ndarray, mask: np.ndarray) -> bool:
    ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    h, w = mask.shape
    ok = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    return bool(ok.all() and mask[vi, ui].all())


# --------------------------------------------------------------------------- Matches


def test_matches_validation_and_helpers() -> None:
    m = Matches(np.zeros((3, 2)), np.ones((3, 2)), [0.1, 0.5, 1.0])
    assert m.uv_i.dtype == np.float32 and m.confidence.dtype == np.float32
    assert len(m) == 3
    np.testing.assert_allclose(m.displacement(), np.sqrt(2.0), rtol=1e-6)
    r = m.reversed()
    np.testing.assert_array_equal(r.uv_i, m.uv_j)
    assert len(m.select(m.confidence > 0.2)) == 2
    assert len(Matches.empty()) == 0
    with pytest.raises(InputError):
        Matches(np.zeros((3, 2)), np.zeros((2, 2)), np.ones(3))
    with pytest.raises(InputError):
        Matches(np.zeros((1, 2)), np.zeros((1, 2)), [1.5])
    with pytest.raises(InputError):
        Matches(np.full((1, 2), np.nan), np.zeros((1, 2)), [1.0])


def test_matches_from_flows_forward_backward_check() -> None:
    h = w = 40
    fw = np.zeros((h, w, 2), np.float32)
    fw[..., 0] = 2.0
    bw = np.zeros((h, w, 2), np.float32)
    bw[..., 0] = -2.0
    bw[:, 30:, 1] = 5.0  # inconsistent backward flow where the forward flow lands at u >= 30
    valid = np.ones((h, w), bool)
    m = matches_from_flows(fw, bw, valid, stride=2, fb_threshold_px=1.0)
    assert len(m) > 0
    np.testing.assert_allclose(m.uv_j - m.uv_i, [[2.0, 0.0]] * len(m), atol=1e-6)
    assert (m.uv_j[:, 0] < 29.5).all()  # the inconsistent region is rejected
    assert (m.uv_j[:, 0] <= w - 1).all()  # end points stay inside the image
    np.testing.assert_allclose(m.confidence, 1.0)


# --------------------------------------------------------------------------- DIS / SIFT


def test_dis_recovers_homography(pair) -> None:
    img_i, img_j, valid = pair
    matcher = DISFlowMatcher(appearance_check=False)
    m = matcher.match(img_i, img_j, valid)
    assert isinstance(matcher, Matcher)
    assert len(m) > 600  # ~ pi * 75^2 / 16 grid points
    err = np.linalg.norm(_apply_h(HOMOGRAPHY, m.uv_i) - m.uv_j, axis=1)
    assert np.median(err) < 0.2
    assert (err < 1.0).mean() > 0.95
    assert _inside(m.uv_i, valid) and _inside(m.uv_j, valid)
    assert (m.confidence >= 0).all() and (m.confidence <= 1).all()
    # Deterministic.
    m2 = matcher.match(img_i, img_j, valid)
    np.testing.assert_array_equal(m.uv_j, m2.uv_j)


def test_dis_settings_change_output(pair) -> None:
    img_i, img_j, valid = pair
    coarse = DISFlowMatcher(stride=8)
    assert coarse.settings() != DISFlowMatcher().settings()
    assert len(coarse.match(img_i, img_j, valid)) < len(DISFlowMatcher().match(img_i, img_j, valid))
    with pytest.raises(InputError):
        DISFlowMatcher(preset="slow")


def test_sift_recovers_homography(pair) -> None:
    img_i, img_j, valid = pair
    m = SIFTMatcher().match(img_i, img_j, valid)
    assert len(m) > 50
    err = np.linalg.norm(_apply_h(HOMOGRAPHY, m.uv_i) - m.uv_j, axis=1)
    assert np.median(err) < 0.5
    assert (err < 3.0).mean() > 0.9
    assert _inside(m.uv_i, valid) and _inside(m.uv_j, valid)
    assert (m.confidence > 0.19).all() and (m.confidence <= 1).all()  # 1 - ratio, ratio < 0.8
    loose = SIFTMatcher(mutual=False).match(img_i, img_j, valid)
    assert len(loose) >= len(m)


def test_matchers_on_blank_images_return_empty() -> None:
    blank = np.full((64, 64, 3), 0.5, np.float32)
    assert len(SIFTMatcher().match(blank, blank)) == 0
    # No valid pixel -> no match.
    none_valid = np.zeros((64, 64), bool)
    assert len(DISFlowMatcher().match(blank, blank, none_valid)) == 0


def test_input_validation(pair) -> None:
    img_i, img_j, valid = pair
    dis = DISFlowMatcher()
    with pytest.raises(InputError):
        dis.match(img_i[..., 0], img_j[..., 0])
    with pytest.raises(InputError):
        dis.match(img_i, img_j[:100])
    with pytest.raises(InputError):
        dis.match((img_i * 255).astype(np.uint8), img_j)
    with pytest.raises(InputError):
        dis.match(img_i, img_j, valid[:100])
    # A torch mask is accepted.
    assert len(dis.match(img_i, img_j, torch.from_numpy(valid))) > 0


# --------------------------------------------------------------------------- registry


def test_registry() -> None:
    assert {"dis", "sift", "torch_flow"} <= set(MATCHERS)
    m = get_matcher("dis", stride=8)
    assert isinstance(m, DISFlowMatcher) and m.settings()["stride"] == 8
    assert isinstance(get_matcher("sift"), SIFTMatcher)
    with pytest.raises(InputError, match="unknown matcher"):
        get_matcher("nope")
    with pytest.raises(InputError, match="bad arguments"):
        get_matcher("dis", bogus=1)
    with pytest.raises(InputError, match="already registered"):
        register_matcher("dis", DISFlowMatcher)
    try:
        register_matcher("test_dis8", lambda: DISFlowMatcher(stride=8))
        assert get_matcher("test_dis8").stride == 8
    finally:
        MATCHERS.pop("test_dis8", None)


# --------------------------------------------------------------------------- flow networks


class TinyShiftNet(torch.nn.Module):
    """A fake flow network: global integer translation by exhaustive search, times ``gain``.

    With ``gain = 0`` (its initial value) it predicts zero flow; the weight file sets it to 1.
    """

    def __init__(self, radius: int = 4) -> None:
        super().__init__()
        self.radius = radius
        self.gain = torch.nn.Parameter(torch.zeros(()))
        self.calls = 0

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> list[torch.Tensor]:
        self.calls += 1
        r = self.radius
        n, _, h, w = a.shape
        flows = []
        for k in range(n):
            best, best_d = None, (0, 0)
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    # b(x + d) vs a(x) on the overlap.
                    pa = a[k, :, r : h - r, r : w - r]
                    pb = b[k, :, r + dy : h - r + dy, r + dx : w - r + dx]
                    cost = (pa - pb).abs().mean()
                    if best is None or cost < best:
                        best, best_d = cost, (dx, dy)
            f = torch.tensor(best_d, dtype=a.dtype).view(2, 1, 1).expand(2, h, w)
            flows.append(f * self.gain)
        flow = torch.stack(flows)
        return [torch.zeros_like(flow), flow]  # RAFT-like list of refinements, last is used


def _shifted_pair(h: int = 60, w: int = 52, dx: int = 3, dy: int = -2):
    big = _texture(96, 3)
    img_i = np.ascontiguousarray(big[10 : 10 + h, 10 : 10 + w])
    img_j = np.ascontiguousarray(big[10 - dy : 10 - dy + h, 10 - dx : 10 - dx + w])
    return img_i, img_j  # img_j(x + d) = img_i(x), d = (dx, dy)


def test_torch_flow_matcher_from_pt_and_safetensors(tmp_path) -> None:
    from safetensors.torch import save_file

    img_i, img_j = _shifted_pair()
    pt = tmp_path / "shift.pt"
    torch.save({"state_dict": {"gain": torch.tensor(1.0)}}, pt)
    st = tmp_path / "shift.safetensors"
    save_file({"gain": torch.tensor(1.0)}, str(st))

    untrained = TorchFlowMatcher(TinyShiftNet(), None, border_px=0, stride=4)
    for path in (pt, st):
        net = TinyShiftNet()
        matcher = TorchFlowMatcher(net, path, name="tiny_shift", border_px=0, stride=4)
        m = matcher.match(img_i, img_j)
        assert net.calls == 1  # forward and backward flow in one batch
        assert len(m) > 50
        np.testing.assert_allclose(m.uv_j - m.uv_i, [[3.0, -2.0]] * len(m), atol=1e-5)
        assert matcher.settings()["name"] == "tiny_shift"
        assert matcher.settings()["weights_sha256"] != untrained.settings()["weights_sha256"]
    # Zero gain -> zero flow everywhere (the fb check passes trivially).
    m0 = untrained.match(img_i, img_j)
    np.testing.assert_allclose(m0.uv_j, m0.uv_i)
    # Through the registry.
    via_registry = get_matcher("torch_flow", network=TinyShiftNet(), weights_path=st)
    assert via_registry.settings()["weights_sha256"] == matcher.settings()["weights_sha256"]


def test_torch_flow_matcher_weight_errors(tmp_path) -> None:
    with pytest.raises(WeightsError, match="not found"):
        TorchFlowMatcher(TinyShiftNet(), tmp_path / "missing.pt")
    wrong = tmp_path / "wrong.pt"
    torch.save({"other": torch.zeros(3)}, wrong)
    with pytest.raises(WeightsError, match="do not fit"):
        TorchFlowMatcher(TinyShiftNet(), wrong)
    pickled = tmp_path / "pickled.pt"
    torch.save({"gain": Fraction(1, 2)}, pickled)  # arbitrary object: refused by weights_only
    with pytest.raises(WeightsError):
        TorchFlowMatcher(TinyShiftNet(), pickled)
    with pytest.raises(InputError):
        TorchFlowMatcher(object(), None)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- synthetic fisheye


@pytest.fixture(scope="module")
def fisheye_indoor():
    """3 frames of the synthetic indoor scene through a ~190 degree KB4 lens, 160x160."""
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.cameras import KannalaBrandt4

    cam = KannalaBrandt4(
        160, 160, [45.0, 45.0, 79.5, 79.5, 0.01, -0.004, 0.0005, 0.0], max_fov_deg=190.0
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # rendering is much faster without thread contention
    try:
        return synthetic.render_sequence("indoor", cam, n_frames=3, seed=0)
    finally:
        torch.set_num_threads(threads)


def _end_point_errors(seq, i: int, j: int, m: Matches) -> np.ndarray:
    """|uv_j - ground truth| for the matches whose ground truth exists (bilinear in flow)."""
    from raytun3r_plugin import synthetic

    flow, visible = synthetic.dense_flow(seq, i, j)
    flow = np.nan_to_num(flow)
    uv = m.uv_i.astype(np.float64)
    fu, ok_u = synthetic.bilinear_sample(flow[..., 0], uv, visible)
    fv, ok_v = synthetic.bilinear_sample(flow[..., 1], uv, visible)
    ok = ok_u & ok_v
    assert ok.mean() > 0.8  # most matches land where ground truth exists
    return np.linalg.norm(uv + np.stack([fu, fv], 1) - m.uv_j, axis=1)[ok]


@pytest.mark.parametrize(
    ("matcher", "min_matches", "max_median", "min_in1"),
    [
        (DISFlowMatcher(appearance_check=False), 500, 0.5, 0.85),
        (DISFlowMatcher(), 150, 0.3, 0.95),
        (SIFTMatcher(), 100, 0.5, 0.85),
    ],
)
def test_matchers_on_synthetic_fisheye(
    fisheye_indoor, matcher, min_matches, max_median, min_in1
) -> None:
    seq = fisheye_indoor
    valid = seq.camera.valid_mask().numpy()
    for i, j in ((0, 1), (1, 0), (1, 2)):
        m = matcher.match(seq.images[i], seq.images[j], valid)
        assert len(m) >= min_matches
        assert _inside(m.uv_i, valid) and _inside(m.uv_j, valid)
        err = _end_point_errors(seq, i, j, m)
        assert np.median(err) < max_median
        assert (err < 1.0).mean() > min_in1
        assert (err < 3.0).mean() > 0.9


# --------------------------------------------------------------------------- appearance check


def test_appearance_check_rejects_the_zero_flow_failure() -> None:
    """A flow that stopped at zero on a 12 px motion passes the forward-backward check (both
    directions are zero) but fails the appearance check; the true matches pass it."""
    from raytun3r_plugin.adaptation.matchers import appearance_check

    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.random((96, 120)).astype(np.float32), (0, 0), 0.8)
    gray_i, gray_j = texture[:, 12:108], texture[:, :96]  # scene moves 12 px to the right
    grid = (
        np.stack(np.meshgrid(np.arange(16, 80, 4), np.arange(16, 80, 4)), -1)
        .reshape(-1, 2)
        .astype(np.float32)
    )
    true = appearance_check(gray_i, gray_j, grid, grid + [12.0, 0.0])
    zero = appearance_check(gray_i, gray_j, grid, grid)
    assert true.mean() > 0.9
    assert zero.mean() < 0.05


def test_appearance_check_rejects_flat_and_edge_patches() -> None:
    from raytun3r_plugin.adaptation.matchers import appearance_check

    flat = np.full((64, 64), 0.5, np.float32)
    ramp = np.tile(np.linspace(0, 1, 64, dtype=np.float32), (64, 1))  # an edge along v
    uv = np.array([[32.0, 32.0]], np.float32)
    assert not appearance_check(flat, flat, uv, uv).any()
    # Sliding along the ramp's level lines looks the same, so the match is not a distinct peak.
    assert not appearance_check(ramp, ramp, uv, uv).any()


def test_dis_default_holds_at_large_motion_on_the_benchmark_cameras() -> None:
    """Issue 12's matching target on a development sequence per benchmark camera (outdoor, the
    hard case): in every displacement bin (0-4, 4-8, 8-16, 16-32, 32+ px) that holds at least
    5 % of the matches the median end-point error is below 1 px; without the check the
    zero-flow failure puts medians of several pixels into the 8-16 or 16-32 px bins."""
    from raytun3r_plugin import synthetic
    from raytun3r_plugin.apps.benchmark import CAMERAS, make_camera

    bins = [0, 4, 8, 16, 32, np.inf]
    for index, spec in enumerate(CAMERAS):
        camera = make_camera(spec, 112)
        seq = synthetic.render_sequence("outdoor", camera, n_frames=6, seed=80_001 + 10 * index)
        valid = camera.valid_mask().numpy()
        worst = {}
        for name, matcher in (
            ("checked", DISFlowMatcher()),
            ("raw", DISFlowMatcher(appearance_check=False)),
        ):
            errors, motion = [], []
            for i, j in ((0, 2), (2, 0), (1, 3), (3, 1), (2, 4), (4, 2)):
                m = matcher.match(seq.images[i], seq.images[j], valid)
                flow, visible = synthetic.dense_flow(seq, i, j)
                flow = np.nan_to_num(flow)
                uv = m.uv_i.astype(np.float64)
                fu, ok_u = synthetic.bilinear_sample(flow[..., 0], uv, visible)
                fv, ok_v = synthetic.bilinear_sample(flow[..., 1], uv, visible)
                ok = ok_u & ok_v
                truth = np.stack([fu, fv], 1)[ok]
                errors.append(np.linalg.norm(uv[ok] + truth - m.uv_j[ok], axis=1))
                motion.append(np.linalg.norm(truth, axis=1))
            error, moved = np.concatenate(errors), np.concatenate(motion)
            medians = [
                np.median(error[(moved >= lo) & (moved < hi)])
                for lo, hi in zip(bins[:-1], bins[1:], strict=True)
                if ((moved >= lo) & (moved < hi)).mean() >= 0.05
            ]
            worst[name] = max(medians)
        assert worst["checked"] < 1.0, (spec.label, worst)
        assert worst["raw"] > worst["checked"]
