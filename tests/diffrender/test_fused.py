"""The fused Triton backend against the dense reference: forward and backward, float64.

Runs on CUDA where there is a GPU, else on the CPU through Triton's interpreter (slow: tiny scenes only).
Skipped where Triton is not installed (CPU-only PyTorch does not bring it; CI's CPU machine has none).
"""

import os

import pytest
import torch

if not torch.cuda.is_available():  # must be set before the kernels are defined (import of the module)
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")

import diffrender as dr
from diffrender.profiling import SavedTensorMeter
from diffrender.raster import fused
from diffrender.raster.fused import rasterize, tuning
from diffrender.raster.kernel import Static

from .helpers import F64, ant_camera, ant_pose, asset, degenerate_scene, tiny_camera, tiny_scene, tiny_settings

DEV = torch.device("cuda" if torch.cuda.is_available() else "cpu")
pytestmark = pytest.mark.skipif(not fused.available(DEV), reason="fused kernels cannot run here")


@pytest.fixture(scope="module")
def ant64():
    return dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0, device=DEV)


def _set(monkeypatch, **constants):
    """Set ``diffrender.raster.fused.tuning``'s constants for one test (restored after it)."""
    for name, value in constants.items():
        monkeypatch.setattr(tuning, name, value)


def _compare(verts, faces, colors, cam, kw, *, normals=None, tol=1e-10):
    """Render with dense and fused, backpropagate one random-weighted loss; compare image and the gradients
    w.r.t. vertices, colours, camera eye (and normals when given)."""
    out, grads = {}, {}
    for backend in ("dense", "fused"):
        v = verts.clone().requires_grad_()
        c = colors.clone().requires_grad_()
        e = cam.eye.clone().requires_grad_()
        n = None if normals is None else normals.clone().requires_grad_()
        camera = dr.Camera(rotation=cam.rotation, eye=e, focal=cam.focal, height=cam.height, width=cam.width)
        img = dr.render(v, faces, c, camera, dr.RasterSettings(backend=backend, **kw), normals=n)
        w = torch.linspace(-1, 1, img.numel(), dtype=img.dtype, device=img.device).view_as(img)
        (img * w).sum().backward()
        out[backend] = img.detach()
        grads[backend] = [x.grad for x in (v, c, e, n) if x is not None and x.shape[-2] > 0]
    assert (out["dense"] - out["fused"]).abs().max() < 1e3 * tol * max(1.0, float(out["dense"].abs().max()))
    for gd, gf in zip(grads["dense"], grads["fused"]):
        assert gd.abs().max() > 0
        assert (gd - gf).abs().max() <= tol * gd.abs().max()


@pytest.mark.parametrize("kw", [pytest.param(dict(), marks=pytest.mark.slow),
                                pytest.param(dict(cull_backfaces=False, floor=None, save_blend_state=True),
                                                     marks=pytest.mark.slow),
                                # the Triton interpreter takes ~45 s for this one: on CPUs with -m slow
                                pytest.param(dict(sigma=0.3, gamma=1e-3), marks=pytest.mark.slow),
                                pytest.param(dict(raster_model="alpha", cull_backfaces=False), marks=pytest.mark.slow),
                                pytest.param(dict(raster_model="alpha", floor=None, save_blend_state=True),
                                             marks=pytest.mark.slow),
                                pytest.param(dict(raster_model="hard"), marks=pytest.mark.slow),
                                dict(raster_model="hard", cull_backfaces=False, floor=None, save_blend_state=True)])
def test_fused_matches_dense_on_the_ant(ant64, kw):
    """Two ants at 10 x 10 px with the default blocks (944 faces: 15 of 64, one super-block): 9 forward tiles
    and 4 backward ones, each side's last tile partly outside the image."""
    q = ant_pose(2, seed=1).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    _compare(verts, ant64.faces, ant64.colors, ant_camera(q, size=10), kw)


@pytest.mark.parametrize("model", [pytest.param(m, marks=pytest.mark.slow) for m in ("hard", "softmax", "alpha")])
def test_fused_super_blocks_and_crowded_backward_tile_match_dense(ant64, monkeypatch, model):
    """Super-blocks of two 16-face blocks (the 944 faces make 30 of them, most far from most tiles, so the
    coarse test skips whole runs of blocks), the backward tile chosen for crowded faces and the backward's
    walk split between 4 programs per tile (7 or 8 super-blocks each), the forward's between 3 (10 each, then
    merged) and evaluating its blocks in halves: the image and gradients of the dense reference."""
    _set(monkeypatch, FWD_MAX_SPLITS=3, FWD_SPLIT_SUPER_BLOCKS=4, FWD_SUB_BLOCK=8, FACE_BLOCK=16, SUPER_BLOCK=2,
         DENSE_FACES_PER_PIXEL=0.0, BWD_TILE_DENSE=4, BWD_SUB_BLOCK=16, BWD_MAX_SPLITS=4, BWD_SPLIT_SUPER_BLOCKS=4)
    q = ant_pose(2, seed=6).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    cam = ant_camera(q, size=12)
    assert fused.backward_tile(ant64.num_faces, cam.height, cam.width) == tuning.BWD_TILE_DENSE
    assert fused.backward_splits(30) == 4 and fused.forward_splits(30) == 3
    _compare(verts, ant64.faces, ant64.colors, cam, dict(raster_model=model, save_blend_state=model != "hard"))


@pytest.mark.parametrize(("model", "splits", "sub_block"), [
    ("hard", 1, 16), pytest.param("hard", 3, 16, marks=pytest.mark.slow),
    pytest.param("hard", 3, 8, marks=pytest.mark.slow), pytest.param("softmax", 3, 8, marks=pytest.mark.slow)])
def test_exact_depth_ties_go_to_the_lowest_face_index(monkeypatch, model, splits, sub_block):
    """Five copies of one triangle (exactly equal depths, different colours) in super-blocks of 16 faces:
    face 20 (green) and face 28 (same block; the other half when blocks are evaluated 8 faces at a time) and
    face 68 in part 1 of a 3-part split forward, face 56 in part 0, face 40 in part 2. The hard model shows face
    20, as the dense reference does (the lowest index among exact ties: neither the first part nor the last,
    nor the last tie within a part, a walk or a block); unsplit (splits 1) the one walk meets all five. The
    soft models blend them all; images and gradients equal the reference."""
    _set(monkeypatch, FACE_BLOCK=16, SUPER_BLOCK=1, FWD_MAX_SPLITS=splits, FWD_SPLIT_SUPER_BLOCKS=1,
         FWD_SUB_BLOCK=sub_block)
    assert fused.forward_splits(6) == splits
    base, _, _ = tiny_scene(1)
    tri = base[0, :3]
    verts = tri[0].repeat(1, 96 * 3, 1)  # every other face has three equal corners: dropped
    colors = torch.full((96 * 3, 3), 0.5, dtype=F64)
    copies = {56: (0.9, 0.1, 0.1), 20: (0.1, 0.9, 0.1), 28: (0.9, 0.1, 0.9), 68: (0.5, 0.1, 0.9), 40: (0.1, 0.1, 0.9)}
    for face, rgb in copies.items():
        verts[0, 3 * face:3 * face + 3] = tri
        colors[3 * face:3 * face + 3] = torch.tensor(rgb, dtype=F64)
    faces = torch.arange(96 * 3).view(96, 3)
    eye, target, _ = tiny_camera(1)
    cam = dr.Camera.look_at(eye.to(DEV), target.to(DEV), (0.0, 0.0, 1.0), 40.0, 10, 10)
    kw = dict(sigma=0.5, gamma=0.05, znear=0.5, zfar=10.0, cull_backfaces=False, raster_model=model)
    _compare(verts.to(DEV), faces.to(DEV), colors.to(DEV), cam, kw)
    img = dr.render(verts.to(DEV), faces.to(DEV), colors.to(DEV), cam, dr.RasterSettings(backend="fused", **kw))
    if model == "hard":  # some pixels show the triangle, all of them in face 20's green
        r, g, b = img[0]
        assert (g > r + 0.2).any() and not ((r > g + 0.2) | (b > g + 0.2)).any()


def _two_ants_set_up(ant64, settings: dr.RasterSettings, *, seed: int) -> tuple[Static, tuple]:
    """Two ant images of 12 x 12 px as the forward kernel takes them (16-face blocks, super-blocks of 2): the
    static settings and the setup's (coefficients, face boxes, block boxes, super-block boxes, floor)."""
    q = ant_pose(2, seed=seed).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    cam = ant_camera(q, size=12)
    st = Static.make(settings, focal=cam.focal, height=cam.height, width=cam.width, tile_h=tuning.TILE,
                     tile_w=tuning.TILE)
    return st, rasterize._setup(verts, None, ant64.colors, cam.rotation, cam.eye, ant64.faces, st, 16, 2)


def _forward_of(st: Static, setup: tuple, *, save: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The forward kernels' image and blend state of :func:`_two_ants_set_up`'s images (NaN where unwritten);
    ``save=False``: the image alone, nothing saved, as renders without gradient run (the hard model's
    ``FWD_DEFER_SHADING`` walk applies only there), and None for the state."""
    out = torch.full((2, 3, 12, 12), float("nan"), dtype=F64, device=DEV)
    state = torch.full((2, rasterize.STATE_PER_PIXEL, 12, 12), float("nan"), dtype=F64, device=DEV) if save else None
    rasterize._launch_forward(*setup, st, tuning.TILE, 16, out, state)
    return out, state


def _assert_same_blend(model: str, reference: tuple, other: tuple) -> None:
    """Two (image, blend state) of :func:`_forward_of`: both finite; the hard model's state bit for bit (the same
    face at the same depth, a face chosen somewhere) and its image bit for bit under the interpreter, to a few
    units in the last place on a GPU (whose compiler contracts the shading's multiply-adds differently in two
    walks: 1-2 ulp on an H200); the soft models' to float64 rounding (with a face kept somewhere)."""
    (out_r, state_r), (out_o, state_o) = reference, other
    assert all(torch.isfinite(t).all() for t in (out_r, state_r, out_o, state_o))
    if model == "hard":
        assert torch.equal(state_o, state_r) and (state_r[:, 1] >= 0).any()
        _assert_same_shading(out_o, out_r)
    else:
        assert (state_r[:, 3] > 0).any()
        torch.testing.assert_close(state_o, state_r, rtol=1e-12, atol=1e-300)
        torch.testing.assert_close(out_o, out_r, rtol=1e-12, atol=1e-14)


def _assert_same_shading(image: torch.Tensor, reference: torch.Tensor) -> None:
    """The hard model's colours of the same faces from two walks: bit for bit under the interpreter (numpy, no
    contraction), else within 4 units in the last place of the dtype."""
    if DEV.type == "cpu":
        assert torch.equal(image, reference)
    else:
        torch.testing.assert_close(image, reference, rtol=4 * torch.finfo(image.dtype).eps, atol=1e-30)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["hard", "softmax", "alpha"])
def test_split_forward_keeps_the_unsplit_blend_state(ant64, monkeypatch, model):
    """The state the backward reads (maximum, denominator, weight and coverage sums; the hard model's chosen
    face) and the image, from one walk and from three merged parts: equal (the hard model's state exactly, its
    image to the last place on a GPU)."""
    _set(monkeypatch, FACE_BLOCK=16, SUPER_BLOCK=2, FWD_SPLIT_SUPER_BLOCKS=4)
    st, setup = _two_ants_set_up(ant64, dr.RasterSettings(backend="fused", raster_model=model), seed=3)
    results = []
    for splits in (1, 3):
        monkeypatch.setattr(tuning, "FWD_MAX_SPLITS", splits)
        assert fused.forward_splits(setup[3].shape[2]) == splits
        results.append(_forward_of(st, setup))
    _assert_same_blend(model, *results)


@pytest.mark.parametrize(("model", "walk", "split_counts", "sub_block"), [
    # FWD_COMPACT is off by default: its cases run with -m slow (and at task size on a GPU)
    pytest.param("hard", dict(FWD_COMPACT=True), (1, 3), 4, marks=pytest.mark.slow),
    pytest.param("hard", dict(FWD_COMPACT=True, FWD_DEFER_SHADING=True), (1, 3), 4, marks=pytest.mark.slow),
    # the default walk of images rendered with nothing saved, in whole-block chunks as the defaults walk
    # (FWD_SUB_BLOCK = FACE_BLOCK); split in three, the case with part boundaries (the default walk split and
    # unsplit agree: test_split_forward_keeps_the_unsplit_blend_state)
    pytest.param("hard", dict(FWD_DEFER_SHADING=True), (3,), 16, marks=pytest.mark.slow),
    pytest.param("hard", dict(FWD_DEFER_SHADING=True), (1,), 16, marks=pytest.mark.slow),
    # blocks walked in chunks of 4, several per block: a duplicate of the chunk loop the compacted cases cover
    pytest.param("hard", dict(FWD_DEFER_SHADING=True), (3,), 4, marks=pytest.mark.slow),
    pytest.param("softmax", dict(FWD_COMPACT=True), (1, 3), 4, marks=pytest.mark.slow),
    pytest.param("alpha", dict(FWD_COMPACT=True), (1, 3), 4, marks=pytest.mark.slow)])
def test_forward_walk_variants_keep_the_image_and_blend_state(ant64, monkeypatch, model, walk, split_counts,
                                                              sub_block):
    """The forward's walk variants against the block-wise walk that shades every pair, on 16-face blocks in
    chunks of ``sub_block`` (the ant's 944 faces; in chunks of 4, blocks that reach a tile with none, some and
    more than one chunk of faces whose boxes reach it), unsplit and split in three (``split_counts``):
    ``FWD_COMPACT`` (of each block near a tile, only the faces whose boxes reach it, packed into chunks) and the
    hard model's ``FWD_DEFER_SHADING`` (the chosen face alone shaded, in images rendered with nothing saved): the
    hard model's state bit for bit and image to the last place (bit for bit under the interpreter), the soft
    models' to float64 rounding (their sums are regrouped); with the state kept and without. Slow-only: the
    compacted walk (off by default), the unsplit deferred walk and the deferred walk in chunks smaller than a
    block (4x the interpreter's time for the chunk loop the compacted cases cover)."""
    _set(monkeypatch, FACE_BLOCK=16, SUPER_BLOCK=2, FWD_SPLIT_SUPER_BLOCKS=4, FWD_SUB_BLOCK=sub_block)
    settings = dr.RasterSettings(backend="fused", raster_model=model, cull_backfaces=model != "alpha")
    st, setup = _two_ants_set_up(ant64, settings, seed=5)
    for splits in split_counts:
        results, images = {}, {}
        for variant in (dict(FWD_COMPACT=False, FWD_DEFER_SHADING=False), walk):
            _set(monkeypatch, FWD_MAX_SPLITS=splits, **variant)
            results[variant is walk] = _forward_of(st, setup)
            images[variant is walk] = _forward_of(st, setup, save=False)[0]
        _assert_same_blend(model, results[False], results[True])
        assert torch.isfinite(images[True]).all()
        if model == "hard":
            _assert_same_shading(images[True], images[False])
        else:
            torch.testing.assert_close(images[True], images[False], rtol=1e-12, atol=1e-14)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["softmax", "hard"])
def test_compacted_forward_walk_matches_dense(ant64, monkeypatch, model):
    """Images and gradients of the compacted forward walk (the backward recomputes its blend state with it;
    the hard model's chosen face alone shaded) against the dense reference. Slow-only: ``FWD_COMPACT`` is off
    by default (45 s a case under the interpreter; at task size on a GPU in
    test_compacted_forward_walk_at_task_size_float32)."""
    _set(monkeypatch, FACE_BLOCK=16, SUPER_BLOCK=2, FWD_SUB_BLOCK=4, FWD_COMPACT=True, FWD_DEFER_SHADING=True)
    q = ant_pose(1, seed=1).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    _compare(verts, ant64.faces, ant64.colors, ant_camera(q, size=8), dict(raster_model=model))


@pytest.mark.slow
@pytest.mark.parametrize("model", ["softmax", "hard", "alpha"])
def test_compacted_backward_lanes_give_every_face_the_same_gradient(ant64, monkeypatch, model):
    """The backward with ``BWD_COMPACT`` (a program's lanes hold only the faces whose boxes reach its tile, in
    sub-blocks of 8 here, of 16-face blocks) against the block-wise lanes: the same gradients, bit for bit (each
    face sums the same pixels' terms in the same order), so the dense reference's as the block-wise ones are.
    The ant's first 480 faces (its torso and first legs: 30 blocks, 15 super-blocks, the backward's walk split
    between 7 programs) in a 6 x 6 image, one backward tile (partly outside the image) that 218 of them reach,
    1-16 of each block's 16: blocks of one and of two sub-blocks. The blend state kept, so the forward runs once a
    render (the backward's recompute of it is another test's: test_fused_matches_dense_on_the_ant)."""
    _set(monkeypatch, FACE_BLOCK=16, SUPER_BLOCK=2, BWD_SUB_BLOCK=8)
    q = ant_pose(1, seed=2).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    faces = ant64.faces[:480]
    cam = ant_camera(q, size=6)
    settings = dr.RasterSettings(backend="fused", raster_model=model, save_blend_state=True)
    assert fused.backward_splits(15) == 7
    grads = {}
    for compact in (False, True):
        _set(monkeypatch, BWD_COMPACT=compact)
        v = verts.clone().requires_grad_()
        img = dr.render(v, faces, ant64.colors, cam, settings)
        w = torch.linspace(-1, 1, img.numel(), dtype=img.dtype, device=img.device).view_as(img)
        (img * w).sum().backward()
        grads[compact] = v.grad
    assert grads[False].abs().max() > 0
    if DEV.type == "cpu":  # the interpreter runs the programs in order: the atomic adds too
        assert torch.equal(grads[True], grads[False])
    else:
        torch.testing.assert_close(grads[True], grads[False], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("model", [pytest.param("softmax", marks=pytest.mark.slow), "hard"])
def test_small_faces_whose_boxes_end_inside_tiles_match_dense(model):
    """Six triangles of ~2 px, apart, at different sub-pixel offsets in a 32 x 32 image: the backward walks
    only the pixels inside each sub-block's face boxes, which here end inside the 8 x 8 tiles on every side;
    images and gradients equal the dense reference."""
    g = torch.Generator().manual_seed(4)
    centres = torch.tensor([[-0.55, 0.0, 0.45], [-0.2, 0.1, 0.7], [0.15, -0.1, 0.95], [0.5, 0.05, 0.6],
                            [0.0, 0.2, 1.25], [0.33, -0.05, 0.3]], dtype=F64)
    corners = torch.tensor([[-0.05, 0.0, -0.04], [0.05, 0.0, -0.03], [0.0, 0.0, 0.05]], dtype=F64)
    verts = (centres[:, None] + corners[None] * (0.7 + 0.6 * torch.rand(6, 1, 1, generator=g, dtype=F64)))
    verts = verts.reshape(1, 18, 3)
    faces = torch.arange(18).view(6, 3)
    colors = 0.1 + 0.8 * torch.rand(18, 3, generator=g, dtype=F64)
    eye, target, _ = tiny_camera(1)
    cam = dr.Camera.look_at(eye.to(DEV), target.to(DEV), (0.0, 0.0, 1.0), 40.0, 32, 32)
    _compare(verts.to(DEV), faces.to(DEV), colors.to(DEV), cam,
             dict(sigma=0.3, gamma=0.05, znear=0.5, zfar=10.0, cull_backfaces=False, raster_model=model))


def test_super_block_boxes_are_unions_of_their_blocks(monkeypatch):
    """Each super-box is the union of its blocks' boxes; padding blocks are empty and touch no pixel."""
    g = torch.Generator().manual_seed(0)
    lo = torch.rand(2, 2, 7, generator=g) * 50
    block = torch.stack([lo[:, 0], lo[:, 0] + 3, lo[:, 1], lo[:, 1] + 5], dim=1)  # (2, 4, 7)
    padded, sup = fused.super_block_boxes(block, 4)
    assert padded.shape == (2, 4, 8) and sup.shape == (2, 4, 2)
    assert torch.equal(padded[:, :, :7], block)
    assert (padded[:, 0, 7] > padded[:, 1, 7]).all() and (padded[:, 2, 7] > padded[:, 3, 7]).all()
    for k, (a, b) in enumerate(((0, 4), (4, 7))):
        for row, reduce in enumerate((torch.amin, torch.amax, torch.amin, torch.amax)):
            assert torch.equal(sup[:, row, k], reduce(block[:, row, a:b], -1))
    monkeypatch.setattr(tuning, "BWD_TILE_DENSE", tuning.BWD_TILE // 2)  # the defaults are equal: tell them apart
    assert fused.backward_tile(100_000, 84, 84) == tuning.BWD_TILE_DENSE
    assert fused.backward_tile(1856, 84, 84) == tuning.BWD_TILE
    # one program per tile for the ant (2 super-blocks), the most for 100k faces (99)
    assert fused.backward_splits(2) == 1 and fused.backward_splits(99) == tuning.BWD_MAX_SPLITS > 1
    assert fused.backward_splits(0) == 1
    assert fused.forward_splits(2) == 1 and fused.forward_splits(99) == tuning.FWD_MAX_SPLITS > 1
    assert fused.forward_splits(0) == 1


@pytest.mark.parametrize(("bwd_tile", "sub_block"), [pytest.param(8, 64, marks=pytest.mark.slow),
                                                     pytest.param(4, 16, marks=pytest.mark.slow)])
def test_fused_float32_hidden_faces_match_dense(ant64, monkeypatch, bwd_tile, sub_block):
    """float32 with back faces kept: the depth softmax weight of hidden faces underflows to exactly 0, which
    the backward uses to skip them (no atomics, pixels skipped); the gradients must still equal dense's, with
    the backward packing the faces that reach a tile into lanes of 64 or 16, over tiles of either size."""
    monkeypatch.setattr(tuning, "BWD_TILE", bwd_tile)
    monkeypatch.setattr(tuning, "BWD_SUB_BLOCK", sub_block)
    q = ant_pose(2, seed=3).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    cam = ant_camera(q, size=16)
    cam32 = dr.Camera(rotation=cam.rotation.float(), eye=cam.eye.float(), focal=cam.focal, height=cam.height,
                      width=cam.width)
    _compare(verts.float(), ant64.faces, ant64.colors.float(), cam32,
             dict(cull_backfaces=False, save_blend_state=bwd_tile == 8), tol=2e-3)


@pytest.mark.slow
def test_fused_matches_dense_with_given_normals_and_per_env_colors(ant64):
    q = ant_pose(2, seed=5).to(DEV)
    verts, normals = ant64.world_vertices_and_normals(q)
    colors = torch.rand(2, ant64.num_vertices, 3, dtype=F64, device=DEV)
    _compare(verts, ant64.faces, colors, ant_camera(q, size=12), dict(), normals=normals)


@pytest.mark.parametrize("model", ["softmax", pytest.param("alpha", marks=pytest.mark.slow),
                                   pytest.param("hard", marks=pytest.mark.slow)])
def test_fused_gradcheck_tiny_scene(monkeypatch, model):
    """torch.autograd.gradcheck in float64 of the image in the vertices, colours and camera eye. Super-blocks of
    one block: the default 16 would give the setup kernel 15 padding blocks to write per render (15/16 of its
    interpreter time here; the padding's empty boxes are test_fused_matches_dense_on_the_ant's and the setup
    tests'). 5 x 4 px: two forward tiles, the second one row deep; one backward tile, partly outside."""
    monkeypatch.setattr(tuning, "SUPER_BLOCK", 1)
    verts, faces, colors = (x.to(DEV) for x in tiny_scene())
    eye, target, _ = (x.to(DEV) if isinstance(x, torch.Tensor) else x for x in tiny_camera())
    s = tiny_settings(backend="fused", cull_backfaces=False, raster_model=model)

    def fn(v, c, e):
        cam = dr.Camera.look_at(e, target, (0.0, 0.0, 1.0), 40.0, 5, 4)
        return dr.render(v, faces, c, cam, s)

    torch.autograd.gradcheck(fn, (verts.clone().requires_grad_(), colors.clone().requires_grad_(),
                                  eye.clone().requires_grad_()), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


def test_fused_floor_only_scene_matches_dense():
    eye, target, _ = tiny_camera()
    cam = dr.Camera.look_at(eye.to(DEV), target.to(DEV), (0.0, 0.0, 1.0), 40.0, 7, 6)
    faces = torch.zeros(0, 3, dtype=torch.long, device=DEV)
    verts = torch.zeros(2, 0, 3, dtype=F64, device=DEV)
    _compare(verts, faces, torch.zeros(0, 3, dtype=F64, device=DEV), cam, dict(sigma=1.0, gamma=0.05))


@pytest.mark.parametrize("cull", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_fused_degenerate_faces_match_dense(cull):
    """Zero-area, collinear, edge-on, behind-camera, znear-straddling faces and a vertex at the eye: finite,
    equal to the dense reference, and the dropped faces get no gradient."""
    verts, faces, colors, cam = degenerate_scene()
    # the scene's view at 8 x 8 px (half its focal length): one backward tile, four forward ones
    cam = dr.Camera(rotation=cam.rotation.to(DEV), eye=cam.eye.to(DEV), focal=cam.focal / 2, height=8, width=8)
    verts, faces, colors = verts.to(DEV), faces.to(DEV), colors.to(DEV)
    kw = dict(cull_backfaces=cull, sigma=0.7, gamma=1e-3, znear=0.1, zfar=8.0)
    _compare(verts, faces, colors, cam, kw)
    v = verts.clone().requires_grad_()
    img = dr.render(v, faces, colors, cam, dr.RasterSettings(backend="fused", **kw))
    img.sum().backward()
    assert torch.isfinite(img).all() and torch.isfinite(v.grad).all()
    assert v.grad[0, :3].abs().sum() > 0 and v.grad[0, 12:18].abs().sum() == 0


@pytest.mark.parametrize("model", ["hard", pytest.param("softmax", marks=pytest.mark.slow),
                                   pytest.param("alpha", marks=pytest.mark.slow)])
def test_images_without_gradient_equal_the_differentiable_ones(ant64, model):
    """What decoupled rollouts, evaluation and videos render (no_grad: the forward kernel saves nothing) is the
    image the differentiable path renders, with the blend state kept for the backward or recomputed by it: bit
    for bit under the interpreter, to float64 rounding on a GPU (other kernel specialisations). One ant: the
    images of a batch without the state are test_fused_matches_dense_on_the_ant's (the default keeps none)."""
    q = ant_pose(1, seed=6).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    cam = ant_camera(q, size=8)
    with torch.no_grad():
        plain = dr.render(verts, ant64.faces, ant64.colors, cam, dr.RasterSettings(backend="fused", raster_model=model))
    assert plain.abs().sum() > 0
    for keep_state in (True, False):
        v = verts.clone().requires_grad_()
        img = dr.render(v, ant64.faces, ant64.colors, cam,
                        dr.RasterSettings(backend="fused", raster_model=model, save_blend_state=keep_state))
        assert img.requires_grad
        if DEV.type == "cpu":
            assert torch.equal(img.detach(), plain)
        else:
            torch.testing.assert_close(img.detach(), plain, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("keep_state", [pytest.param(False, marks=pytest.mark.slow),
                                        pytest.param(True, marks=pytest.mark.slow)])
def test_fused_saved_memory_is_flat_in_faces(ant64, keep_state):
    """Saved for backward: the inputs (and with save_blend_state 7 numbers per pixel: image, blend maximum,
    denominator, the faces' weight and coverage sums), the same bytes for 3x the faces."""
    q = ant_pose(2, seed=0).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    cam = ant_camera(q, size=8)
    more = torch.cat([ant64.faces] + [ant64.faces.roll(k, 0) for k in range(1, 3)])  # 3x the faces
    saved = []
    for faces in (ant64.faces, more):
        v = verts.clone().requires_grad_()
        with SavedTensorMeter(exclude=[faces]) as meter:
            img = dr.render(v, faces, ant64.colors, cam,
                            dr.RasterSettings(backend="fused", save_blend_state=keep_state))
        img.sum().backward()
        assert torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0
        saved.append(meter.bytes)
    assert saved[0] == saved[1]
    per_pixel = (3 + rasterize.STATE_PER_PIXEL) * 2 * cam.height * cam.width * verts.element_size()
    inputs = sum(x.numel() * x.element_size() for x in (verts, ant64.colors, cam.rotation, cam.eye))
    assert saved[0] <= inputs + per_pixel * keep_state
    assert saved[0] > per_pixel * keep_state


@pytest.mark.parametrize("shared_colors", [pytest.param(True, marks=pytest.mark.slow),
                                           pytest.param(False, marks=pytest.mark.slow)])
def test_fused_chunks_over_environments_change_nothing(ant64, monkeypatch, shared_colors):
    """Rendering 3 environments 2 at a time (a ragged last chunk) gives the image and gradients of one pass."""
    q = ant_pose(3, seed=2).to(DEV)
    verts, normals = ant64.world_vertices_and_normals(q)
    colors = ant64.colors if shared_colors else torch.rand(3, ant64.num_vertices, 3, dtype=F64, device=DEV)
    cam = ant_camera(q, size=8)
    res = []
    for elems in (tuning.COEF_ELEMS, 2 * fused.NUM_COEFFS * 960):  # 944 faces -> 960 padded (64-face blocks)
        monkeypatch.setattr(tuning, "COEF_ELEMS", elems)
        v, n, c, e = (x.clone().requires_grad_() for x in (verts, normals, colors, cam.eye))
        camera = dr.Camera(rotation=cam.rotation, eye=e, focal=cam.focal, height=cam.height, width=cam.width)
        img = fused.rasterize_fused(v, n, c, camera, ant64.faces, dr.RasterSettings(), face_block=64)
        (img * torch.linspace(-1, 1, img.numel(), dtype=F64, device=DEV).view_as(img)).sum().backward()
        res.append((img.detach(), v.grad, n.grad, c.grad, e.grad))
    for a, b in zip(*res):
        assert a.abs().max() > 0 and (a - b).abs().max() <= 1e-12 * a.abs().max()


@pytest.mark.slow
def test_fused_compiled_setup_matches_eager(ant64):
    """settings.compile runs the per-face setup (coefficients, floor planes) through torch.compile, in
    forward and in the backward's recompute: the same image and gradients (float64)."""
    q = ant_pose(2, seed=4).to(DEV)
    verts, normals = ant64.world_vertices_and_normals(q)
    cam = ant_camera(q, size=12)
    res = []
    for comp in (False, True):
        v, n, e = (x.clone().requires_grad_() for x in (verts, normals, cam.eye))
        camera = dr.Camera(rotation=cam.rotation, eye=e, focal=cam.focal, height=cam.height, width=cam.width)
        img = dr.render(v, ant64.faces, ant64.colors, camera, dr.RasterSettings(backend="fused", compile=comp),
                        normals=n)
        (img * torch.linspace(-1, 1, img.numel(), dtype=F64, device=DEV).view_as(img)).sum().backward()
        res.append((img.detach(), v.grad, n.grad, e.grad))
    for a, b in zip(*res):
        # float64, but inductor's kernels contract and reorder the setup's arithmetic: 2.6e-9 relative on an H100
        assert a.abs().max() > 0 and (a - b).abs().max() <= 1e-8 * a.abs().max()


def test_fused_backward_skips_an_undefined_gradient(ant64, monkeypatch):
    """A gradient that never reaches the image (like gradlab's closed ImageGate, which returns None) costs no
    recompute."""

    class Cut(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.view_as(x)

        @staticmethod
        def backward(ctx, grad):
            return None

    calls = []
    setup = rasterize.face_setup
    monkeypatch.setattr(rasterize, "face_setup", lambda *a, **k: (calls.append(1), setup(*a, **k))[1])
    q = ant_pose(1).to(DEV)
    verts = ant64.world_vertices(q).detach().requires_grad_()
    img = dr.render(verts, ant64.faces, ant64.colors, ant_camera(q, size=8), dr.RasterSettings(backend="fused"))
    (Cut.apply(img).sum() + verts.sum()).backward()
    assert len(calls) == 1 and torch.equal(verts.grad, torch.ones_like(verts))


def test_fused_refuses_what_it_does_not_implement(ant64):
    q = ant_pose(1).to(DEV)
    verts, _ = ant64.world_vertices_and_normals(q)
    with pytest.raises(ValueError, match="power of two"):
        fused.rasterize_fused(verts, None, ant64.colors, ant_camera(q, size=8), ant64.faces, dr.RasterSettings(),
                              tile=6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only: the task-size point")
@pytest.mark.parametrize("model", ["softmax", "alpha", "hard"])
def test_fused_matches_tiled_at_task_size_float32(model):
    """64 ants at 84 x 84 in float32 (what training renders): fused and tiled agree to float32 rounding."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), detail=1, device=DEV)
    q = ant_pose(64, dtype=torch.float32, seed=3).to(DEV)
    res = {}
    for backend in ("tiled", "fused"):
        qq = q.clone().requires_grad_()
        v, n = robot.world_vertices_and_normals(qq)
        img = dr.render(v, robot.faces, robot.colors, ant_camera(qq, size=84),
                        dr.RasterSettings(backend=backend, raster_model=model), normals=n)
        w = torch.rand(img.shape, generator=torch.Generator(device=DEV).manual_seed(0), device=DEV)
        (img * w).sum().backward()
        res[backend] = (img.detach(), qq.grad)
    diff = (res["tiled"][0] - res["fused"][0]).abs().amax(1)
    if model == "hard":  # a pixel centre within rounding of a silhouette edge may see another surface
        assert (diff > 1e-4).double().mean() < 1e-4
    else:
        assert diff.max() < 1e-4
    g_t, g_f = res["tiled"][1], res["fused"][1]
    assert torch.isfinite(g_f).all()
    assert (g_t - g_f).norm() <= 1e-3 * g_t.norm()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only: the task-size point")
@pytest.mark.parametrize("model", ["softmax", "alpha", "hard"])
@pytest.mark.parametrize("sub_block", [8, 16])
def test_compacted_forward_walk_at_task_size_float32(monkeypatch, model, sub_block):
    """64 ants at 84 x 84 in float32, forward without gradient (what decoupled rollouts and evaluation render):
    the compacted walk's images (the hard model's chosen face alone shaded) equal the block-wise walk's that
    shades every pair, the hard model's to a few units in the last place."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), detail=1, device=DEV)
    q = ant_pose(64, dtype=torch.float32, seed=3).to(DEV)
    v, n = robot.world_vertices_and_normals(q)
    settings = dr.RasterSettings(backend="fused", raster_model=model, cull_backfaces=model != "alpha")
    imgs = {}
    for compact in (False, True):
        _set(monkeypatch, FWD_COMPACT=compact, FWD_DEFER_SHADING=compact,
             FWD_SUB_BLOCK=sub_block if compact else tuning.FWD_SUB_BLOCK)
        with torch.no_grad():
            imgs[compact] = dr.render(v, robot.faces, robot.colors, ant_camera(q, size=84), settings, normals=n)
    if model == "hard":
        _assert_same_shading(imgs[True], imgs[False])
    else:
        assert (imgs[True] - imgs[False]).abs().max() < 1e-5


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only: the task-size point")
@pytest.mark.parametrize("model", ["softmax", "alpha", "hard"])
def test_compacted_backward_lanes_at_task_size_float32(monkeypatch, model):
    """64 ants at 84 x 84 in float32: the gradient into the joint angles with the backward's compacted lanes
    (sub-blocks of 32, the default) equals the block-wise one's (sub-blocks of 64) up to the order of the
    atomic adds."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), detail=1, device=DEV)
    q0 = ant_pose(64, dtype=torch.float32, seed=4).to(DEV)
    settings = dr.RasterSettings(backend="fused", raster_model=model, cull_backfaces=model != "alpha")
    grads = {}
    for compact in (False, True):
        _set(monkeypatch, BWD_COMPACT=compact, BWD_SUB_BLOCK=32 if compact else 64)
        q = q0.clone().requires_grad_()
        v, n = robot.world_vertices_and_normals(q)
        img = dr.render(v, robot.faces, robot.colors, ant_camera(q, size=84), settings, normals=n)
        w = torch.rand(img.shape, generator=torch.Generator(device=DEV).manual_seed(0), device=DEV)
        (img * w).sum().backward()
        grads[compact] = q.grad
    assert torch.isfinite(grads[True]).all() and grads[False].norm() > 0
    assert (grads[True] - grads[False]).norm() <= 1e-4 * grads[False].norm()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only")
def test_auto_backend_is_fused_on_cuda_for_every_model():
    for model in ("hard", "softmax", "alpha"):
        assert dr.backend_for(dr.RasterSettings(raster_model=model), DEV) == "fused"
    assert dr.backend_for(dr.RasterSettings(), torch.device("cpu")) == "tiled"
