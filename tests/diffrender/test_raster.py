"""The soft rasterizer: gradients, backend agreement, limits, symmetries, robustness, memory, errors."""

import dataclasses
import importlib
import itertools
import math
import warnings

import pytest
import torch

import diffrender as dr
from diffrender.profiling import SavedTensorMeter
from diffrender.settings import RASTER_MODELS

from .helpers import (
    F64,
    ant_camera,
    ant_pose,
    asset,
    degenerate_scene,
    hard_zbuffer,
    tiny_camera,
    tiny_scene,
    tiny_settings,
)

BACKENDS = ("dense", "tiled")


def _settings(backend, **kw):
    # tiled: 3x3 tiles that do not divide the 7x6 image, one environment per chunk
    extra = dict(tile_size=3, chunk_elems=1) if backend == "tiled" else {}
    extra.update(kw)
    return tiny_settings(backend=backend, **extra)


@pytest.fixture(scope="module")
def ant64():
    return dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)


# ------------------------------------------------------------------------------------------------ gradients
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("cull", "model"), [(True, "softmax"), (False, "softmax"), (False, "alpha"), (True, "hard"),
                                             (False, "hard")])
def test_gradcheck_vertices_and_colors(backend, cull, model):
    """Each model's gradient against central differences of its own image. The hard image is differentiable
    wherever no pixel centre lies on an edge (the perturbations of 1e-6 move no edge across a centre here)."""
    verts, faces, colors = tiny_scene()
    _, _, cam = tiny_camera()
    s = _settings(backend, cull_backfaces=cull, raster_model=model)
    per_env_colors = colors.expand(2, 9, 3).clone()
    for col in (colors, per_env_colors):
        torch.autograd.gradcheck(lambda v, c: dr.render(v, faces, c, cam, s),
                                 (verts.clone().requires_grad_(), col.clone().requires_grad_()),
                                 eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("model", ["softmax", "alpha", "hard"])
def test_gradcheck_camera_eye_target_and_normals(backend, model):
    verts, faces, colors = tiny_scene()
    eye, target, _ = tiny_camera()
    normals = torch.nn.functional.normalize(torch.randn(2, 9, 3, dtype=F64) + torch.tensor([0, -2.0, 0.5],
                                                                                          dtype=F64), dim=-1)
    s = _settings(backend, raster_model=model)

    def fn(e, t, n):
        cam = dr.Camera.look_at(e, t, (0.0, 0.0, 1.0), 40.0, 7, 6)
        return dr.render(verts, faces, colors, cam, s, normals=n)

    torch.autograd.gradcheck(fn, (eye.clone().requires_grad_(), target.clone().requires_grad_(),
                                  normals.clone().requires_grad_()), eps=1e-6, atol=1e-7, rtol=1e-5,
                             fast_mode=True)


def test_vertex_normals_match_a_loop_and_gradcheck():
    """Area-weighted vertex normals against a loop over the faces (float64), and gradcheck of their backward
    (an index_add into the shared corners) on a closed mesh with unequal face areas."""
    from diffrender.meshes import sphere_mesh
    from diffrender.raster import vertex_normals

    g = torch.Generator().manual_seed(0)
    m = sphere_mesh(1.0, detail=0)
    faces = torch.as_tensor(m.faces, dtype=torch.long)
    verts = torch.as_tensor(m.vertices, dtype=F64)[None] * (1.0 + 0.3 * torch.rand(2, m.num_vertices, 1,
                                                                                        generator=g, dtype=F64))
    acc = torch.zeros_like(verts)
    for a, b, c in faces.tolist():
        n = torch.linalg.cross(verts[:, b] - verts[:, a], verts[:, c] - verts[:, a])
        for k in (a, b, c):
            acc[:, k] += n
    assert torch.allclose(vertex_normals(verts, faces), acc / acc.norm(dim=-1, keepdim=True), atol=1e-14)
    torch.autograd.gradcheck(lambda v: vertex_normals(v, faces), (verts.clone().requires_grad_(),))


def test_camera_gradient_reaches_floor_only_scene():
    """With no faces at all the image is pure floor: it still depends smoothly on the eye."""
    eye, target, _ = tiny_camera()
    faces = torch.zeros(0, 3, dtype=torch.long)
    for backend in BACKENDS:
        s = _settings(backend)

        def fn(e, s=s):
            cam = dr.Camera.look_at(e, target, (0.0, 0.0, 1.0), 40.0, 7, 6)
            return dr.render(torch.zeros(2, 0, 3, dtype=F64), faces, torch.zeros(0, 3, dtype=F64), cam, s)

        e = eye.clone().requires_grad_()
        torch.autograd.gradcheck(fn, (e,), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)
        fn(e).sum().backward()
        assert e.grad.abs().sum() > 1e-3


# ------------------------------------------------------------------------------------------------ backends
def _ant_inputs(robot, batch=2, size=20, seed=0):
    q = ant_pose(batch, seed=seed)
    verts, normals = robot.world_vertices_and_normals(q)
    return verts, normals, ant_camera(q, size=size)


@pytest.mark.parametrize(
    "kw",
    [
        dict(),
        dict(tile_size=5, chunk_elems=1),  # ragged tiles, one environment per chunk
        dict(tile_size=16, cull_backfaces=False, floor=None),
        dict(tile_size=4, sigma=0.3, gamma=1e-3),
        dict(raster_model="alpha", cull_backfaces=False, tile_size=3, chunk_elems=1),
        dict(raster_model="alpha", floor=None),
        dict(raster_model="hard"),
        dict(raster_model="hard", cull_backfaces=False, tile_size=3, chunk_elems=1),
    ],
)
def test_tiled_matches_dense_forward_and_backward(ant64, kw):
    verts, _normals, cam = _ant_inputs(ant64)
    colors = ant64.colors
    out, grads = {}, {}
    for backend in BACKENDS:
        v = verts.clone().requires_grad_()
        c = colors.clone().requires_grad_()
        e = cam.eye.clone().requires_grad_()
        camera = dr.Camera(rotation=cam.rotation, eye=e, focal=cam.focal, height=cam.height, width=cam.width)
        s = dr.RasterSettings(backend=backend, **kw)
        img = dr.render(v, ant64.faces, c, camera, s)
        w = torch.linspace(-1, 1, img.numel(), dtype=F64).view_as(img)
        (img * w).sum().backward()
        out[backend], grads[backend] = img.detach(), (v.grad, c.grad, e.grad)
    assert (out["dense"] - out["tiled"]).abs().max() < 1e-12
    for gd, gt in zip(grads["dense"], grads["tiled"]):
        assert gd.abs().max() > 0
        assert (gd - gt).abs().max() <= 1e-10 * gd.abs().max()


def test_tiled_matches_dense_with_given_normals_and_per_env_colors(ant64):
    verts, normals, cam = _ant_inputs(ant64, batch=2, size=20, seed=5)
    colors = torch.rand(2, ant64.num_vertices, 3, dtype=F64)
    res = []
    for backend in BACKENDS:
        n = normals.clone().requires_grad_()
        c = colors.clone().requires_grad_()
        img = dr.render(verts, ant64.faces, c, cam, dr.RasterSettings(backend=backend, tile_size=6), normals=n)
        img.square().sum().backward()
        res.append((img.detach(), n.grad, c.grad))
    for a, b in zip(*res):
        assert a.abs().max() > 0 and (a - b).abs().max() <= 1e-10 * a.abs().max()


# ------------------------------------------------------------------------------------------------ limits
@pytest.mark.parametrize(("floor", "model"), [(True, "softmax"), (False, "softmax"), (True, "alpha")])
def test_soft_approaches_hard_zbuffer_monotonically(ant64, floor, model):
    """As sigma, gamma -> 0 the fraction of pixels differing from an independent hard z-buffer decreases
    monotonically to (almost) nothing."""
    verts, normals, cam = _ant_inputs(ant64, batch=2, size=32, seed=2)
    base = dict(znear=0.5, zfar=6.0, floor=dr.FloorSettings() if floor else None, raster_model=model)
    hard = hard_zbuffer(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(**base), normals=normals)
    fractions = []
    for sigma, gamma in [(1.0, 1e-2), (0.3, 3e-3), (0.1, 1e-3), (0.03, 3e-4), (0.01, 1e-4), (0.003, 1e-5)]:
        s = dr.RasterSettings(sigma=sigma, gamma=gamma, **base)
        soft = dr.render(verts, ant64.faces, ant64.colors, cam, s, normals=normals)
        fractions.append(((soft - hard).abs().amax(1) > 0.02).double().mean().item())
    assert all(a > b for a, b in itertools.pairwise(fractions)), fractions
    assert fractions[0] > 0.1 and fractions[-1] < 0.01, fractions
    # and towards the renderer's own hard model
    own = dr.render(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(**base | dict(raster_model="hard")),
                    normals=normals)
    assert ((soft - own).abs().amax(1) > 0.02).double().mean() < 0.01


@pytest.mark.parametrize(("floor", "cull"), [(True, True), (False, True), (False, False)])
def test_hard_model_equals_the_independent_hard_zbuffer(ant64, floor, cull):
    verts, normals, cam = _ant_inputs(ant64, batch=2, size=32, seed=2)
    s = dr.RasterSettings(raster_model="hard", znear=0.5, zfar=6.0, cull_backfaces=cull,
                          floor=dr.FloorSettings() if floor else None)
    hard = hard_zbuffer(verts, ant64.faces, ant64.colors, cam, s, normals=normals)
    for backend in BACKENDS:
        img = dr.render(verts, ant64.faces, ant64.colors, cam, dataclasses.replace(s, backend=backend),
                        normals=normals)
        assert (img - hard).abs().max() < 1e-12


def _coverage_masks(robot, q, models, size=64, **kw):
    """Per model, the robot's mask: pixels where it owns more than half the colour (white unlit robot over a
    black sky, no floor). (B, H, W) bool each."""
    verts, normals = robot.world_vertices_and_normals(q)
    cam = dr.tracking_camera(q[:, :3], eye_offset=(0.5, -2.0, 1.0), target_offset=(0.0, 0.0, 1.0), track="xyz",
                             fov_deg=90.0, height=size, width=size)
    white = torch.ones_like(robot.colors)
    out = {}
    for model in models:
        s = dr.RasterSettings(raster_model=model, floor=None, background=(0.0, 0.0, 0.0), ambient=1.0, diffuse=0.0,
                              **kw)
        out[model] = dr.render(verts, robot.faces, white, cam, s, normals=normals)[:, 0] > 0.5
    return out


def _iou(a, b) -> float:
    return float((a & b).sum() / (a | b).sum())


@pytest.mark.slow
@pytest.mark.parametrize(("sigma", "cull"), [(0.02, True), (0.005, False)])
def test_soft_silhouettes_are_not_dilated(sigma, cull):
    """The soft models' half-coverage mask agrees with the hard model's (IoU >= 0.99) on ant images at task
    resolution: the robot's share of a silhouette pixel follows its coverage, 1/2 on the true edge, instead of
    owning every pixel out to the coverage cut-off. In the sharp limit: the tails of the k faces that meet at a
    silhouette vertex add up, which moves the half level out by sigma ln(2k - 1) there; without culling the front
    and back faces of a silhouette both count (sigma ln 3 along it), hence the smaller sigma."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=1)
    masks = _coverage_masks(robot, ant_pose(3, seed=3), ("hard", "softmax", "alpha"), sigma=sigma, gamma=1e-4,
                            cull_backfaces=cull)
    assert masks["hard"].sum() > 500
    for model in ("softmax", "alpha"):
        assert _iou(masks[model], masks["hard"]) >= 0.99, (model, _iou(masks[model], masks["hard"]))


@pytest.mark.parametrize("model", ["softmax", "alpha", "hard"])
def test_silhouette_gradient_over_the_floor(model):
    """One triangle in front of the floor, moved sideways by 1e-3 px: at its silhouette pixels the soft models'
    derivative predicts the image change (central differences), the hard model's is zero there (its image
    there does not change under so small a step, up to rounding)."""
    verts = torch.tensor([[[-0.3, 0.0, 0.6], [0.3, 0.0, 0.6], [0.0, 0.0, 1.1]]], dtype=F64)
    faces = torch.tensor([[0, 2, 1]])
    colors = torch.full((3, 3), 0.9, dtype=F64)
    cam = dr.Camera.look_at(torch.tensor([0.0, -2.0, 0.9], dtype=F64), torch.tensor([0.0, 0.0, 0.8], dtype=F64),
                            (0.0, 0.0, 1.0), 40.0, 16, 16)
    s = dr.RasterSettings(raster_model=model, sigma=0.3, gamma=1e-3, cull_backfaces=False)
    shift = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    # world metres per pixel at the triangle's depth: 1e-3 px of motion
    h = 1e-3 * 2.0 * math.tan(math.radians(20.0)) / 16 * 2.0

    def img(t):
        return dr.render(verts + t * shift, faces, colors, cam, s)

    t = torch.zeros((), dtype=F64, requires_grad=True)
    base = img(t)
    weights = torch.randn(base.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    hard_s = dataclasses.replace(s, raster_model="hard")
    hard = dr.render(verts, faces, colors, cam, hard_s)
    empty = dr.render(verts[:, :0], faces[:0], colors[:0], cam, hard_s)  # the floor and sky alone
    covered = (hard - empty).abs().amax(1) > 0
    inside = torch.nn.functional.max_pool2d(covered.double(), 3, 1, 1) > 0
    outside = torch.nn.functional.max_pool2d((~covered).double(), 3, 1, 1) > 0
    silhouette = (inside & outside)[:, None].expand_as(base)
    assert silhouette.sum() > 3 * 10
    fd = ((img(torch.tensor(h, dtype=F64)) - img(torch.tensor(-h, dtype=F64))) / (2 * h)).detach()
    (grad,) = torch.autograd.grad((base * weights * silhouette).sum(), t)
    predicted, observed = float(grad), float((fd * weights * silhouette).sum())
    if model == "hard":
        assert abs(predicted) < 1e-12 and abs(observed) < 1e-8  # rounding of the unchanged image
    else:
        assert abs(observed) > 1.0 and abs(predicted - observed) < 1e-4 * abs(observed), (predicted, observed)


def test_floor_occludes_faces_below_it_except_in_alpha():
    """A triangle half below the floor: "softmax" and "hard" hide the buried half, "alpha" shows it."""
    verts = torch.tensor([[[-0.4, 0.0, -0.3], [0.4, 0.0, -0.3], [0.0, 0.0, 0.5]]], dtype=F64)
    faces = torch.tensor([[0, 2, 1]])
    colors = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64).expand(3, 3)
    cam = dr.Camera.look_at(torch.tensor([0.0, -2.0, 1.0], dtype=F64), torch.tensor([0.0, 0.0, 0.0], dtype=F64),
                            (0.0, 0.0, 1.0), 50.0, 24, 24)
    red = {}
    for model in ("hard", "softmax", "alpha"):
        img = dr.render(verts, faces, colors, cam, dr.RasterSettings(raster_model=model, cull_backfaces=False))
        red[model] = img[0, 0] - img[0, 1] > 0.2  # the floor and sky are grey-blue
    uv = cam.project(verts)[0]
    assert red["alpha"].sum() > red["hard"].sum() + 10
    assert (red["softmax"] ^ red["hard"]).sum() <= 2  # pixel centres within ~sigma of an edge may differ
    assert red["hard"].sum() > 10 and float(uv[:, 1].max()) > 12


@pytest.mark.parametrize("model", ["softmax", "alpha"])
def test_tessellated_surface_has_no_seams(model):
    """A square tessellated into many triangles renders like the same square as two triangles: the mesh's
    internal edges leave no trace (in "alpha" mode the coverage of adjacent triangles must add up to 1)."""
    n = 6
    g = torch.linspace(-0.5, 0.5, n + 1, dtype=F64)
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    verts = torch.stack([xx.flatten(), torch.zeros_like(xx.flatten()), yy.flatten() + 1.0], -1)[None]
    idx = torch.arange((n + 1) ** 2).view(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].flatten(), idx[:-1, 1:].flatten(), idx[1:, :-1].flatten(), idx[1:, 1:].flatten()
    fine = torch.cat([torch.stack([a, c, d], 1), torch.stack([a, d, b], 1)])  # faces -y (towards the camera)
    coarse = torch.tensor([[0, n * (n + 1), (n + 1) ** 2 - 1], [0, (n + 1) ** 2 - 1, n]])
    colors = torch.full((verts.shape[1], 3), 0.5, dtype=F64)
    normals = torch.tensor([0.0, -1.0, 0.0], dtype=F64).expand_as(verts).contiguous()
    cam = dr.Camera.look_at(torch.tensor([0.0, -2.0, 1.0], dtype=F64), torch.tensor([0.0, 0.0, 1.0], dtype=F64),
                            (0.0, 0.0, 1.0), 40.0, 24, 24)
    s = dr.RasterSettings(sigma=0.5, raster_model=model, cull_backfaces=False)
    imgs = [dr.render(verts, f, colors, cam, s, normals=normals) for f in (fine, coarse)]
    uv = cam.project(verts)[0]
    inner = (uv[:, 0].min() + 3, uv[:, 0].max() - 3, uv[:, 1].min() + 3, uv[:, 1].max() - 3)
    jj, ii = torch.meshgrid(torch.arange(24) + 0.5, torch.arange(24) + 0.5, indexing="xy")
    mask = (jj > inner[0]) & (jj < inner[1]) & (ii > inner[2]) & (ii < inner[3])
    assert mask.sum() > 50
    diff = (imgs[0] - imgs[1]).abs().amax(1)[0]
    # Both soft models compose over the sky by the joint coverage A = min(1, sum D), which inside the square
    # falls short of 1 by the outer edges' sigmoid tails (exp(-6) at 3 px with sigma 0.5, times the colour
    # contrast) and differently for the two tessellations: that, not a seam, is the difference left. (The
    # product form 1 - prod(1 - D) left seams of ~0.1 here.)
    assert diff[mask].max() < 1e-3, diff[mask].max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_perspective_correct_interpolation(backend):
    """A quad receding from ~1 m to 5 m with albedo and normals varying along it: away from its edges every
    pixel equals the independent hard z-buffer's perspective-correct interpolation (screen-space
    barycentrics would be off by up to ~0.2 here)."""
    verts = torch.tensor([[[-1.5, 0.6, 0.0], [1.5, 0.6, 0.0], [-1.5, 5.0, 0.0], [1.5, 5.0, 0.0]]], dtype=F64)
    faces = torch.tensor([[0, 1, 3], [0, 3, 2]])  # facing up, towards the camera above it
    colors = torch.tensor([[0.0, 0.1, 1.0], [0.0, 0.9, 0.5], [1.0, 0.1, 0.0], [1.0, 0.9, 0.5]], dtype=F64)
    normals = torch.nn.functional.normalize(torch.tensor([[[0.0, -1, 0.3], [0.3, -1, 0.1], [-0.5, -1, 1],
                                                           [0.2, -0.2, 1]]], dtype=F64), dim=-1)
    cam = dr.Camera.look_at(torch.tensor([0.0, 0.0, 1.0], dtype=F64), torch.tensor([0.0, 2.0, 0.0], dtype=F64),
                            (0.0, 0.0, 1.0), 70.0, 32, 32)
    # sigma 0.05: at 1.5 px inside, the sky's share through the coverage, about exp(-1.5 / sigma), is below 1e-13
    s = dr.RasterSettings(backend=backend, floor=None, sigma=0.05, cull_backfaces=True, znear=0.1, zfar=10.0)
    soft = dr.render(verts, faces, colors, cam, s, normals=normals)
    hard = hard_zbuffer(verts, faces, colors, cam, s, normals=normals)
    # pixels farther than 1.5 px from every edge of both triangles (the diagonal included)
    uv = cam.project(verts)[0, :, :2]
    jj, ii = torch.meshgrid(torch.arange(32, dtype=F64) + 0.5, torch.arange(32, dtype=F64) + 0.5, indexing="xy")
    p = torch.stack([jj, ii], -1)
    dist = torch.full((32, 32), math.inf, dtype=F64)
    for a, b in ((0, 1), (1, 3), (3, 2), (2, 0), (0, 3)):
        e = uv[b] - uv[a]
        t = (((p - uv[a]) @ e) / (e @ e)).clamp(0, 1)
        dist = torch.minimum(dist, (p - uv[a] - t[..., None] * e).norm(dim=-1))
    covered = (hard - torch.tensor(s.background, dtype=F64).view(1, 3, 1, 1)).abs().amax(1)[0] > 1e-6
    mask = covered & (dist > 1.5)
    assert mask.sum() > 100
    assert (soft - hard).abs().amax(1)[0][mask].max() < 1e-9
    # and the scene does exercise perspective: screen-space barycentrics differ
    assert (hard[0, 0][mask].max() - hard[0, 0][mask].min()) > 0.5


# ------------------------------------------------------------------------------------------------ symmetries
def test_mirror_equivariance(ant64):
    """Mirroring the world about the camera's vertical plane x = s/2 (which maps the checker onto itself)
    mirrors the image left-right, for both backends."""
    q = ant_pose(2, seed=7)
    verts, normals = ant64.world_vertices_and_normals(q)
    s_sq = dr.FloorSettings().square_size
    eye = torch.tensor([s_sq / 2, -2.0, 1.2], dtype=F64)
    target = torch.tensor([s_sq / 2, 0.3, 0.5], dtype=F64)
    cam = dr.Camera.look_at(eye, target, (0.0, 0.0, 1.0), 60.0, 20, 26)
    flip = torch.tensor([-1.0, 1.0, 1.0], dtype=F64)
    mverts = verts * flip + torch.tensor([s_sq, 0, 0], dtype=F64)
    mfaces = ant64.faces[:, [0, 2, 1]]  # mirroring flips the winding
    for backend in BACKENDS:
        s = dr.RasterSettings(backend=backend, sigma=0.5, gamma=1e-3, light_dir=(0.3, -0.5, 1.0))
        sm = dr.RasterSettings(backend=backend, sigma=0.5, gamma=1e-3, light_dir=(-0.3, -0.5, 1.0))
        a = dr.render(verts, ant64.faces, ant64.colors, cam, s, normals=normals)
        b = dr.render(mverts, mfaces, ant64.colors, cam, sm, normals=normals * flip)
        assert (a - a.flip(-1)).abs().max() > 0.05  # the scene itself is not symmetric
        assert (a - b.flip(-1)).abs().max() < 1e-12


def test_integer_pixel_shift_equivariance(ant64):
    """Widening the image by 2k pixels moves the principal point by k: the wide image, cropped by k, equals the
    narrow one (tiles land differently relative to the content)."""
    verts, _normals, cam = _ant_inputs(ant64, batch=2, size=24, seed=3)
    for backend in BACKENDS:
        s = dr.RasterSettings(backend=backend, tile_size=8)
        ref = dr.render(verts, ant64.faces, ant64.colors, cam, s)
        for dx, dy in ((3, 0), (0, 2), (5, 1)):
            wide = dr.Camera(rotation=cam.rotation, eye=cam.eye, focal=cam.focal, height=24 + 2 * dy,
                             width=24 + 2 * dx)
            img = dr.render(verts, ant64.faces, ant64.colors, wide, s)
            assert (img[..., dy: dy + 24, dx: dx + 24] - ref).abs().max() < 1e-12


# ------------------------------------------------------------------------------------------------ robustness
def test_degenerate_faces_give_finite_images_and_gradients():
    """Zero-area, collinear, edge-on, behind-camera, near-plane-straddling faces and a vertex at the eye."""
    verts, faces, colors, cam = degenerate_scene()
    for backend in BACKENDS:
        for cull in (True, False):
            v = verts.clone().requires_grad_()
            s = dr.RasterSettings(backend=backend, cull_backfaces=cull, sigma=0.7, gamma=1e-3, znear=0.1, zfar=8)
            img = dr.render(v, faces, colors, cam, s)
            assert torch.isfinite(img).all() and 0 <= img.min() and img.max() <= 1
            img.sum().backward()
            assert torch.isfinite(v.grad).all()
            assert v.grad[0, :3].abs().sum() > 0  # the good face gets gradients
            assert v.grad[0, 12:18].abs().sum() == 0  # dropped faces (behind, straddling) get none


def test_float32_matches_float64(ant64):
    verts, _normals, cam = _ant_inputs(ant64, batch=2, size=24, seed=4)
    ref = dr.render(verts, ant64.faces, ant64.colors, cam)
    cam32 = dr.Camera(rotation=cam.rotation.float(), eye=cam.eye.float(), focal=cam.focal, height=24, width=24)
    img = dr.render(verts.float(), ant64.faces, ant64.colors.float(), cam32)
    assert img.dtype == torch.float32 and (img.double() - ref).abs().max() < 2e-3


# ------------------------------------------------------------------------------------------------ memory
def test_backward_twice_with_retain_graph(ant64):
    verts, _normals, cam = _ant_inputs(ant64, batch=2, size=16)
    v = verts.clone().requires_grad_()
    img = dr.render(v, ant64.faces, ant64.colors, cam, dr.RasterSettings(chunk_elems=1))
    loss = (img * torch.rand_like(img)).sum()
    g1, = torch.autograd.grad(loss, v, retain_graph=True)
    g2, = torch.autograd.grad(loss, v)
    assert g1.abs().max() > 0 and torch.equal(g1, g2)


def _saved_bytes(verts, faces, colors, cam, settings):
    v = verts.clone().requires_grad_()
    with SavedTensorMeter(exclude=[faces]) as meter:
        img = dr.render(v, faces, colors, cam, settings)
    img.sum().backward()  # what was saved is enough for a backward
    assert v.grad.abs().sum() > 0
    return meter.bytes


def test_saved_memory_is_flat_in_faces(ant64):
    """Tiled: saved-for-backward bytes do not change when the face count grows 10x over the same vertices
    (only the caller's faces tensor itself, excluded here, grows); dense grows with faces x pixels."""
    verts, _, cam = _ant_inputs(ant64, batch=2, size=16)
    g = torch.Generator().manual_seed(0)
    # 10x the faces over the same vertices: the mesh plus reshuffled copies of its faces
    many = torch.cat([ant64.faces] + [ant64.faces[torch.randperm(ant64.num_faces, generator=g)][:, [0, 2, 1]]
                                      .roll(k, dims=1) for k in range(9)])
    assert many.shape[0] == 10 * ant64.num_faces and int(many.max()) < ant64.num_vertices
    s = dr.RasterSettings(cull_backfaces=False)
    small, big = (_saved_bytes(verts, f, ant64.colors, cam, s) for f in (ant64.faces, many))
    assert small == big
    assert small <= verts.numel() * 8 + ant64.colors.numel() * 8 + 4096  # inputs only: vertices, colours, camera
    # the measurement does see per-face intermediates where they exist (dense, 2x faces)
    sd = dr.RasterSettings(backend="dense", cull_backfaces=False)
    d_small, d_big = (_saved_bytes(verts[:1], f, ant64.colors, _first(cam), sd)
                      for f in (ant64.faces, many[: 2 * ant64.num_faces]))
    assert d_big > 1.8 * d_small > 50 * small


def _first(cam):
    return dr.Camera(rotation=cam.rotation[:1], eye=cam.eye[:1], focal=cam.focal, height=cam.height,
                     width=cam.width)


def test_saved_memory_is_linear_in_vertices(ant64):
    """Growing the scene (extra meshes) grows saved bytes only with B * V."""
    verts, _, cam = _ant_inputs(ant64, batch=2, size=16)
    big = ant64.with_extra_meshes(40, 200)
    q = ant_pose(2)
    vb = big.world_vertices(q)
    s = dr.RasterSettings()
    a = _saved_bytes(verts, ant64.faces, ant64.colors, cam, s)
    b = _saved_bytes(vb, big.faces, big.colors, cam, s)
    per_vertex = (b - a) / (big.num_vertices - ant64.num_vertices)
    assert per_vertex <= 2 * 3 * 8 + 3 * 8  # verts (B = 2) and shared colours, float64


# ------------------------------------------------------------------------------------------------ errors
def test_bin_overflow_raises_with_numbers_or_poisons_without_sync(ant64):
    verts, _, cam = _ant_inputs(ant64, batch=3, size=24)
    s = dr.RasterSettings(bin_capacity=64)
    with pytest.raises(RuntimeError, match=r"environments 0\.\.2 \(rendered together\) need \d+ \(tile, face\) "
                                           r"pairs, \d+ per environment, but bin_capacity is 64.*busiest tile.*"
                                           r"holds \d+ faces.*bin_capacity=\.\.\.\) to at least"):
        dr.render(verts, ant64.faces, ant64.colors, cam, s)
    img = dr.render(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(bin_capacity=64, sync_checks=False))
    assert torch.isnan(img).all()
    # exactly the capacity needed: no error, no NaN; one slot less: error
    st = dr.raster.tiled_static(dr.RasterSettings(), cam)
    need = -(-int(dr.raster.count_pairs(verts, cam.rotation, cam.eye, ant64.faces, st).sum()) // 3)
    img = dr.render(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(bin_capacity=need))
    assert torch.isfinite(img).all()
    with pytest.raises(RuntimeError, match="bin overflow"):
        dr.render(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(bin_capacity=need - 1))
    # one environment per chunk: only the overflowing environments are poisoned
    s1 = dict(chunk_elems=1, sync_checks=False)
    per_env = dr.raster.count_pairs(verts, cam.rotation, cam.eye, ant64.faces, st)
    cap = int(per_env.min())
    img = dr.render(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(bin_capacity=cap, **s1))
    assert torch.equal(torch.isnan(img).flatten(1).all(1), per_env > cap) and (per_env > cap).any()


def test_automatic_capacity_grows_instead_of_failing(ant64, monkeypatch):
    render_module = importlib.import_module("diffrender.render")
    monkeypatch.setattr(render_module, "_growth_warned", False)  # as in a fresh process
    # and no capacities of earlier tests: a freed faces tensor's address, reused here, would name their entries
    monkeypatch.setattr(render_module, "_capacity_cache", {})
    verts, _, cam = _ant_inputs(ant64, batch=2, size=24)
    small = ant64.to(dtype=F64)  # a fresh faces tensor: a fresh automatic capacity
    # first frame: the robots half out of view set a small capacity
    aside = verts + 1.5 * cam.rotation[:, 0][:, None]
    st = dr.raster.tiled_static(dr.RasterSettings(), cam)
    counts = [dr.raster.count_pairs(v, cam.rotation, cam.eye, small.faces, st).sum() for v in (aside, verts)]
    assert counts[0] * 1.5 < counts[1]
    dr.render(aside, small.faces, small.colors, cam)
    ref = dr.render(verts, small.faces, small.colors, cam, dr.RasterSettings(backend="dense"))
    keys = [k for k in render_module._capacity_cache if k[0] == small.faces.data_ptr()]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # so that only diffrender's own once-per-process rule can hide a repeat
        # a busier frame needs more than the measured capacity: it grows, the frame is rendered completely
        img = dr.render(verts, small.faces, small.colors, cam)
        assert (img - ref).abs().max() < 1e-12
        # a later growth renders as completely but says nothing more (a warning once, not every frame)
        for key in keys:
            render_module._capacity_cache[key] = 64
        again = dr.render(verts, small.faces, small.colors, cam)
        assert (again - ref).abs().max() < 1e-12 and all(render_module._capacity_cache[k] > 64 for k in keys)
    grown = [w for w in caught if issubclass(w.category, dr.BinCapacityWarning)]
    assert len(grown) == 1 and "automatic bin capacity grown" in str(grown[0].message)
    assert issubclass(dr.BinCapacityWarning, UserWarning)  # filterable as a category of its own


def test_a_new_faces_tensor_at_a_freed_address_is_checked_again():
    """The index check is cached per faces tensor (keyed by its storage); a freed tensor's address reused by a
    new faces tensor with bad indices must not hit that cache."""
    verts, faces, colors = tiny_scene()
    _, _, cam = tiny_camera()
    s = tiny_settings()
    for _ in range(20):  # the allocator hands a freed block of the same size back
        good = faces.clone()
        dr.render(verts, good, colors, cam, s)
        del good
        last = torch.zeros_like(faces, dtype=torch.bool)
        last[-1, -1] = True
        bad = faces.masked_fill(last, verts.shape[1])  # a fresh tensor (version 0), one index out of range
        with pytest.raises(ValueError, match="faces index vertices"):
            dr.render(verts, bad, colors, cam, s)
        del bad


def test_bad_inputs_raise_clear_errors():
    verts, faces, colors = tiny_scene()
    _, _, cam = tiny_camera()
    s = tiny_settings()
    cases = [
        (dict(verts=verts[0]), r"verts must have shape \(B, V, 3\)"),
        (dict(verts=verts.long()), "verts must be float32 or float64"),
        (dict(verts=verts.float()), "colors is torch.float64 but verts is torch.float32"),
        (dict(verts=verts.float(), colors=colors.float()), "camera is torch.float64 but verts is torch.float32"),
        (dict(colors=colors.float()), "colors is torch.float32 but verts is torch.float64"),
        (dict(colors=colors[:5]), r"colors must have shape \(9, 3\) or \(2, 9, 3\)"),
        (dict(faces=faces.double()), "faces must be an int64/int32 tensor"),
        (dict(faces=faces[:, :2]), r"faces must have shape \(F, 3\)"),
        (dict(faces=faces.to("meta")), "faces is on meta but verts is on cpu"),
        (dict(faces=faces + 1), r"faces index vertices 1\.\.9 but there are 9 vertices"),
        (dict(verts=verts.clone().index_put_((torch.tensor([1]),), torch.tensor(math.nan, dtype=F64))),
         "verts contain.* NaN or inf"),
        (dict(colors=colors.clone().fill_(math.inf)), "colors contain.* NaN or inf"),
        (dict(camera=tiny_camera(1)[2].expand(1)), None),  # a single camera broadcasts: fine
        (dict(camera="cam"), "camera must be a diffrender.Camera"),
        (dict(settings=dict(sigma=1.0)), "settings must be a RasterSettings"),
        (dict(normals=torch.zeros(2, 8, 3, dtype=F64)), "normals must have the shape of verts"),
    ]
    for override, msg in cases:
        args = dict(verts=verts, faces=faces, colors=colors, camera=cam, settings=s) | override
        if msg is None:
            dr.render(**args)
            continue
        with pytest.raises(ValueError, match=msg):
            dr.render(**args)
    three = dr.Camera.look_at(torch.zeros(3, 3, dtype=F64), torch.ones(3, dtype=F64), (0, 0, 1.0), 40, 7, 6)
    with pytest.raises(ValueError, match="camera has 3 views but verts has 2 environments"):
        dr.render(verts, faces, colors, three, s)
    for kw, msg in ((dict(sigma=0.0), "sigma"), (dict(znear=2.0, zfar=1.0), "znear"), (dict(backend="x"), "backend"),
                    (dict(raster_model="soft"), "raster_model must be one of 'hard', 'softmax', 'alpha'"),
                    (dict(tile_size=0), "tile_size"), (dict(bin_capacity=-1), "bin_capacity"),
                    (dict(background=(2, 0, 0)), "background")):
        with pytest.raises(ValueError, match=msg):
            dr.RasterSettings(**kw)
    with pytest.raises(TypeError):
        dr.RasterSettings(0.5)  # keyword-only


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(ant64):
    verts, _normals, cam = _ant_inputs(ant64, batch=2, size=24)
    ref_v = verts.clone().requires_grad_()
    ref = dr.render(ref_v, ant64.faces, ant64.colors, cam)
    ref.square().sum().backward()
    dev = torch.device("cuda")
    cam_d = dr.Camera(rotation=cam.rotation.to(dev), eye=cam.eye.to(dev), focal=cam.focal, height=24, width=24)
    v = verts.to(dev).requires_grad_()
    img = dr.render(v, ant64.faces.to(dev), ant64.colors.to(dev), cam_d)
    img.square().sum().backward()
    assert (img.cpu() - ref).abs().max() < 1e-10
    assert (v.grad.cpu() - ref_v.grad).abs().max() < 1e-8 * ref_v.grad.abs().max()


@pytest.mark.slow
def test_compiled_kernel_matches_eager():
    """settings.compile runs binning and the kernel through torch.compile (forward and the recompute in
    backward): same image and gradients as eager. (Slow: inductor compiles three graphs, ~30 s on 2 cores.
    It caught an inductor mis-fusion of a scatter-add into a zero buffer, see kernel.py.)"""
    verts, faces, colors = tiny_scene()
    _, _, cam = tiny_camera(height=12, width=10)
    for model in RASTER_MODELS:
        res = []
        for comp in (False, True):
            v = verts.clone().requires_grad_()
            img = dr.render(v, faces, colors, cam, tiny_settings(compile=comp, raster_model=model))
            (img * torch.linspace(0, 1, img.numel(), dtype=F64).view_as(img)).sum().backward()
            res.append((img.detach(), v.grad))
        assert (res[0][0] - res[1][0]).abs().max() < 1e-12
        assert res[0][1].abs().max() > 0
        assert (res[0][1] - res[1][1]).abs().max() < 1e-10 * res[0][1].abs().max()
