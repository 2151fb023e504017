"""Cameras: conventions, tracking, differentiability, errors."""

import math

import pytest
import torch

import diffrender as dr

from .helpers import F64


def test_look_at_conventions():
    """OpenCV-style: the target projects to the image centre, +up is up in the image (smaller v), the
    camera's right is +u, depth is the distance along the view direction, fov is vertical."""
    eye = torch.tensor([1.0, -3.0, 2.0], dtype=F64)
    target = torch.tensor([0.5, 0.0, 1.0], dtype=F64)
    cam = dr.Camera.look_at(eye, target, (0.0, 0.0, 1.0), 60.0, 30, 40)
    assert cam.batch_size == 1 and cam.dtype == F64
    r = cam.rotation[0]
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=F64))
    assert torch.isclose(torch.det(r), torch.tensor(1.0, dtype=F64))
    uvz = cam.project(target.view(1, 1, 3))[0, 0]
    assert torch.allclose(uvz, torch.tensor([20.0, 15.0, (target - eye).norm()], dtype=F64))
    up = cam.project((target + torch.tensor([0, 0, 0.1], dtype=F64)).view(1, 1, 3))[0, 0]
    assert up[1] < 15.0 and abs(up[0] - 20.0) < 1.0
    right = torch.linalg.cross(target - eye, torch.tensor([0, 0, 1.0], dtype=F64))
    px = cam.project((target + 0.1 * right / right.norm()).view(1, 1, 3))[0, 0]
    assert px[0] > 20.0 and abs(px[1] - 15.0) < 1e-9
    # vertical fov: a point at the top edge of the view along the up axis lands on v = 0
    d = (target - eye).norm()
    up_axis = -r[1]
    top = target + up_axis * d * math.tan(math.radians(30.0))
    assert torch.isclose(cam.project(top.view(1, 1, 3))[0, 0, 1], torch.tensor(0.0, dtype=F64), atol=1e-9)
    # the public focal length is the one look_at uses: half the height over tan(fov / 2)
    assert cam.focal == dr.focal_length(60.0, 30) == pytest.approx(15.0 / math.tan(math.radians(30.0)), rel=1e-15)


def test_batched_broadcasting_and_gradients():
    eye = torch.tensor([[0.0, -3.0, 1.0], [0.5, -2.0, 1.5]], dtype=F64, requires_grad=True)
    target = torch.zeros(3, dtype=F64, requires_grad=True)
    cam = dr.Camera.look_at(eye, target, (0.0, 0.0, 1.0), 45.0, 8, 8)
    assert cam.rotation.shape == (2, 3, 3) and cam.eye.shape == (2, 3)
    pts = torch.randn(2, 5, 3, dtype=F64)
    torch.autograd.gradcheck(lambda e, t: dr.Camera.look_at(e, t, (0, 0, 1.0), 45.0, 8, 8).project(pts),
                             (eye, target))


def test_tracking_camera_follows_tracked_axes():
    root = torch.tensor([[1.0, 2.0, 0.7], [-1.0, 0.5, 0.3]], dtype=F64, requires_grad=True)
    kw = dict(eye_offset=(0.0, -2.8, 1.35), target_offset=(0.0, 0.0, 1.25), fov_deg=45.0, height=8, width=8)
    xyz = dr.tracking_camera(root, track="xyz", **kw)
    assert torch.allclose(xyz.eye, root + torch.tensor([0.0, -2.8, 1.35], dtype=F64))
    xz = dr.tracking_camera(root, track="xz", **kw)
    assert torch.allclose(xz.eye, root * torch.tensor([1.0, 0, 1], dtype=F64) + torch.tensor([0, -2.8, 1.35]))
    fixed = dr.tracking_camera(root, track="none", **kw)
    assert torch.allclose(fixed.eye, torch.tensor([0, -2.8, 1.35], dtype=F64).expand(2, 3))
    # gradients reach the root through the extrinsics; "xz" ignores y
    xz.eye.sum().backward()
    assert torch.equal(root.grad, torch.tensor([[1.0, 0, 1], [1.0, 0, 1]], dtype=F64))
    with pytest.raises(ValueError, match="track"):
        dr.tracking_camera(root, track="yz", **kw)
    with pytest.raises(ValueError, match="root_pos"):
        dr.tracking_camera(root[0], **kw)


def test_camera_errors():
    with pytest.raises(ValueError, match="fov_deg"):
        dr.Camera.look_at((0, 0, 1.0), (0, 1, 1.0), (0, 0, 1.0), 180.0, 8, 8)
    with pytest.raises(ValueError, match="share dtype"):
        dr.Camera.look_at(torch.zeros(3), torch.ones(3, dtype=F64), (0, 0, 1.0), 40.0, 8, 8)
    with pytest.raises(ValueError, match="up must have shape"):
        dr.Camera.look_at((0, 0, 1.0), (0, 1, 1.0), (0, 1.0), 40.0, 8, 8)
    with pytest.raises(ValueError, match="batch sizes"):
        dr.Camera.look_at(torch.zeros(2, 3), torch.ones(3, 3), (0, 0, 1.0), 40.0, 8, 8)
    with pytest.raises(ValueError, match="image size"):
        dr.Camera.look_at((0, 0, 1.0), (0, 1, 1.0), (0, 0, 1.0), 40.0, 0, 8)
    # a degenerate look-at (up parallel to the view direction) is not silently wrong: render rejects it
    cam = dr.Camera.look_at((0, 0, 1.0), (0, 0, 0.0), (0, 0, 1.0), 40.0, 8, 8)
    assert not torch.isfinite(cam.rotation).all()
    verts = torch.zeros(1, 3, 3)
    with pytest.raises(ValueError, match=r"camera\.rotation contain"):
        dr.render(verts, torch.tensor([[0, 1, 2]]), torch.zeros(3, 3), cam)
