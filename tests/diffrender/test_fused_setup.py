"""The fused backend's Triton setup kernels (:func:`diffrender.raster.fused.face_setup`) against the PyTorch
reference :func:`diffrender.raster.fused.face_coefficients`: forward (coefficients, face and block boxes) and
backward (into vertices, normals, colours and the camera), float64.

Runs on CUDA where there is a GPU, else on the CPU through Triton's interpreter; skipped without Triton.
"""

import math
import os

import pytest
import torch

if not torch.cuda.is_available():  # must be set before the kernels are defined (import of the module)
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")

import diffrender as dr
from diffrender.raster import fused
from diffrender.raster.fused import reference
from diffrender.raster.kernel import Static, face_validity, project, vertex_normals
from diffrender.raster.setup_kernels import floor_planes

from .helpers import F64, ant_camera, ant_pose, asset, degenerate_scene

DEV = torch.device("cuda" if torch.cuda.is_available() else "cpu")
pytestmark = pytest.mark.skipif(not fused.available(DEV), reason="fused kernels cannot run here")


def _static(cam: dr.Camera, **kw) -> Static:
    return Static.make(dr.RasterSettings(**kw), focal=cam.focal, height=cam.height, width=cam.width, tile_h=4,
                       tile_w=4)


def _scene(cull: bool):
    """Two environments of :func:`degenerate_scene` (zero-area, collinear, edge-on, behind-camera,
    znear-straddling faces, a vertex at the eye), seen from two eyes, plus a random mesh that shares vertices
    between faces (some back-facing), and one face beyond zfar (kept, as face_validity keeps it). Returns
    verts (2, V, 3), faces (F, 3), camera, static settings, and the (2, F) validity of the faces."""
    verts, faces, _, cam = degenerate_scene()
    g = torch.Generator().manual_seed(1)
    mesh = torch.rand(10, 3, dtype=F64, generator=g) * torch.tensor([1.6, 1.0, 1.2], dtype=F64) - torch.tensor(
        [0.8, 0.5, -0.2], dtype=F64)
    mesh_faces = torch.stack([torch.randperm(10, generator=g)[:3] for _ in range(13)])
    far = torch.tensor([[-1.0, 9.0, 0.5], [1.0, 9.0, 0.5], [0.0, 9.0, 1.8]], dtype=F64)  # z > zfar = 8
    nv = verts.shape[1]
    verts = torch.cat([verts[0], mesh, far])[None].repeat(2, 1, 1)
    verts[1] += 0.03 * torch.randn(verts.shape[1:], dtype=F64, generator=g)
    faces = torch.cat([faces, mesh_faces + nv, torch.arange(3)[None] + nv + 10])
    eye = torch.stack([cam.eye[0], cam.eye[0] + torch.tensor([0.2, 0.1, -0.1], dtype=F64)])
    cam = dr.Camera.look_at(eye, torch.tensor([0.0, 0.0, 0.8], dtype=F64), (0.0, 0.0, 1.0), 50.0, 16, 16)
    verts, faces = verts.to(DEV), faces.to(DEV)
    cam = dr.Camera(rotation=cam.rotation.to(DEV), eye=cam.eye.to(DEV), focal=cam.focal, height=16, width=16)
    st = _static(cam, cull_backfaces=cull, znear=0.1, zfar=8.0)
    valid = face_validity(project(verts, cam.rotation, cam.eye, st)[:, faces], st)
    return verts, faces, cam, st, valid


def _new(verts, normals, colors, rotation, eye, faces, st, fb, sb):
    """face_setup's (coef, face_box, block_box, super_box) from the inputs of face_coefficients."""
    uvz = project(verts, rotation, eye, st)
    n = vertex_normals(verts, faces) if normals is None else normals
    return fused.face_setup(uvz, n, colors, faces, st, face_block=fb, super_block=sb)


def _both(verts, normals, colors, rotation, eye, faces, st, fb, sb):
    """The reference's (coef, face_box, block_box) and :func:`_new`'s outputs, from the same leaves."""
    return (fused.face_coefficients(verts, normals, colors, rotation, eye, faces, st, fb),
            _new(verts, normals, colors, rotation, eye, faces, st, fb, sb))


def _check_forward(ref, new, sb, *, tol=0.0):
    coef_r, box_r, bbox_r = ref
    coef, box, bbox, sbox = new
    assert coef.shape == coef_r.shape and box.shape == box_r.shape
    nb = bbox_r.shape[2]
    assert bbox.shape[2] == -(-nb // sb) * sb and sbox.shape[2] == -(-nb // sb)
    scale = coef_r.abs().amax(2, keepdim=True).clamp(min=1.0)  # rows differ in magnitude by orders
    assert ((coef.detach() - coef_r.detach()).abs() <= tol * scale).all()
    assert ((box - box_r).abs() <= tol * box_r.abs().clamp(min=1.0)).all()
    padded, sup = fused.super_block_boxes(bbox_r, sb)  # the reference's padded block boxes and their unions
    assert ((bbox - padded).abs() <= tol * padded.abs().clamp(min=1.0)).all()
    assert ((sbox - sup).abs() <= tol * sup.abs().clamp(min=1.0)).all()


def _grads(out, leaves, weight):
    return torch.autograd.grad((out * weight).sum(), leaves, allow_unused=True)


@pytest.mark.parametrize("cull", [True, False])
@pytest.mark.parametrize(("colors_kind", "normals_given", "fb", "sb"),
                         [("shared", False, 4, 2), ("per_env", True, 8, 3), ("per_env", False, 16, 1),
                          ("shared", True, 32, 4)])
def test_face_setup_matches_face_coefficients(cull, colors_kind, normals_given, fb, sb):
    """Dropped faces (behind znear, zero area, back-facing with culling), a face beyond zfar, padding faces
    (F is no multiple of the block), shared or per-environment colours, normals given or the mesh's: the same
    coefficients and boxes as the reference, and the same gradients of a random weighting of the coefficients
    into vertices, normals, colours, camera rotation and eye."""
    verts, faces, cam, st, valid = _scene(cull)
    assert (~valid).any() and valid.any() and faces.shape[0] % fb  # the cases this test is about are there
    g = torch.Generator(device=DEV).manual_seed(fb)
    nv = verts.shape[1]
    colors = torch.rand((nv, 3) if colors_kind == "shared" else (2, nv, 3), dtype=F64, device=DEV, generator=g)
    normals = torch.randn(2, nv, 3, dtype=F64, device=DEV, generator=g) if normals_given else None
    leaves_r, leaves_n = ([x.clone().requires_grad_() if x is not None else None
                           for x in (verts, colors, cam.rotation, cam.eye, normals)] for _ in range(2))
    v, c, r, e, n = leaves_r
    ref = fused.face_coefficients(v, n, c, r, e, faces, st, fb)
    v, c, r, e, n = leaves_n
    new = _new(v, n, c, r, e, faces, st, fb, sb)
    _check_forward(ref, new, sb, tol=1e-13)
    weight = torch.randn(ref[0].shape, dtype=F64, device=DEV, generator=g)
    keep = [i for i, x in enumerate(leaves_r) if x is not None]
    g_ref = _grads(ref[0], [leaves_r[i] for i in keep], weight)
    g_new = _grads(new[0], [leaves_n[i] for i in keep], weight)
    for gr, gn in zip(g_ref, g_new):
        assert gr.abs().max() > 0
        assert (gr - gn).abs().max() <= 1e-12 * gr.abs().max()


def test_face_setup_backward_leaves_dropped_and_padding_faces_out():
    """A gradient only on dropped faces' geometry rows reaches no vertex (their corners are a constant
    triangle); one on their colour rows does (the reference differentiates those too), and none on padding
    faces."""
    verts, faces, cam, st, valid = _scene(True)
    uvz = project(verts, cam.rotation, cam.eye, st).requires_grad_()
    colors = torch.rand(verts.shape[1], 3, dtype=F64, device=DEV).requires_grad_()
    coef = fused.face_setup(uvz, vertex_normals(verts, faces), colors, faces, st, face_block=8, super_block=2)[0]
    nf = faces.shape[0]
    dropped = torch.nn.functional.pad(~valid, (0, coef.shape[2] - nf), value=False)  # (2, Fp)
    weight = torch.zeros_like(coef)
    weight[:, :27] = dropped[:, None].to(F64)  # geometry rows of dropped faces
    weight[:, :, nf:] = 1.0  # every row of the padding faces
    g_uvz, g_col = torch.autograd.grad((coef * weight).sum(), (uvz, colors), retain_graph=True)
    assert torch.equal(g_uvz, torch.zeros_like(g_uvz)) and torch.equal(g_col, torch.zeros_like(g_col))
    weight[:, 36:] = dropped[:, None].to(F64)
    g_col = torch.autograd.grad((coef * weight).sum(), colors)[0]
    used = faces[(~valid).any(0)].unique()
    assert (g_col[used] != 0).any(-1).all() and (g_col.abs().sum(-1) != 0).sum() == used.numel()


def test_face_setup_without_faces_is_one_padding_block():
    cam = ant_camera(ant_pose(2).to(DEV), size=8)
    st = _static(cam)
    verts = torch.zeros(2, 0, 3, dtype=F64, device=DEV)
    faces = torch.zeros(0, 3, dtype=torch.long, device=DEV)
    ref, new = _both(verts, None, torch.zeros(0, 3, dtype=F64, device=DEV), cam.rotation, cam.eye, faces, st, 16, 4)
    _check_forward(ref, new, 4)


def test_face_setup_on_the_ant_matches_float64_and_float32():
    """944 faces sharing vertices (many atomic adds into one vertex), 15 blocks in one super-block of 16:
    float64 to rounding; float32 to float32 rounding (relative to each row's scale)."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0, device=DEV)
    q = ant_pose(2, seed=7).to(DEV)
    verts, normals = robot.world_vertices_and_normals(q)
    cam = ant_camera(q, size=16)
    for dt, tol in ((F64, 1e-12), (torch.float32, 1e-4)):
        st = _static(cam)
        v, n, c = (x.to(dt).clone().requires_grad_() for x in (verts, normals, robot.colors))
        r, e = cam.rotation.to(dt), cam.eye.to(dt).requires_grad_()
        ref, new = _both(v, n, c, r, e, robot.faces, st, 64, 16)
        _check_forward(ref, new, 16, tol=tol)
        w = torch.randn(ref[0].shape, dtype=dt, device=DEV, generator=torch.Generator(device=DEV).manual_seed(0))
        for gr, gn in zip(_grads(ref[0], (v, n, c, e), w), _grads(new[0], (v, n, c, e), w)):
            assert gr.abs().max() > 0
            assert (gr - gn).norm() <= 10 * tol * gr.norm()


def test_face_setup_gradcheck():
    """Central finite differences of face_setup itself (projected vertices, normals, per-env colours) on two
    kept faces that share an edge, one dropped (a corner behind znear) face and five padding faces."""
    g = torch.Generator().manual_seed(3)
    uvz = torch.tensor([[[2.0, 1.0, 2.0], [6.5, 1.5, 2.5], [3.0, 6.0, 3.0], [7.0, 6.5, 2.2], [1.0, 4.0, -0.5]]],
                       dtype=F64) + 0.1 * torch.rand(1, 5, 3, dtype=F64, generator=g)
    faces = torch.tensor([[0, 2, 1], [1, 2, 3], [0, 4, 2]], device=DEV)
    normals = torch.randn(1, 5, 3, dtype=F64, generator=g)
    colors = torch.rand(1, 5, 3, dtype=F64, generator=g)
    cam = ant_camera(ant_pose(1).to(DEV), size=8)
    st = _static(cam, cull_backfaces=False, znear=0.1)
    kept = face_validity(uvz.to(DEV)[:, faces], st)
    assert kept[0, :2].all() and not kept[0, 2]

    def fn(u, n, c):
        return fused.face_setup(u, n, c, faces, st, face_block=8, super_block=1)[0]

    torch.autograd.gradcheck(fn, tuple(x.to(DEV).requires_grad_() for x in (uvz, normals, colors)), eps=1e-6,
                             atol=1e-6, rtol=1e-5, fast_mode=True)


def test_face_setup_refuses_bad_options():
    verts, faces, cam, st, _ = _scene(True)
    uvz = project(verts, cam.rotation, cam.eye, st)
    n = vertex_normals(verts, faces)
    colors = torch.rand(verts.shape[1], 3, dtype=F64, device=DEV)
    with pytest.raises(ValueError, match="face_block"):
        fused.face_setup(uvz, n, colors, faces, st, face_block=6, super_block=2)
    with pytest.raises(ValueError, match="super_block"):
        fused.face_setup(uvz, n, colors, faces, st, face_block=8, super_block=0)
    with pytest.raises(ValueError, match="colors"):
        fused.face_setup(uvz, n, colors.expand(3, -1, -1), faces, st, face_block=8, super_block=2)


def _floor_cameras():
    """Three cameras: looking down at the floor, at the horizon from close above it (grazing rays, far hits
    past zfar, squares sharper than the cap nearby), and from below the floor looking down (no hit)."""
    eye = torch.tensor([[0.0, -3.0, 1.0], [0.4, -2.0, 0.15], [0.1, 0.2, -0.5]], dtype=F64)
    target = torch.tensor([[0.0, 0.0, 0.0], [0.3, 4.0, 0.1], [0.0, 0.5, -2.0]], dtype=F64)
    cam = dr.Camera.look_at(eye, target, (0.0, 0.0, 1.0), 70.0, 13, 17)
    return dr.Camera(rotation=cam.rotation.to(DEV), eye=cam.eye.to(DEV), focal=cam.focal, height=13, width=17)


def _floor_sharpness(cam: dr.Camera, st: Static) -> torch.Tensor:
    """(B, H, W) the checker's sharpness before its cap (floor_candidate's formula), where the ray hits."""
    py, px = torch.meshgrid(torch.arange(st.height, dtype=F64, device=DEV) + 0.5,
                            torch.arange(st.width, dtype=F64, device=DEV) + 0.5, indexing="ij")
    ray = torch.stack([(px - st.cx) / st.focal, (py - st.cy) / st.focal, torch.ones_like(px)], -1)  # camera
    dz = torch.einsum("bij,hwi->bhwj", cam.rotation, ray)[..., 2]
    t = -cam.eye[:, 2, None, None] / dz
    footprint = t / (st.focal * dz.abs())
    return st.floor.square_size / (math.pi * st.floor.edge_px * footprint)


@pytest.mark.parametrize("kw", [dict(), dict(gamma=1e-3, zfar=3.0, floor=dr.FloorSettings(square_size=0.2,
                                                                                           edge_px=0.02))])
def test_floor_planes_match_the_pytorch_floor(kw):
    """floor_planes against the PyTorch floor planes (floor_candidate at every pixel centre): depth, colour and
    hit flag, and the gradients of a random weighting of depth and colour into camera rotation and eye, with
    hits and misses, far hits at the depth floor, and capped sharpness all present."""
    cam = _floor_cameras()
    st = _static(cam, **kw)
    r_ref, e_ref, r_new, e_new = (x.clone().requires_grad_() for x in (cam.rotation, cam.eye) * 2)
    ref = reference.floor_planes(r_ref, e_ref, st, F64, DEV)
    new = floor_planes(r_new, e_new, st)
    hit = ref[:, 4] > 0.5
    assert hit.any() and (~hit).any() and not hit[2].any()
    if "zfar" in kw:
        assert (ref[:, 0][hit] == 20.0 * st.gamma).any()  # beyond zfar: at the depth floor
        sharp = _floor_sharpness(cam, st)[hit]
        assert (sharp > 50.0).any() and (sharp < 50.0).any()  # floor.py caps it at 50
    # 1e-12, not ~1e-15: at grazing rays the checker edge (sharpness capped at 50 per square of 0.2 m) turns the
    # rounding of a hit point metres away into ~100x larger colour differences, and the kernel's fused
    # multiply-adds round differently from PyTorch's separate ones (3e-14 seen on an H100); a wrong formula
    # would differ by orders more
    assert (new.detach() - ref.detach()).abs().max() <= 1e-12
    w = torch.randn(ref.shape, dtype=F64, device=DEV, generator=torch.Generator(device=DEV).manual_seed(1))
    w[:, 4] = 0.0
    g_ref = torch.autograd.grad((ref * w).sum(), (r_ref, e_ref))
    g_new = torch.autograd.grad((new * w).sum(), (r_new, e_new))
    for gr, gn in zip(g_ref, g_new):
        assert gr.abs().max() > 0
        # the same edges square that amplification in the gradient, which atomic adds sum in any order (8e-12 of
        # the largest entry seen on an H100)
        assert (gr - gn).abs().max() <= 1e-10 * gr.abs().max()


def test_floor_planes_gradcheck():
    cam = _floor_cameras()
    st = _static(cam, gamma=0.05, zfar=6.0)
    torch.autograd.gradcheck(lambda r, e: floor_planes(r, e, st)[:, :4],
                             (cam.rotation.clone().requires_grad_(), cam.eye.clone().requires_grad_()), eps=1e-7,
                             atol=1e-6, rtol=1e-5, fast_mode=True)


def test_floor_planes_at_rays_parallel_to_the_floor():
    """A level camera 13 px high: the middle row's rays run exactly parallel to the floor (dz = 0, where the
    ray's hit parameter would divide by zero). It never hits, its planes and their gradients are finite and
    equal the PyTorch floor's; the rows below hit, the rows above miss."""
    eye = torch.tensor([[0.0, -3.0, 1.0]], dtype=F64)
    cam = dr.Camera.look_at(eye, torch.tensor([[0.0, 0.0, 1.0]], dtype=F64), (0.0, 0.0, 1.0), 70.0, 13, 17)
    cam = dr.Camera(rotation=cam.rotation.to(DEV), eye=cam.eye.to(DEV), focal=cam.focal, height=13, width=17)
    st = _static(cam)
    assert st.cy == 6.5 and float(cam.rotation[0, 2, 2]) == 0.0 and float(cam.rotation[0, 0, 2]) == 0.0
    r_ref, e_ref, r_new, e_new = (x.clone().requires_grad_() for x in (cam.rotation, cam.eye) * 2)
    ref = reference.floor_planes(r_ref, e_ref, st, F64, DEV)
    new = floor_planes(r_new, e_new, st)
    hit = new[0, 4] > 0.5
    assert not hit[6].any() and hit[7:].all() and not hit[:6].any()
    assert torch.isfinite(new).all() and (new.detach() - ref.detach()).abs().max() <= 1e-12
    w = torch.randn(ref.shape, dtype=F64, device=DEV, generator=torch.Generator(device=DEV).manual_seed(2))
    w[:, 4] = 0.0
    g_ref = torch.autograd.grad((ref * w).sum(), (r_ref, e_ref))
    g_new = torch.autograd.grad((new * w).sum(), (r_new, e_new))
    for gr, gn in zip(g_ref, g_new):
        assert torch.isfinite(gn).all() and gr.abs().max() > 0
        assert (gr - gn).abs().max() <= 1e-10 * gr.abs().max()
