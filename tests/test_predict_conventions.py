"""``predict`` conventions of every backbone: a known pose in gives the known cam_from_world out.

docs/conventions.md section 2: poses are returned as cam_from_world (world-to-camera, OpenCV axes),
depth as (B, S, H, W), confidence as (B, S, H, W). DA3 and VGGT predict cam_from_world, Pi3
predicts world_from_cam. The conversions are checked on stand-in networks that return a chosen
output, so the expected pose is exact; the Pi3 family is also checked on a model.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

B, S, H, W = 1, 2, 28, 42


def rotation(axis, degrees) -> torch.Tensor:
    """Rotation matrix about ``axis`` (Rodrigues), float64."""
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    angle = math.radians(degrees)
    cross = torch.tensor(
        [[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
        dtype=torch.float64,
    )
    return (
        torch.eye(3, dtype=torch.float64)
        + math.sin(angle) * cross
        + (1 - math.cos(angle)) * cross @ cross
    )


def quaternion_xyzw(axis, degrees) -> torch.Tensor:
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    half = math.radians(degrees) / 2
    return torch.cat((axis * math.sin(half), torch.tensor([math.cos(half)], dtype=torch.float64)))


def rigid(rotation_matrix, translation) -> torch.Tensor:
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = rotation_matrix
    pose[:3, 3] = torch.as_tensor(translation, dtype=torch.float64)
    return pose


# Two views: the first at the world origin, the second turned and moved.
POSES = [((0.0, 0.0, 1.0), 0.0, (0.0, 0.0, 0.0)), ((0.3, -1.0, 0.2), 35.0, (0.4, -0.1, 1.5))]


class StandIn(nn.Module):
    """Returns a fixed output dict, with the attributes the predict functions read."""

    def __init__(self, output: dict, **attributes):
        super().__init__()
        self.output = output
        for name, value in attributes.items():
            setattr(self, name, value)

    def forward(self, images, **kwargs):
        self.seen = images
        return dict(self.output)


def namespace(**attributes):
    module = nn.Module()
    for name, value in attributes.items():
        setattr(module, name, value)
    return module


def images():
    return torch.rand(B, S, 3, H, W, generator=torch.Generator().manual_seed(0))


# ---------------------------------------------------------------------------------------------
# DA3: extrinsics (B, S, 3, 4) are already cam_from_world
# ---------------------------------------------------------------------------------------------


def test_da3_extrinsics_are_returned_as_cam_from_world():
    from raytun3r_plugin.patches import da3

    cam_from_world = torch.stack([rigid(rotation(axis, deg), t) for axis, deg, t in POSES]).float()[
        None
    ]
    depth = torch.rand(B, S, H, W) + 0.5
    intrinsics = torch.eye(3).expand(B, S, 3, 3)
    root = StandIn(
        {
            "depth": depth,
            "depth_conf": depth + 1,
            "extrinsics": cam_from_world[..., :3, :],
            "intrinsics": intrinsics,
        },
        backbone=namespace(pretrained=namespace(patch_size=14)),
    )
    given = images()
    prediction = da3.predict(root, given)
    assert torch.equal(prediction.cam_from_world, cam_from_world)
    assert torch.equal(prediction.depth, depth) and torch.equal(prediction.confidence, depth + 1)
    assert torch.equal(prediction.extras["intrinsics"], intrinsics)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(3, 1, 1)
    assert torch.allclose(root.seen, (given - mean) / std)  # DA3 wants ImageNet-normalised input


# ---------------------------------------------------------------------------------------------
# VGGT: pose_enc [T, quaternion xyzw, fov_h, fov_w] decodes to cam_from_world
# ---------------------------------------------------------------------------------------------


def test_vggt_pose_encoding_decodes_to_the_known_cam_from_world():
    pytest.importorskip("vggt")
    from raytun3r_plugin.patches import vggt

    fov_h, fov_w = math.radians(50.0), math.radians(70.0)
    encodings, expected = [], []
    for index, (axis, degrees, translation) in enumerate(POSES):
        quaternion = quaternion_xyzw(axis, degrees) * (
            -1 if index else 1
        )  # q and -q: same rotation
        encodings.append(
            torch.cat(
                (
                    torch.tensor(translation, dtype=torch.float64),
                    quaternion,
                    torch.tensor([fov_h, fov_w], dtype=torch.float64),
                )
            )
        )
        expected.append(rigid(rotation(axis, degrees), translation))
    pose_enc = torch.stack(encodings).float()[None]
    expected = torch.stack(expected).float()[None]
    depth = torch.rand(B, S, H, W, 1) + 0.5
    root = StandIn(
        {"pose_enc": pose_enc, "depth": depth, "depth_conf": depth[..., 0] + 1},
        aggregator=namespace(patch_size=14),
    )
    given = images()
    prediction = vggt.predict(root, given)
    assert torch.equal(root.seen, given)  # VGGT normalises inside: images go in as [0, 1]
    assert prediction.cam_from_world.shape == (B, S, 4, 4)
    assert torch.allclose(prediction.cam_from_world, expected, atol=1e-5)
    assert torch.equal(prediction.depth, depth[..., 0]) and torch.equal(
        prediction.confidence, depth[..., 0] + 1
    )
    intrinsics = prediction.extras["intrinsics"]
    assert torch.allclose(intrinsics[..., 0, 0], torch.tensor((W / 2) / math.tan(fov_w / 2)))
    assert torch.allclose(intrinsics[..., 1, 1], torch.tensor((H / 2) / math.tan(fov_h / 2)))
    # cam_from_world maps a world point into the camera frame: X_c = R X_w + t
    point = torch.tensor([0.2, -0.3, 4.0])
    camera = (
        prediction.cam_from_world[0, 1, :3, :3] @ point + prediction.cam_from_world[0, 1, :3, 3]
    )
    assert torch.allclose(camera, expected[0, 1, :3, :3] @ point + expected[0, 1, :3, 3], atol=1e-5)


def test_vggt_without_camera_head_is_a_clear_error():
    pytest.importorskip("vggt")
    from raytun3r_plugin.patches import vggt

    from raytun3r_plugin.errors import InputError

    root = StandIn({"depth": torch.ones(B, S, H, W, 1)}, aggregator=namespace(patch_size=14))
    with pytest.raises(InputError, match="no camera head"):
        vggt.predict(root, images())


# ---------------------------------------------------------------------------------------------
# Pi3 / Pi3X: camera_poses are world_from_cam; depth is the range |local_points|
# ---------------------------------------------------------------------------------------------


def test_pi3_world_from_cam_is_inverted():
    from raytun3r_plugin.patches import pi3

    world_from_cam = torch.stack([rigid(rotation(axis, deg), t) for axis, deg, t in POSES])[None]
    cam_from_world = torch.linalg.inv(world_from_cam)
    local_points = torch.randn(B, S, H, W, 3, generator=torch.Generator().manual_seed(2))
    local_points[..., 2] = local_points[..., 2].abs() + 0.5
    points = torch.einsum(
        "bnij,bnhwj->bnhwi",
        world_from_cam.float(),
        torch.cat((local_points, torch.ones_like(local_points[..., :1])), -1),
    )[..., :3]
    conf = torch.randn(B, S, H, W, 1)
    root = StandIn(
        {
            "local_points": local_points,
            "points": points,
            "conf": conf,
            "camera_poses": world_from_cam.float(),
        },
        patch_size=14,
    )
    given = images()
    prediction = pi3.predict(root, given)
    assert torch.equal(root.seen, given)  # Pi3 normalises inside
    assert torch.allclose(prediction.cam_from_world, cam_from_world.float(), atol=1e-6)
    assert torch.allclose(
        prediction.cam_from_world @ world_from_cam.float(),
        torch.eye(4).expand(B, S, 4, 4),
        atol=1e-6,
    )
    assert torch.allclose(prediction.depth, local_points.norm(dim=-1))  # range along the ray
    assert torch.equal(prediction.extras["depth_z"], local_points[..., 2])
    assert torch.allclose(prediction.confidence, torch.sigmoid(conf[..., 0]))
    # a world point goes back to the camera frame with cam_from_world
    back = torch.einsum(
        "bnij,bnhwj->bnhwi",
        prediction.cam_from_world,
        torch.cat((points, torch.ones_like(points[..., :1])), -1),
    )[..., :3]
    assert torch.allclose(back, local_points, atol=1e-5)


def test_invert_rigid_matches_the_matrix_inverse():
    from raytun3r_plugin.patches.pi3 import invert_rigid

    poses = torch.stack([rigid(rotation(axis, deg), t) for axis, deg, t in POSES])
    assert torch.allclose(invert_rigid(poses), torch.linalg.inv(poses), atol=1e-12)


@pytest.mark.parametrize("which", ["Pi3", "Pi3X"])
def test_pi3_models_predict_consistent_poses(which):
    """On a model: cam_from_world maps upstream's world points back to its camera-frame points.

    For Pi3X the prediction is also differentiable through the pose (upstream scales the pose
    translation in place; predict works around it) and equal to the no-grad prediction.
    """
    pytest.importorskip("pi3")
    import raytun3r_plugin as rt
    from tests.backbones import build  # the stub recipe, or a small network of the real classes

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model = build(which.lower())
        given = torch.rand(B, S, 3, H, W, generator=torch.Generator().manual_seed(3))
        with torch.no_grad():
            plain = rt.predict(model, given)
        model.requires_grad_(False)
        model.encoder.pos_embed.requires_grad_(True)
        with_grad = rt.predict(model, given)
        with_grad.cam_from_world[..., :3, 3].square().sum().backward()
    finally:
        torch.set_num_threads(threads)
    assert model.encoder.pos_embed.grad is not None
    assert torch.equal(with_grad.cam_from_world.detach(), plain.cam_from_world)
    points = plain.extras["points"]
    back = torch.einsum(
        "bnij,bnhwj->bnhwi",
        plain.cam_from_world,
        torch.cat((points, torch.ones_like(points[..., :1])), -1),
    )[..., :3]
    scale = float(plain.extras["local_points"].abs().max())
    assert torch.allclose(back, plain.extras["local_points"], atol=1e-5 * scale)
    assert torch.allclose(plain.depth, plain.extras["local_points"].norm(dim=-1))
    bottom = plain.cam_from_world[..., 3, :]
    assert torch.equal(bottom, torch.tensor([0.0, 0.0, 0.0, 1.0]).expand_as(bottom))
