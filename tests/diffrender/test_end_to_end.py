"""qpos -> FK -> tracking camera + vertices -> soft rasterizer -> image: autograd against finite differences."""

import dataclasses

import pytest
import torch

import diffrender as dr

from .helpers import F64, ant_camera, ant_pose, asset


@pytest.fixture(scope="module")
def ant():
    return dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)


def _loss_fn(robot, settings, weights, *, track="xyz", size=24):
    def loss(q):
        verts, normals = robot.world_vertices_and_normals(q)
        img = dr.render(verts, robot.faces, robot.colors, ant_camera(q, size=size, track=track), settings,
                        normals=normals)
        return (img * weights).sum()

    return loss


def _fd(loss, q, idx, h=1e-6):
    out = []
    for i in idx:
        qp, qm = q.clone(), q.clone()
        qp[0, i] += h
        qm[0, i] -= h
        out.append((loss(qp) - loss(qm)).item() / (2 * h))
    return torch.tensor(out, dtype=F64)


@pytest.mark.parametrize("backend", ["tiled", "dense"])
def test_image_gradient_wrt_joints_and_base_pose_matches_finite_differences(ant, backend):
    """The ant under a tracking camera, so gradients flow through the mesh, the camera extrinsics and the
    floor: directional derivatives along the 8 hinge angles, the root position, the root quaternion
    (unnormalised) and all of qpos, autograd against central differences."""
    q = ant_pose(1, seed=11)
    settings = dr.RasterSettings(backend=backend, sigma=0.4, gamma=2e-3, znear=0.3, zfar=8.0)
    size = 24 if backend == "tiled" else 16  # the dense reference is slow; it is compared at full size elsewhere
    g = torch.Generator().manual_seed(0)
    weights = torch.randn(1, 3, size, size, dtype=F64, generator=g)
    loss = _loss_fn(ant, settings, weights, size=size)
    qg = q.clone().requires_grad_()
    loss(qg).backward()
    grad = qg.grad[0]
    assert (grad[7:].abs() > 1e-3).all() and (grad[:3].abs() > 1e-3).all()  # every joint and the base matter
    for part in (slice(7, 15), slice(0, 3), slice(3, 7), slice(0, 15)):
        direction = torch.zeros(1, 15, dtype=F64)
        direction[0, part] = torch.randn(part.stop - part.start, dtype=F64, generator=g)
        h = 1e-6
        fd = (loss(q + h * direction) - loss(q - h * direction)).item() / (2 * h)
        ad = float(grad @ direction[0])
        # relative to the terms' magnitude, not their sum: along all of qpos they nearly cancel, and the
        # central difference's own error (~5e-7 here) does not shrink with the sum
        assert abs(ad - fd) < 1e-6 * float(grad.abs() @ direction[0].abs()) + 1e-9, (part, ad, fd)


def test_base_position_gradient_comes_from_the_textured_floor(ant):
    """With a camera tracking the root, moving the root moves robot and camera together: only the floor's
    texture changes in the image. With the floor the base-position gradient is non-zero and matches finite
    differences; without it it is zero (up to rounding)."""
    q = ant_pose(1, seed=12)
    weights = torch.randn(1, 3, 24, 24, dtype=F64, generator=torch.Generator().manual_seed(1))
    with_floor = dr.RasterSettings(sigma=0.4, gamma=2e-3, znear=0.3, zfar=8.0)
    no_floor = dr.RasterSettings(sigma=0.4, gamma=2e-3, znear=0.3, zfar=8.0, floor=None)
    grads = {}
    for name, s in (("floor", with_floor), ("none", no_floor)):
        loss = _loss_fn(ant, s, weights)
        qg = q.clone().requires_grad_()
        loss(qg).backward()
        grads[name] = qg.grad[0, :3]
        if name == "floor":
            fd = _fd(loss, q, range(3))
            assert (grads[name] - fd).abs().max() < 1e-6 * fd.abs().max()
    assert grads["floor"].abs().min() > 1e-2
    assert grads["none"].abs().max() < 1e-9 * grads["floor"].abs().max()


def test_hopper_xz_tracking_gradients(tmp_path):
    """Planar hopper (slides with ref, a hinge root) under an x-z tracking camera."""
    robot = dr.RobotModel.from_mjcf(asset("hopper"), dtype=F64, detail=0)
    q = robot.qpos0[None].clone()
    q[0, 2:] = torch.tensor([0.1, -0.4, -0.5, 0.2], dtype=F64)
    s = dr.RasterSettings(sigma=0.4, gamma=2e-3, znear=0.3, zfar=8.0)
    weights = torch.randn(1, 3, 20, 20, dtype=F64, generator=torch.Generator().manual_seed(2))

    def loss(qq):
        verts, normals = robot.world_vertices_and_normals(qq)
        root = torch.stack([qq[:, 0], torch.zeros_like(qq[:, 0]), qq[:, 1] - 1.25], -1)
        cam = dr.tracking_camera(root, eye_offset=(0, -2.8, 1.35), target_offset=(0, 0, 1.0), track="xz",
                                 fov_deg=45, height=20, width=20)
        return (dr.render(verts, robot.faces, robot.colors, cam, s, normals=normals) * weights).sum()

    qg = q.clone().requires_grad_()
    loss(qg).backward()
    fd = _fd(loss, q, range(6))
    assert (qg.grad[0] - fd).abs().max() < 1e-6 * fd.abs().max()
    assert (qg.grad[0].abs() > 1e-3).all()


def test_measured_bin_capacity_renders_the_frame_as_the_automatic_one(ant):
    """measure_bin_capacity gives a fixed capacity the frame fits in: the tiled render with it equals the
    render with the automatic capacity; a single camera is broadcast to the batch; a tighter capacity than
    the frame needs is reported as an overflow."""
    q = ant_pose(2, seed=4)
    verts, normals = ant.world_vertices_and_normals(q)
    cam = ant_camera(q, size=16)
    auto = dr.RasterSettings(backend="tiled", znear=0.3, zfar=8.0)
    capacity = dr.measure_bin_capacity(verts, ant.faces, cam, auto)
    assert isinstance(capacity, int) and capacity > 0
    fixed = dataclasses.replace(auto, bin_capacity=capacity)
    image = dr.render(verts, ant.faces, ant.colors, cam, fixed, normals=normals)
    reference = dr.render(verts, ant.faces, ant.colors, cam, auto, normals=normals)
    torch.testing.assert_close(image, reference, rtol=0, atol=1e-12)

    one = ant_camera(q[:1], size=16)
    same_pose = verts[:1].expand(2, -1, -1)
    assert dr.measure_bin_capacity(same_pose, ant.faces, one, auto) == dr.measure_bin_capacity(
        verts[:1], ant.faces, one, auto)
    with pytest.raises(RuntimeError, match="bin_capacity"):
        dr.render(verts, ant.faces, ant.colors, cam, dataclasses.replace(auto, bin_capacity=capacity // 8),
                  normals=normals)
    with pytest.raises(ValueError, match=r"verts must be a \(B, V, 3\) tensor"):
        dr.measure_bin_capacity(verts[0], ant.faces, cam, auto)
