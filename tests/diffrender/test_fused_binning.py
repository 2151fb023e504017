"""The fused backend's per-tile face lists (``tuning.FWD_BIN``): the lists against an oracle from the setup's
face boxes, and every forward walk reading them (each model, with and without gradient, crowded tiles and
lists that overflow their capacity) against the dense reference and the unbinned walk, float64.

Runs on CUDA where there is a GPU, else on the CPU through Triton's interpreter (tiny scenes only).
"""

import os
import warnings

import pytest
import torch

if not torch.cuda.is_available():  # must be set before the kernels are defined (import of the module)
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")

import diffrender as dr
from diffrender.raster import fused
from diffrender.raster.fused import rasterize, tuning
from diffrender.raster.kernel import Static

from .helpers import F64, tiny_camera, tiny_scene
from .test_fused import _assert_same_shading, _compare

DEV = torch.device("cuda" if torch.cuda.is_available() else "cpu")
pytestmark = pytest.mark.skipif(not fused.available(DEV), reason="fused kernels cannot run here")

SIZE = 8  # image side [px]: 2 x 2 forward tiles of 4 x 4
TIES = (5, 7, 10)  # faces that are exact copies of one small triangle, in different colours
KW = dict(sigma=0.5, gamma=0.05, znear=0.5, zfar=10.0, cull_backfaces=False, floor=None)  # no floor: it would hide half


def _crowd():
    """Two environments of 12 faces crowding an 8 x 8 image: the three overlapping triangles of
    :func:`tiny_scene`, six small ones around the image centre and three exact copies of one more small one (faces
    5, 7, 10: equal depths, different colours, in front). Every tile lists 7-12 faces. Returns verts (2, 36, 3), faces
    (12, 3), colours (36, 3), camera."""
    g = torch.Generator().manual_seed(7)
    big, _, big_colors = tiny_scene(2)
    small = torch.tensor([[-0.25, 0.0, -0.16], [0.25, 0.0, -0.12], [0.0, 0.0, 0.24]], dtype=F64)
    centre = torch.tensor([0.0, -0.3, 0.75], dtype=F64)
    offsets = 0.25 * (torch.rand(7, 1, 3, generator=g, dtype=F64) - 0.5)
    offsets[:, :, 1] = 0.0
    smalls = centre + offsets + small  # (7, 3, 3)
    smalls[6] = centre + torch.tensor([0.1, -0.3, 0.0], dtype=F64) + 1.6 * small  # the tie copies: in front
    tris = [big[0, 0:3], big[0, 3:6], big[0, 6:9]]
    order = []  # 12 faces: 0-2 big, TIES copies of small 6, the rest smalls 0-5
    it = iter(range(6))
    for f in range(3, 12):
        order.append(6 if f in TIES else next(it))
    tris += [smalls[i] for i in order]
    verts = torch.stack(tris).reshape(1, 36, 3).repeat(2, 1, 1)
    verts[1] = verts[1] + 0.03 * torch.randn(36, 3, generator=g, dtype=F64)
    for f in TIES:  # the copies stay exact copies in both environments
        verts[:, 3 * f:3 * f + 3] = verts[:, 3 * TIES[0]:3 * TIES[0] + 3]
    colors = 0.1 + 0.8 * torch.rand(36, 3, generator=g, dtype=F64)
    colors[:9] = big_colors
    eye, target, _ = tiny_camera(2)
    cam = dr.Camera.look_at(eye.to(DEV), target.to(DEV), (0.0, 0.0, 1.0), 40.0, SIZE, SIZE)
    return verts.to(DEV), torch.arange(36).view(12, 3).to(DEV), colors.to(DEV), cam


def _small_blocks(monkeypatch, **constants):
    """4-face blocks, one per super-block, walked 4 faces at a time (three blocks, three super-blocks), and the
    given constants; restored after the test."""
    for name, value in dict(FACE_BLOCK=4, SUPER_BLOCK=1, FWD_SUB_BLOCK=4, **constants).items():
        monkeypatch.setattr(tuning, name, value)


def _set_up(model: str):
    verts, faces, colors, cam = _crowd()
    settings = dr.RasterSettings(backend="fused", raster_model=model, **KW)
    st = Static.make(settings, focal=cam.focal, height=SIZE, width=SIZE, tile_h=tuning.TILE, tile_w=tuning.TILE)
    return st, rasterize._setup(verts, None, colors, cam.rotation, cam.eye, faces, st, tuning.FACE_BLOCK,
                                tuning.SUPER_BLOCK)


def _oracle(box: torch.Tensor, tile: int) -> list[list[list[int]]]:
    """Per environment and tile (row-major), the faces whose box (B, 4, Fp) reaches a pixel centre of the tile,
    in face order."""
    tiles = -(-SIZE // tile)
    out = []
    for env_box in box.cpu():
        x0, x1, y0, y1 = env_box
        per_tile = []
        for ty in range(tiles):
            for tx in range(tiles):
                xl, xh = tx * tile + 0.5, min(tx * tile + tile, SIZE) - 0.5
                yl, yh = ty * tile + 0.5, min(ty * tile + tile, SIZE) - 0.5
                hit = (x1 >= xl) & (x0 <= xh) & (y1 >= yl) & (y0 <= yh)
                per_tile.append(torch.nonzero(hit).flatten().tolist())
        out.append(per_tile)
    return out


@pytest.mark.parametrize("cap", [16, 5])
def test_bins_list_every_face_whose_box_reaches_the_tile_in_face_order(monkeypatch, cap):
    """The binning kernel's lists and counts against the faces whose setup boxes reach each tile (in face order,
    the padding faces never), the count past the capacity where a tile overflows, and the device counter adding
    one per overflowing (tile, environment)."""
    _small_blocks(monkeypatch)
    st, (_, box, bbox, sbox, _) = _set_up("softmax")
    counter = torch.zeros(1, dtype=torch.int32, device=DEV)
    bins, cnt = rasterize._bin(box, bbox, sbox, st, tuning.TILE, tuning.FACE_BLOCK, cap, counter)
    expected = _oracle(box, tuning.TILE)
    assert bins.shape == (2, 4, cap) and cnt.shape == (2, 4)
    over = 0
    for env in range(2):
        for t, faces in enumerate(expected[env]):
            assert cnt[env, t].item() == len(faces)
            n = min(len(faces), cap)
            assert bins[env, t, :n].tolist() == faces[:n]
            over += len(faces) > cap
    assert max(len(f) for per in expected for f in per) >= 6  # crowded tiles
    assert (over > 0) == (cap == 5) and counter.item() == over
    verts, faces, colors, cam = _crowd()
    busiest = max(len(f) for per in expected for f in per)
    settings = dr.RasterSettings(backend="fused", **KW)
    assert fused.bin_capacity_needed(verts, None, colors, cam, faces, settings) == busiest


def _forward(st, setup, save: bool):
    out = torch.full((2, 3, SIZE, SIZE), float("nan"), dtype=F64, device=DEV)
    state = torch.full((2, rasterize.STATE_PER_PIXEL, SIZE, SIZE), float("nan"), dtype=F64, device=DEV) if save \
        else None
    rasterize._launch_forward(*setup, st, tuning.TILE, tuning.FACE_BLOCK, out, state)
    return out, state


# the Triton interpreter takes 15-25 s (CPU) for each of these: on CPUs with -m slow
@pytest.mark.slow
@pytest.mark.parametrize("model", ["hard", "softmax", "alpha"])
@pytest.mark.parametrize("splits", [1, 2])
def test_binned_forward_keeps_the_unbinned_image_and_blend_state(monkeypatch, model, splits):
    """Binned (lists of 16: none overflows; of 3: most tiles overflow and walk the blocks) against the unbinned
    walk, unsplit and split in two, with the blend state kept and without: the hard model's face, depth and
    image bit for bit (its lowest-index tie rule among faces 5, 7, 10; images without state against the
    ``FWD_DEFER_SHADING`` walk's), the soft models' to float64 rounding."""
    _small_blocks(monkeypatch, FWD_MAX_SPLITS=splits, FWD_SPLIT_SUPER_BLOCKS=1, FWD_DEFER_SHADING=True)
    st, setup = _set_up(model)
    assert fused.forward_splits(setup[3].shape[2]) == splits
    ref = {save: _forward(st, setup, save) for save in (True, False)}
    monkeypatch.setattr(tuning, "FWD_BIN", True)
    monkeypatch.setattr(rasterize, "_overflow_warned", False)
    fused.bin_overflows()
    for cap in (16, 3):
        monkeypatch.setattr(tuning, "BIN_CAPACITY", cap)
        for save in (True, False):
            out, state = _forward(st, setup, save)
            assert torch.isfinite(out).all()
            if model == "hard":
                _assert_same_shading(out, ref[save][0])
                if save:
                    assert torch.equal(state, ref[save][1])
                    assert torch.isin(state[:, 1], torch.tensor(TIES[1:], dtype=F64, device=DEV)).sum() == 0
                    assert (state[:, 1] == TIES[0]).any()
            else:
                torch.testing.assert_close(out, ref[save][0], rtol=1e-12, atol=1e-14)
                if save:
                    torch.testing.assert_close(state, ref[save][1], rtol=1e-12, atol=1e-300)
    with pytest.warns(fused.BinOverflowWarning):
        assert fused.bin_overflows() > 0


@pytest.mark.slow
@pytest.mark.parametrize("model", ["hard", "softmax", "alpha"])
@pytest.mark.parametrize("cap", [16, 2])
def test_binned_renders_match_dense(monkeypatch, model, cap):
    """Images and gradients (vertices, colours, camera eye) of binned renders against the dense reference, with
    lists that hold every tile's faces (16) and lists that overflow (2: the walks fall back on the blocks),
    the backward recomputing the blend state through the lists; the overflow counted, read once."""
    _small_blocks(monkeypatch, FWD_BIN=True, BIN_CAPACITY=cap)
    fused.bin_overflows()  # earlier renders' overflows
    verts, faces, colors, cam = _crowd()
    _compare(verts, faces, colors, cam, dict(raster_model=model, **KW))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fused.BinOverflowWarning)
        assert (fused.bin_overflows() > 0) == (cap == 2)


@pytest.mark.slow
def test_an_overflow_warns_once_and_the_counter_reads_outside_a_graph(monkeypatch):
    """A forced overflow gives one BinOverflowWarning for the process, however often it recurs; the counter
    resets at each read and counts each overflowing (tile, environment) of each binned launch."""
    _small_blocks(monkeypatch, FWD_BIN=True, BIN_CAPACITY=2)
    monkeypatch.setattr(rasterize, "_overflow_warned", False)
    fused.bin_overflows()
    verts, faces, colors, cam = _crowd()
    settings = dr.RasterSettings(backend="fused", raster_model="hard", **KW)
    with torch.no_grad():
        dr.render(verts, faces, colors, cam, settings)
    box = _set_up("hard")[1][1]
    expected = sum(len(f) > 2 for per in _oracle(box, tuning.TILE) for f in per)
    with pytest.warns(fused.BinOverflowWarning, match="BIN_CAPACITY = 2"):
        assert fused.bin_overflows() == expected > 0
    with torch.no_grad():
        dr.render(verts, faces, colors, cam, settings)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fused.bin_overflows() == expected
        assert fused.bin_overflows() == 0
    with torch.no_grad():  # the package's door reads the same counters (what the trainer calls each iteration)
        dr.render(verts, faces, colors, cam, settings)
    assert dr.bin_overflows() == expected and dr.bin_overflows() == 0


def test_bin_capacity_must_be_a_positive_integer(monkeypatch):
    _small_blocks(monkeypatch, FWD_BIN=True, BIN_CAPACITY=0)
    verts, faces, colors, cam = _crowd()
    with pytest.raises(ValueError, match="BIN_CAPACITY"):
        dr.render(verts, faces, colors, cam, dr.RasterSettings(backend="fused", **KW))
