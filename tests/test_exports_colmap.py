"""``--export colmap``: a sparse model with the real lens, read back with pycolmap."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from raytun3r_plugin import cameras
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.exports import ExportOptions, plan_exports
from raytun3r_plugin.exports.lens import colmap_lens
from tests.export_scenes import scene_of
from tests.helpers import fisheye

pycolmap = pytest.importorskip("pycolmap")

W, H = 96, 80
CENTRE = {"fx": 40.0, "fy": 41.0, "cx": 47.3, "cy": 39.6}

#: Lenses COLMAP stores exactly, with the COLMAP model each must be written as.
EXACT = {
    "PINHOLE": cameras.Pinhole(W, H, {"fx": 70.0, "fy": 71.0, "cx": 47.3, "cy": 39.6}),
    "OPENCV": cameras.OpenCVRadTan(
        W,
        H,
        {"fx": 70.0, "fy": 71.0, "cx": 47.3, "cy": 39.6, "k1": -0.1, "k2": 0.02}
        | {"p1": 1e-3, "p2": -5e-4},
    ),
    "OPENCV_FISHEYE": cameras.KannalaBrandt4(
        W, H, CENTRE | {"k1": 0.02, "k2": -0.01, "k3": 0.002, "k4": -1e-4}
    ),
    "THIN_PRISM_FISHEYE": cameras.ThinPrismFisheye(
        W,
        H,
        CENTRE
        | {"k1": 0.01, "k2": -0.002, "p1": 2e-4, "p2": -1e-4, "k3": 1e-4, "k4": 0.0}
        | {"sx1": 1e-4, "sy1": -2e-4},
    ),
    "FOV": cameras.FOV(W, H, CENTRE | {"omega": 0.9}),
    "EUCM": cameras.EUCM(W, H, CENTRE | {"alpha": 0.6, "beta": 1.1}),
    "EUCM (from UCM)": cameras.UCM(W, H, CENTRE | {"alpha": 0.6}),
    "RAD_TAN_THIN_PRISM_FISHEYE": cameras.Fisheye624(
        W,
        H,
        CENTRE
        | {"k0": 0.01, "k1": -0.002, "k2": 3e-4, "k3": 0.0, "k4": 0.0, "k5": 0.0}
        | {"p0": 1e-4, "p1": -2e-4, "s0": 1e-4, "s1": 0.0, "s2": -1e-4, "s3": 0.0},
    ),
}


def _colmap_camera(lens, camera):
    params = list(lens.params)
    params[2] += 0.5
    params[3] += 0.5
    return pycolmap.Camera(
        model=lens.model, width=camera.width, height=camera.height, params=params
    )


def _rays_within(camera, degrees: float) -> np.ndarray:
    rays, valid = camera.ray_table(dtype=torch.float64)
    keep = valid & (rays[..., 2] > math.cos(math.radians(degrees)))
    return rays[keep].numpy()


@pytest.mark.parametrize("expected", sorted(EXACT))
def test_exact_lenses_project_as_raytun3r_in_colmap(expected):
    camera = EXACT[expected]
    lens = colmap_lens(camera)
    assert lens.exact and lens.model == expected.split(" ")[0]
    colmap = _colmap_camera(lens, camera)
    rays = _rays_within(camera, 80.0)
    assert len(rays) > 1000
    ours = camera.project(torch.from_numpy(rays))[0].numpy()
    theirs = np.asarray(colmap.img_from_cam(rays))
    # COLMAP's first pixel centre is (0.5, 0.5), raytun3r's (0, 0): everything moves by +0.5.
    assert np.abs(theirs - (ours + 0.5)).max() < 1e-6
    # Pixel-centre convention, explicitly: raytun3r's pixel (0, 0) is COLMAP's (0.5, 0.5).
    corner_ray = camera.unproject(torch.zeros(1, 2, dtype=torch.float64))[0].numpy()
    assert np.allclose(colmap.img_from_cam(corner_ray), [[0.5, 0.5]], atol=1e-6)
    # Axes: +x lands right of the principal point, +y below it (both tools: x right, y down).
    cx, cy = lens.params[2] + 0.5, lens.params[3] + 0.5
    right, down = colmap.img_from_cam(np.array([[0.2, 0.0, 1.0], [0.0, 0.2, 1.0]]))
    # (tangential and thin-prism terms may bend the image off the axis a little)
    assert right[0] > cx + 1 and abs(right[1] - cy) < 0.1 * (right[0] - cx)
    assert down[1] > cy + 1 and abs(down[0] - cx) < 0.1 * (down[1] - cy)


@pytest.mark.parametrize("model", ["ds", "mei"])
def test_lenses_colmap_lacks_are_fitted_with_their_error_stated(model):
    if model == "ds":
        camera = cameras.fisheye((W, H), 195.0, "ds")
    else:
        camera = cameras.MEI(
            W,
            H,
            {"fx": 91.6, "fy": 91.5, "cx": 47.3, "cy": 39.6, "xi": 2.2134, "k1": 0.0168}
            | {"k2": 1.6549, "p1": 4.2e-4, "p2": 4.2e-4},
        )
    lens = colmap_lens(camera)
    assert lens.model == "OPENCV_FISHEYE" and not lens.exact
    assert lens.fit["median_px"] <= lens.fit["worst_px"] < 1.0
    assert any("worst" in note and "median" in note for note in lens.notes)
    # The stated worst error is what COLMAP's projection of the fitted lens really misses by.
    rays = _rays_within(camera, lens.fit["max_angle_deg"])
    ours = camera.project(torch.from_numpy(rays))[0].numpy()
    theirs = np.asarray(_colmap_camera(lens, camera).img_from_cam(rays))
    error = np.linalg.norm(theirs - (ours + 0.5), axis=-1)
    assert error.max() <= lens.fit["worst_px"] + 1e-6
    assert abs(np.median(error) - lens.fit["median_px"]) < 0.1 * lens.fit["worst_px"] + 1e-9
    # A threshold below the fit's error refuses, naming the alternatives.
    with pytest.raises(InputError, match="glb or rerun"):
        colmap_lens(camera, max_fit_error_px=lens.fit["worst_px"] / 2)


@pytest.mark.parametrize("model", ["FOV", "EUCM", "THIN_PRISM_FISHEYE", "OPENCV", "PINHOLE"])
def test_opencv_fisheye_only_fits_what_a_basic_reader_lacks(model):
    """--colmap-lens opencv-fisheye (gsplat's COLMAP loader reads models 0-5 only): the basic
    models stay exact, the others become a fitted OPENCV_FISHEYE that COLMAP projects as stated."""
    camera = EXACT[model]
    lens = colmap_lens(camera, choice="opencv-fisheye")
    if model in ("OPENCV", "PINHOLE"):
        assert lens.exact and lens.model == model
        return
    assert lens.model == "OPENCV_FISHEYE" and lens.fit["fitted_to"] == camera.model
    rays = _rays_within(camera, lens.fit["max_angle_deg"])
    ours = camera.project(torch.from_numpy(rays))[0].numpy()
    theirs = np.asarray(_colmap_camera(lens, camera).img_from_cam(rays))
    assert np.linalg.norm(theirs - (ours + 0.5), axis=-1).max() <= lens.fit["worst_px"] + 1e-6


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    camera = fisheye(W, H, 190.0)
    scene = scene_of(camera, frames=3)
    out = tmp_path_factory.mktemp("colmap")
    plans = plan_exports(scene, ["colmap"], ExportOptions(max_points=1500))
    record = plans["colmap"].write(out)
    return scene, out / "colmap", record


@pytest.mark.parametrize("form", ["binary", "text"])
def test_model_reads_back_with_pycolmap(written, form):
    scene, folder, record = written
    reconstruction = pycolmap.Reconstruction()
    if form == "binary":
        reconstruction.read_binary(str(folder / "sparse" / "0"))
    else:
        reconstruction.read_text(str(folder / "text"))
    assert record["camera_model"] == "OPENCV_FISHEYE" and record["lens"] == "exact"
    colmap_camera = reconstruction.cameras[1]
    assert colmap_camera.model_name == "OPENCV_FISHEYE"
    assert (colmap_camera.width, colmap_camera.height) == (W, H)
    values = scene.camera.values
    expected = [values[n] for n in scene.camera.param_names]
    expected[2] += 0.5
    expected[3] += 0.5
    assert np.array_equal(np.asarray(colmap_camera.params), expected)

    by_name = {image.name: image for image in reconstruction.images.values()}
    assert sorted(by_name) == [f"{name}.png" for name in scene.names]
    for k, name in enumerate(scene.names):
        image = by_name[f"{name}.png"]
        pose = image.cam_from_world().matrix()
        assert np.abs(pose - scene.cam_from_world[k][:3]).max() < 1e-9
        assert (folder / "images" / image.name).is_file()

    assert reconstruction.num_points3D() > 500
    assert reconstruction.compute_mean_track_length() > 1.5  # tracks span frames
    worst = 0.0
    for point in reconstruction.points3D.values():
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            observed = np.asarray(image.points2D[element.point2D_idx].xy)
            projected = colmap_camera.img_from_cam((image.cam_from_world() * point.xyz)[None])[0]
            worst = max(worst, float(np.linalg.norm(projected - observed)))
    assert worst < 1e-5
    reconstruction.update_point_3d_errors()
    assert reconstruction.compute_mean_reprojection_error() < 1e-5


def test_points_lie_on_their_pixels_rays_at_the_predicted_depth(written):
    """Independent of COLMAP's reader: a point's first observation (its own pixel, COLMAP
    convention) unprojected with raytun3r's camera at the ground-truth range is the point."""
    scene, folder, _ = written
    reconstruction = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    checked = 0
    for point in list(reconstruction.points3D.values())[:200]:
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            k = scene.names.index(image.name[:-4])
            uv = np.asarray(image.points2D[element.point2D_idx].xy) - 0.5
            if not np.allclose(uv, np.round(uv), atol=1e-9):
                continue  # an observation in another frame: not a pixel centre
            col, row = (int(v) for v in np.round(uv))
            ray = scene.camera.unproject(torch.tensor(uv))[0].numpy()
            world = scene.world_from_cam(k)
            expected = world[:3, :3] @ (scene.depth[k, row, col] * ray) + world[:3, 3]
            assert np.abs(np.asarray(point.xyz) - expected).max() < 1e-5
            checked += 1
    assert checked >= 100
