"""Synthetic world: scenes, trajectories, rendering, correspondences, folder round trip."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.datasets import load_synthetic
from raytun3r_plugin.synthetic import (
    Renderer,
    correspondences,
    dense_flow,
    driving_trajectory,
    handheld_trajectory,
    intersect,
    make_scene,
    render_frame,
    render_sequence,
    write_sequence,
)
from raytun3r_plugin.synthetic.noise import SolidNoise
from raytun3r_plugin.synthetic.scene import Scene


def fisheye(size: int = 96, fov: float = 195.0) -> cameras.KannalaBrandt4:
    """An equidistant-like KB4 fisheye whose lens circle (``fov`` degrees) fits the image."""
    f = (size / 2 - 1) / math.radians(fov / 2)
    c = (size - 1) / 2
    return cameras.KannalaBrandt4(
        size,
        size,
        {"fx": f, "fy": f, "cx": c, "cy": c, "k1": 0.01, "k2": -0.002, "k3": 0.0005, "k4": 0.0},
        max_fov_deg=fov,
    )


@pytest.fixture(scope="module")
def cam() -> cameras.KannalaBrandt4:
    return fisheye()


@pytest.fixture(scope="module")
def indoor(cam):
    return render_sequence("indoor", cam, n_frames=4, seed=3, flow_px=3.0)


@pytest.fixture(scope="module")
def outdoor(cam):
    return render_sequence("outdoor", cam, n_frames=3, seed=5, flow_px=3.0)


def _empty_scene(**kw) -> Scene:
    base = dict(
        kind="test",
        seed=0,
        materials=np.zeros((4, 14), dtype=np.float32),
        boxes=np.zeros((0, 7)),
        box_materials=np.zeros(0, np.int64),
        spheres=np.zeros((0, 4)),
        sphere_materials=np.zeros(0, np.int64),
        cylinders=np.zeros((0, 5)),
        cylinder_materials=np.zeros(0, np.int64),
    )
    base.update(kw)
    return Scene(**base)


def test_intersections_are_analytic():
    scene = _empty_scene(
        spheres=np.array([[0.0, 0.0, 5.0, 1.0]]),
        sphere_materials=np.array([1]),
        boxes=np.array([[3.0, 0.0, 0.0, 0.5, 0.5, 0.5, math.pi / 4]]),
        box_materials=np.array([2]),
        cylinders=np.array([[0.0, -4.0, -1.0, 1.0, 0.5]]),
        cylinder_materials=np.array([3]),
    )
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    hit = intersect(scene, np.zeros(3), dirs)
    # sphere front at z = 4; rotated unit cube: corner at distance 3 - sqrt(0.5); cylinder side at z = -3.5
    np.testing.assert_allclose(hit.t[:3].numpy(), [4.0, 3.0 - math.sqrt(0.5), 3.5], atol=1e-5)
    assert hit.material.tolist() == [1, 2, 3, -1]
    assert not bool(hit.hit[3])
    np.testing.assert_allclose(hit.normal[0].numpy(), [0, 0, -1], atol=1e-5)
    np.testing.assert_allclose(hit.normal[2].numpy(), [0, 0, 1], atol=1e-5)
    # the room is seen from inside; the floor (+y) normal points into the room (-y)
    room = _empty_scene(
        room=np.array([-1.0, -2.0, -3.0, 1.0, 0.5, 3.0]), room_materials=np.arange(6)
    )
    h = intersect(room, np.zeros(3), torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(h.t.numpy(), [0.5, 3.0], atol=1e-6)
    np.testing.assert_allclose(h.normal[0].numpy(), [0, -1, 0])
    assert h.material.tolist() == [3, 5]


def test_noise_is_smooth_deterministic_and_in_range():
    n1, n2 = SolidNoise(seed=4), SolidNoise(seed=4)
    p = torch.rand(2000, 3, generator=torch.Generator().manual_seed(0)) * 300.0 - 150.0
    a, b = n1.octave_stack(p), n2.octave_stack(p)
    assert torch.equal(a, b)
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    # continuity across lattice cells and slices: a tiny step changes the value a little
    d = (n1.lattice(p + 1e-3) - n1.lattice(p)).abs().max()
    assert float(d) < 0.02
    assert not torch.equal(SolidNoise(seed=5).lattice(p), n1.lattice(p))


def test_trajectories_are_smooth_rigid_and_move():
    for poses in (
        handheld_trajectory(30, seed=1, step=0.3),
        driving_trajectory(30, seed=1, step=0.8),
    ):
        assert poses.shape == (30, 4, 4) and poses.dtype == np.float64
        R = poses[:, :3, :3]
        np.testing.assert_allclose(
            R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
        )
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
        C = -np.einsum("nji,nj->ni", R, poses[:, :3, 3])
        v = np.diff(C, axis=0)
        assert np.linalg.norm(v, axis=1).min() > 1e-4  # always moving
        acc = np.linalg.norm(np.diff(v, axis=0), axis=1)
        assert acc.max() < 0.5 * np.linalg.norm(v, axis=1).max()  # smooth
    drive = driving_trajectory(20, seed=2, step=1.0)
    C = -np.einsum("nji,nj->ni", drive[:, :3, :3], drive[:, :3, 3])
    assert 18.0 < C[-1, 2] - C[0, 2] <= 19.0 + 1e-9  # 1 m per step along +z
    assert np.abs(C[:, 0] - C[0, 0]).max() < 0.5  # gentle sway only
    assert np.allclose(handheld_trajectory(10, seed=1), handheld_trajectory(10, seed=1))


def test_render_outputs(cam, indoor):
    seq = indoor
    n, h, w = 4, cam.height, cam.width
    assert seq.images.shape == (n, h, w, 3) and seq.images.dtype == np.float32
    assert seq.depth.shape == (n, h, w) and seq.depth.dtype == np.float32
    assert seq.mask.shape == (n, h, w) and seq.cam_from_world.shape == (n, 4, 4)
    assert seq.depth_kind == "range" and len(seq) == n and seq.timestamps.shape == (n,)
    lens = cam.valid_mask().numpy()
    assert (seq.mask <= lens).all() and seq.mask[:, lens].mean() > 0.99  # indoors every ray hits
    assert seq.images.min() >= 0.0 and seq.images.max() <= 1.0
    assert (seq.images[~seq.mask] == 0).all() and (seq.depth[~seq.mask] == 0).all()
    assert (seq.depth[seq.mask] > 0.05).all() and seq.depth.max() < 30.0
    assert seq.images[seq.mask].std() > 0.08  # textured, not flat
    # The renderer's own recipe (float64 table cast to float32, then z = range * ray_z): an
    # independently computed float32 table differs by ~eps32 / |ray_z| near the 90-degree ring,
    # which is more than any tight tolerance on some CPUs. Same inputs, same product: exact.
    rays = cam.ray_table(dtype=torch.float64)[0].float().numpy()
    z = seq.meta["per_frame"]["z_depth"]
    expect = np.where(seq.mask & (rays[..., 2] > 0), seq.depth * rays[..., 2], 0.0)
    np.testing.assert_array_equal(z, expect.astype(np.float32))
    # beyond 90 degrees from the axis: rays with z < 0 see the scene with positive range
    behind = seq.mask[0] & (rays[..., 2] < -0.05)
    assert behind.sum() > 10 and (seq.depth[0][behind] > 0).all()


def test_render_is_deterministic_and_seeded(cam, indoor):
    again = render_sequence("indoor", cam, n_frames=4, seed=3, flow_px=3.0)
    assert np.array_equal(again.images, indoor.images)
    assert np.array_equal(again.depth, indoor.depth)
    assert np.array_equal(again.cam_from_world, indoor.cam_from_world)
    other = render_sequence("indoor", cam, n_frames=2, seed=4, flow_px=3.0)
    assert not np.array_equal(other.images[0], indoor.images[0])


def test_outdoor_has_sky_and_ground(outdoor):
    sky = outdoor.meta["per_frame"]["sky"]
    assert sky.any() and (outdoor.depth[sky] > 1000).all()
    assert outdoor.mask[sky].all()
    rays = outdoor.camera.ray_table()[0].numpy()
    down = outdoor.mask[0] & (rays[..., 1] > 0.9)  # looking down: the road 1.6 m below
    assert down.any()
    np.testing.assert_allclose(outdoor.depth[0][down] * rays[..., 1][down], 1.6, atol=0.05)


def test_supersampling_modes_agree():
    cam = fisheye(48)
    poses = handheld_trajectory(1, seed=0)
    scene = make_scene("indoor", 0, np.array([[0.0, -1.5, 0.0]]))
    full = render_frame(scene, cam, poses[0], supersample=2, adaptive=False)
    fast = render_frame(scene, cam, poses[0], supersample=2, adaptive=True)
    one = render_frame(scene, cam, poses[0], supersample=1)
    assert np.array_equal(full.range, fast.range) and np.array_equal(full.valid, one.valid)
    assert np.abs(full.rgb - fast.rgb).mean() < 0.02
    assert np.abs(full.rgb - one.rgb).mean() > 1e-4  # supersampling changes something
    assert full.rgb.shape == (48, 48, 3)


def test_pinhole_camera_renders():
    cam = cameras.Pinhole(40, 30, {"fx": 30.0, "fy": 30.0, "cx": 19.5, "cy": 14.5})
    seq = render_sequence("outdoor", cam, n_frames=2, seed=1, flow_px=2.0)
    assert seq.images.shape == (2, 30, 40, 3) and seq.mask.all()


def test_correspondences_identity_and_consistency(indoor):
    uv_i, uv_j, vis = correspondences(indoor, 1, 1)
    assert vis.all() and np.allclose(uv_i, uv_j, atol=1e-3)
    uv_i, uv_j, vis = correspondences(indoor, 0, 1)
    assert uv_i.shape == uv_j.shape and vis.dtype == bool and vis.mean() > 0.6
    assert np.isnan(uv_j[~np.isfinite(uv_j).all(1)]).all()
    # matches of visible points go back: depth of frame j at uv_j, pose j -> i, project
    flow10, vis10 = dense_flow(indoor, 1, 0)
    u, v = np.rint(uv_j[vis]).astype(int).T
    near = np.abs(uv_j[vis] - np.rint(uv_j[vis])).max(1) < 0.05  # uv_j lands on a pixel centre
    ok = near & vis10[v, u]
    assert ok.sum() >= 10
    np.testing.assert_allclose(uv_j[vis][ok] + flow10[v[ok], u[ok]], uv_i[vis][ok], atol=0.05)
    # stride subsamples the grid
    s_i, _, _ = correspondences(indoor, 0, 1, stride=4)
    assert (s_i % 4 == 0).all() and len(s_i) < len(uv_i) / 10


def test_flow_magnitude_and_occlusion_modes(indoor, outdoor):
    for seq in (indoor, outdoor):
        uv_i, uv_j, vis = correspondences(seq, 0, 1)
        flow = np.linalg.norm(uv_j[vis] - uv_i[vis], axis=1)
        assert 1.0 < np.median(flow) < 9.0  # several pixels (target 3 px at 96 px)
        _, _, vis_ray = correspondences(seq, 0, 1, occlusion="raycast")
        # the depth test is conservative: (almost) never visible where the exact test says occluded
        assert (vis & ~vis_ray).sum() <= max(3, 0.002 * vis.size)
        assert (vis == vis_ray).mean() > 0.9
    with pytest.raises(ValueError):
        correspondences(indoor, 0, 1, occlusion="magic")


def test_dense_flow_is_trackable_by_dis():
    cam = fisheye(128)
    seq = render_sequence("indoor", cam, n_frames=2, seed=7, flow_px=3.0)
    g = [cv2.cvtColor((seq.images[k] * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY) for k in range(2)]
    est = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(g[0], g[1], None)
    flow, vis = dense_flow(seq, 0, 1)
    err = np.linalg.norm(est[vis] - flow[vis], axis=1)
    assert np.median(err) < 0.5 and (err < 1.0).mean() > 0.7


def test_write_and_load_round_trip(tmp_path, indoor):
    folder = write_sequence(indoor, tmp_path / "seq")
    back = load_synthetic(folder)
    assert back.name == indoor.name and len(back) == len(indoor)
    assert back.camera == indoor.camera
    assert np.array_equal(back.cam_from_world, indoor.cam_from_world)
    assert np.array_equal(back.timestamps, indoor.timestamps)
    assert np.array_equal(back.depth, indoor.depth) and back.depth_kind == "range"
    assert np.array_equal(back.mask, indoor.mask)
    assert back.images is None and back.image_paths is not None
    assert np.abs(back.image(2) - indoor.images[2]).max() <= 0.5 / 255 + 1e-6
    assert back.meta["synthetic"]["seed"] == 3
    # the analytic scene is rebuilt from the stored parameters and path
    a = correspondences(back, 0, 1, occlusion="raycast")[2]
    b = correspondences(indoor, 0, 1, occlusion="raycast")[2]
    assert np.array_equal(a, b)
    png = load_synthetic(
        write_sequence(indoor, tmp_path / "png", depth_format="png16"), load_images=True
    )
    assert png.images.shape == indoor.images.shape
    np.testing.assert_allclose(png.depth, indoor.depth, atol=0.5e-3 + 1e-6)


def test_renderer_reuses_camera_rays(cam):
    r = Renderer(cam, supersample=3)
    scene = make_scene("outdoor", 2, np.array([[2.0, -1.6, 0.0]]))
    pose = driving_trajectory(1, seed=2)[0]
    f1, f2 = r.render(scene, pose), r.render(scene, pose)
    assert np.array_equal(f1.rgb, f2.rgb) and f1.material.dtype == np.int32
    with pytest.raises(ValueError):
        Renderer(cam, supersample=0)
    with pytest.raises(ValueError):
        render_sequence("cave", cam, 1)
