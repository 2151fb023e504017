"""The fused rasterizer's autograd Function and its launches. :func:`rasterize_fused` renders through
``_FusedRasterize``, which per chunk of environments runs the setup (:func:`..setup_kernels.face_setup`,
:func:`..setup_kernels.floor_planes`) and the forward kernels (:mod:`.forward`), and in its backward the
backward kernels (:mod:`.backward`) and autograd through the setup. The launch heuristics (tile sides,
splits, warps, register caps) read :mod:`.tuning` at every launch.
"""

from __future__ import annotations

import functools
import os
import warnings

import torch

from ...camera import Camera
from ...settings import RasterSettings
from ..common import chunks, rows
from ..kernel import Static, project, vertex_normals
from ..setup_kernels import NUM_COEFFS, face_setup, floor_planes
from . import tuning

try:  # Triton ships with CUDA builds of PyTorch; CPU-only installs usually lack it
    import triton
except ImportError:  # pragma: no cover - exercised on machines without triton
    triton = None
else:
    from .backward import _fused_backward, _pixel_backward
    from .forward import _bin_faces, _binned_forward, _fused_forward, _merge_forward

#: numbers per pixel the forward keeps for the backward besides the image (see ``_fused_forward``)
STATE_PER_PIXEL = 4
#: numbers per pixel of one part of a split forward (see ``_fused_forward``), and of the backward's per-pixel
#: part (see ``_pixel_backward``)
PART_PER_PIXEL = 6
PIX_PER_PIXEL = 8
_MODEL_CODE = {"hard": 0, "softmax": 1, "alpha": 2}  # the kernels' MODEL constant


def interpreting() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def available(device: torch.device) -> bool:
    """Whether the fused kernels can run on ``device`` (CUDA with Triton, or Triton's CPU interpreter)."""
    if triton is None:
        return False
    return device.type == "cuda" or (device.type == "cpu" and interpreting())


@functools.cache
def _params(st: Static, dtype, device) -> torch.Tensor:
    """The kernels' float constants as a tensor of the images' dtype (Python floats would reach a Triton
    kernel as float32, which would cost float64 tests their precision). Cached: made once, outside any CUDA
    graph capture, and only read afterwards."""
    cap = max(0.02, 100.0 * torch.finfo(dtype).eps / st.gamma)
    vals = [st.sigma, st.gamma, st.znear, st.zfar, st.cutoff_radius, cap, st.ambient, st.diffuse,
            *st.light, *st.background]
    return torch.tensor(vals, dtype=dtype, device=device)


def _launch_grid(st: Static, b: int, tile: int) -> tuple[tuple[int, int], int]:
    tx = -(-st.width // tile)
    ty = -(-st.height // tile)
    return (tx * ty, b), tx


def _warps(tile: int, fb: int) -> int:
    return 4 if tile * tile * fb <= 1024 else 8


def _camera_space(verts, normals, rotation, eye, faces, st: Static):
    """The setup's PyTorch part: projected vertices (B, V, 3) ``(u [px], v [px], z [m])`` and vertex normals
    (B, V, 3) (the given ones, or area-weighted mesh normals)."""
    uvz = project(verts, rotation, eye, st)
    if normals is None:
        normals = vertex_normals(verts, faces)
    return uvz, normals


def _setup(verts, normals, colors, rotation, eye, faces, st: Static, fb: int, sb: int, *, camera_space=_camera_space):
    """Everything the kernels read for one chunk of environments: :func:`..setup_kernels.face_setup`'s
    coefficients (B, 45, Fp), face boxes (B, 4, Fp), block boxes padded to whole super-blocks and super-block
    boxes, and the floor planes (B, 5, H, W) (:func:`..setup_kernels.floor_planes`). Differentiable (autograd
    through ``camera_space``, the setup kernels' own backward), O(B * F + B * H * W)."""
    uvz, normals = camera_space(verts, normals, rotation, eye, faces, st)
    coef, box, bbox, sbox = face_setup(uvz, normals, colors, faces, st, face_block=fb, super_block=sb)
    if st.floor is None:
        floor = torch.zeros(verts.shape[0], 5, st.height, st.width, dtype=verts.dtype, device=verts.device)
    else:
        floor = floor_planes(rotation, eye, st)
    return coef, box, bbox, sbox, floor


@functools.cache
def _setup_fn(compile_: bool):
    """:func:`_setup`, with its PyTorch part ``torch.compile``'d (``RasterSettings.compile``): eager, projection
    and normals are a few dozen small kernels per render and as many in the backward. The Triton setup
    kernels (faces, floor) stay outside the compiled region: they are already one launch each, and an
    autograd.Function around user Triton kernels inside a compiled graph would have to be registered as a
    custom op (with fake-tensor rules for its outputs) for dynamo to trace it, for no fewer launches."""
    if not compile_:
        return _setup
    return functools.partial(_setup, camera_space=torch.compile(_camera_space, dynamic=False))


def _max_registers(n: int | None) -> dict:
    """Launch options capping a kernel's registers per thread (None: the compiler's choice)."""
    return {} if n is None else {"maxnreg": n}


class BinOverflowWarning(RuntimeWarning):
    """Some forward tiles held more faces than ``tuning.BIN_CAPACITY``: they walked the face blocks instead
    of their lists (the same images, at the unbinned walk's cost). Raise the capacity before capture."""


#: per device, the (1,) int32 count of overflowing (tile, environment) lists since :func:`bin_overflows` last
#: read it; made at a device's first binned render (before any capture: warm-up renders precede it)
_OVERFLOWS: dict[torch.device, torch.Tensor] = {}
_overflow_warned = False


def _overflow_counter(device: torch.device) -> torch.Tensor:
    if device not in _OVERFLOWS:
        _OVERFLOWS[device] = torch.zeros(1, dtype=torch.int32, device=device)
    return _OVERFLOWS[device]


def bin_overflows() -> int:
    """The (tile, environment) face lists that overflowed ``tuning.BIN_CAPACITY`` in the binned renders
    (``tuning.FWD_BIN``) since the last call, over every device; resets the counters. One host transfer per
    device that has rendered binned: call it outside CUDA graph capture, where the iteration synchronises
    anyway. The first nonzero count of the process warns once (:class:`BinOverflowWarning`)."""
    global _overflow_warned
    total = 0
    for counter in _OVERFLOWS.values():
        total += int(counter.item())
        counter.zero_()
    if total and not _overflow_warned:
        _overflow_warned = True
        warnings.warn(f"{total} fused forward tile lists held more than tuning.BIN_CAPACITY = {tuning.BIN_CAPACITY} "
                      "faces and walked the face blocks instead (same images, slower); raise BIN_CAPACITY "
                      "(rasterize.bin_capacity_needed measures a frame)", BinOverflowWarning, stacklevel=2)
    return total


def _bin_capacity() -> int:
    cap = tuning.BIN_CAPACITY
    if not isinstance(cap, int) or isinstance(cap, bool) or cap < 1:
        raise ValueError(f"tuning.BIN_CAPACITY must be a positive integer, got {cap!r}")
    return cap


def _bin(box, bbox, sbox, st: Static, tile: int, fb: int, cap: int,
         counter: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One chunk's face lists: (b, T, cap) int32 face indices and (b, T) int32 counts (``forward._bin_faces``;
    ``cap`` 0: the counts alone, and an empty list tensor); overflows counted in ``counter`` (None: the
    device's, :func:`bin_overflows`)."""
    counter = _overflow_counter(box.device) if counter is None else counter
    (ntiles, b), tx = _launch_grid(st, box.shape[0], tile)
    bins = torch.empty(b, ntiles, cap, dtype=torch.int32, device=box.device)
    cnt = torch.empty(b, ntiles, dtype=torch.int32, device=box.device)
    _bin_faces[(ntiles, b)](box, bbox, sbox, bins, cnt, counter, box.shape[2], bbox.shape[2],
                            sbox.shape[2], st.height, st.width, tx, TILE_=tile, FB=fb,
                            SB=bbox.shape[2] // sbox.shape[2], CAP=cap, num_warps=max(1, min(4, fb // 32)))
    return bins, cnt


def _launch_forward(coef, box, bbox, sbox, floor, st: Static, tile: int, fb: int, out: torch.Tensor,
                    state: torch.Tensor | None) -> None:
    """Blend one chunk's image into ``out`` (b, 3, H, W) and, if ``state`` (b, 4, H, W) is given, what the
    backward needs of each pixel's blend into it (see ``_fused_forward``): one launch, or, where the faces
    make enough super-blocks (:func:`forward_splits`), a split walk and a merge (two launches and a
    transient (splits, b, PART_PER_PIXEL, H, W) of parts). With ``tuning.FWD_BIN`` a binning launch first
    (:func:`_bin`: transient face lists, 4 x T x BIN_CAPACITY bytes an environment)."""
    (ntiles, b), tx = _launch_grid(st, out.shape[0], tile)
    # the parts are a transient of splits x the chunk's pixels: bounded like the coefficients (PART_ELEMS)
    part_bound = tuning.PART_ELEMS // (b * PART_PER_PIXEL * st.height * st.width)
    splits = max(1, min(forward_splits(sbox.shape[2]), part_bound))
    prm = _params(st, out.dtype, out.device)
    model = _MODEL_CODE[st.raster_model]
    save = state is not None
    state = out if state is None else state
    fs = min(fb, tuning.FWD_SUB_BLOCK)
    binned = bool(tuning.FWD_BIN)
    cap = _bin_capacity() if binned else 0
    if binned:
        lists = _bin(box, bbox, sbox, st, tile, fb, cap)
        splits = min(splits, -(-cap // fs))  # a list of cap faces makes ceil(cap / fs) chunks to share out
    part = (torch.empty(splits, b, PART_PER_PIXEL, st.height, st.width, dtype=out.dtype, device=out.device)
            if splits > 1 else out)
    kernel, extra, binned_constants = (_binned_forward, lists, dict(CAP=cap)) if binned else (_fused_forward, (), {})
    kernel[(ntiles, b, splits)](
        coef, box, bbox, sbox, floor, prm, out, state, part, *extra, coef.shape[2], bbox.shape[2], sbox.shape[2],
        splits, st.height, st.width, tx, TILE_=tile, FB=fb, SB=bbox.shape[2] // sbox.shape[2], FS=fs, SAVE=save,
        SPLIT=splits > 1, MODEL=model, COMPACT=tuning.FWD_COMPACT, DEFER=tuning.FWD_DEFER_SHADING and not save,
        num_warps=tuning.FWD_WARPS or _warps(tile, fs), **binned_constants, **_max_registers(tuning.FWD_MAXNREG))
    if splits > 1:
        _merge_forward[(triton.cdiv(st.height * st.width, tuning.MERGE_BLOCK), b)](
            part, floor, prm, out, state, splits, st.height, st.width, BLOCK=tuning.MERGE_BLOCK, SAVE=save, MODEL=model,
            num_warps=4)


def backward_tile(num_faces: int, height: int, width: int) -> int:
    """The backward kernel's tile side [px]: ``BWD_TILE``, or ``BWD_TILE_DENSE`` where there are more than
    ``DENSE_FACES_PER_PIXEL`` faces per pixel of the image. Each backward program walks its tile's pixels once
    per block of faces near it, so its time grows with (faces near the tile) x (tile area); where small faces
    crowd together (many per pixel) the smaller tile splits the busiest tiles' work over more programs."""
    return tuning.BWD_TILE_DENSE if num_faces > tuning.DENSE_FACES_PER_PIXEL * height * width else tuning.BWD_TILE


def forward_splits(num_super_blocks: int) -> int:
    """Forward programs per tile: one per ``FWD_SPLIT_SUPER_BLOCKS`` super-blocks, 1 to ``FWD_MAX_SPLITS``.
    As in the backward (:func:`backward_splits`), the few tiles where detailed meshes crowd thousands of
    faces would otherwise finish long after the rest; split, their walk is shared out and a merge kernel
    combines the parts (worth its extra launch and memory traffic only for many super-blocks)."""
    return max(1, min(tuning.FWD_MAX_SPLITS, num_super_blocks // max(1, tuning.FWD_SPLIT_SUPER_BLOCKS)))


def backward_splits(num_super_blocks: int) -> int:
    """Programs per backward tile: one per ``BWD_SPLIT_SUPER_BLOCKS`` super-blocks, 1 to ``BWD_MAX_SPLITS``.
    A program's time grows with the faces near its tile; where detailed meshes crowd thousands of faces near a
    few tiles, those tiles' programs would run long after the rest of the GPU has finished, so their walk is
    shared out. Programs of a split whose faces are all far from the tile stop after the super-block tests."""
    return max(1, min(tuning.BWD_MAX_SPLITS, num_super_blocks // max(1, tuning.BWD_SPLIT_SUPER_BLOCKS)))


class _FusedRasterize(torch.autograd.Function):
    """Environments are processed ``chunk`` at a time: the per-face coefficients of a chunk (and the
    temporaries that form them) are the renderer's whole working set, so it is bounded by
    ``COEF_ELEMS`` however many faces there are."""

    @staticmethod
    def forward(ctx, verts, normals, colors, rotation, eye, faces, st: Static, tile: int, fb: int, chunk: int,
                compile_: bool, keep_state: bool, bwd_tile: int):
        b = verts.shape[0]
        dt, dev = verts.dtype, verts.device
        setup = _setup_fn(compile_)
        out = torch.empty(b, 3, st.height, st.width, dtype=dt, device=dev)
        # per pixel: the blend's final maximum and denominator (what the backward needs besides the image);
        # kept only when asked to (settings.save_blend_state) and a gradient is wanted
        save = keep_state and any(ctx.needs_input_grad[:5])
        state = torch.empty(b, STATE_PER_PIXEL, st.height, st.width, dtype=dt, device=dev) if save else None
        for sl in chunks(b, chunk):
            coef, box, bbox, sbox, floor = setup(verts[sl], rows(normals, sl), rows(colors, sl, shared_ok=True),
                                                 rotation[sl], eye[sl], faces, st, fb, tuning.SUPER_BLOCK)
            _launch_forward(coef, box, bbox, sbox, floor, st, tile, fb, out[sl],
                            None if state is None else state[sl])
        if save:
            ctx.save_for_backward(verts, normals, colors, rotation, eye, faces, out, state)
        else:
            ctx.save_for_backward(verts, normals, colors, rotation, eye, faces)
        ctx.cfg = (st, tile, fb, chunk, compile_, save, bwd_tile)
        # an undefined incoming gradient (e.g. gradlab's closed ImageGate) stays None: no recompute at all
        ctx.set_materialize_grads(False)
        return out

    @staticmethod
    def backward(ctx, grad_img):
        st, tile, fb, chunk, compile_, saved_state, bwd_tile = ctx.cfg
        if grad_img is None:
            return (None,) * 13
        verts, normals, colors, rotation, eye, faces, *kept = ctx.saved_tensors
        setup = _setup_fn(compile_)
        need = ctx.needs_input_grad[:5]
        inputs = (verts, normals, colors, rotation, eye)
        grads = [torch.zeros_like(x) if (nd and x is not None) else None for x, nd in zip(inputs, need)]
        grad_img = grad_img.contiguous()
        dt, dev = verts.dtype, verts.device
        sub = min(fb, tuning.BWD_SUB_BLOCK)
        for sl in chunks(verts.shape[0], chunk):
            with torch.enable_grad():
                leaves = [None if x is None else rows(x, sl, shared_ok=i == 2).detach().requires_grad_(bool(nd))
                          for i, (x, nd) in enumerate(zip(inputs, need))]
                coef, box, bbox, sbox, floor = setup(*leaves, faces, st, fb, tuning.SUPER_BLOCK)
                floor_diff = floor[:, :4]  # depth and colour (the hit flag has no gradient)
            wanted = [i for i, leaf in enumerate(leaves) if leaf is not None and leaf.requires_grad]
            gcoef = torch.zeros_like(coef)
            gfloor = torch.empty(floor_diff.shape, dtype=dt, device=dev)
            outs = [(t, g) for t, g in ((coef, gcoef), (floor_diff, gfloor)) if t.requires_grad]
            if not (wanted and outs):
                continue
            if saved_state:
                out, state = kept[0][sl], kept[1][sl]
            else:  # the forward pass again, this time keeping the blend state (chunk-sized temporaries)
                nb = sl.stop - sl.start
                out = torch.empty(nb, 3, st.height, st.width, dtype=dt, device=dev)
                state = torch.empty(nb, STATE_PER_PIXEL, st.height, st.width, dtype=dt, device=dev)
                _launch_forward(coef.detach(), box, bbox, sbox, floor.detach(), st, tile, fb, out, state)
            (ntiles, nb), tx = _launch_grid(st, sl.stop - sl.start, bwd_tile)
            splits = backward_splits(sbox.shape[2])
            prm, model = _params(st, dt, dev), _MODEL_CODE[st.raster_model]
            pixel_part = torch.empty(nb, st.height * st.width, PIX_PER_PIXEL, dtype=dt, device=dev)
            _pixel_backward[(triton.cdiv(st.height * st.width, tuning.MERGE_BLOCK), nb)](
                floor.detach(), prm, out, state, grad_img[sl], gfloor, pixel_part, st.height, st.width,
                BLOCK=tuning.MERGE_BLOCK, MODEL=model, num_warps=4)
            _fused_backward[(ntiles, nb, splits)](
                coef.detach(), box, bbox, sbox, prm, pixel_part, gcoef, coef.shape[2], bbox.shape[2], sbox.shape[2],
                splits, st.height, st.width, tx, TILE_=bwd_tile, FB=fb, SB=bbox.shape[2] // sbox.shape[2], SUB=sub,
                MODEL=model, COMPACT=tuning.BWD_COMPACT, num_warps=tuning.BWD_WARPS or max(1, sub // 32),
                **_max_registers(tuning.BWD_MAXNREG_HARD if model == 0 else tuning.BWD_MAXNREG))
            parts = torch.autograd.grad([t for t, _ in outs], [leaves[i] for i in wanted], [g for _, g in outs],
                                        allow_unused=True)
            for i, g in zip(wanted, parts):
                if g is None:
                    continue
                if i == 2 and inputs[i].ndim == 2:  # shared colours: summed over the chunks
                    grads[i] += g
                else:
                    grads[i][sl] += g
        return (*grads, None, None, None, None, None, None, None, None)


@torch.no_grad()
def bin_capacity_needed(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor, camera: Camera,
                        faces: torch.Tensor, settings: RasterSettings, *, tile: int | None = None,
                        face_block: int | None = None) -> int:
    """The most faces any forward tile's list of this frame holds (``tuning.FWD_BIN``; arguments as
    :func:`rasterize_fused`): the smallest ``tuning.BIN_CAPACITY`` with which no tile of it overflows. One host
    transfer; measure before capture, set the capacity with headroom (poses move faces between tiles)."""
    tile = tuning.TILE if tile is None else tile
    face_block = tuning.FACE_BLOCK if face_block is None else face_block
    if not available(verts.device):
        raise ValueError(f"the fused backend runs on CUDA tensors (or on the CPU under TRITON_INTERPRET=1), "
                         f"got {verts.device}")
    st = Static.make(settings, focal=camera.focal, height=camera.height, width=camera.width, tile_h=tile,
                     tile_w=tile)
    nfp = max(1, -(-faces.shape[0] // face_block)) * face_block
    chunk = max(1, tuning.COEF_ELEMS // (NUM_COEFFS * nfp))
    setup = _setup_fn(bool(settings.compile))
    scratch = torch.zeros(1, dtype=torch.int32, device=verts.device)
    most = torch.zeros((), dtype=torch.int32, device=verts.device)
    for sl in chunks(verts.shape[0], chunk):
        _, box, bbox, sbox, _ = setup(verts[sl], rows(normals, sl), rows(colors, sl, shared_ok=True),
                                      camera.rotation[sl], camera.eye[sl], faces, st, face_block, tuning.SUPER_BLOCK)
        most = torch.maximum(most, _bin(box, bbox, sbox, st, tile, face_block, 0, scratch)[1].max())
    return int(most.item())


def rasterize_fused(verts: torch.Tensor, normals: torch.Tensor | None, colors: torch.Tensor, camera: Camera,
                    faces: torch.Tensor, settings: RasterSettings, *, tile: int | None = None,
                    face_block: int | None = None) -> torch.Tensor:
    """Render (B, 3, H, W) with the fused Triton kernels (see :func:`diffrender.render` for the arguments;
    every ``settings.raster_model``). ``tile`` (pixels per tile side) and ``face_block`` (faces
    per block) are powers of two; None reads the module's ``TILE`` and ``FACE_BLOCK``."""
    tile = tuning.TILE if tile is None else tile
    face_block = tuning.FACE_BLOCK if face_block is None else face_block
    if triton is None:
        raise RuntimeError("the fused backend needs triton (it ships with CUDA builds of PyTorch)")
    if not available(verts.device):
        raise ValueError(f"the fused backend runs on CUDA tensors (or on the CPU under TRITON_INTERPRET=1), "
                         f"got {verts.device}")
    for name, n in (("tile", tile), ("face_block", face_block)):
        if n < 1 or n & (n - 1):
            raise ValueError(f"{name} must be a power of two, got {n}")
    st = Static.make(settings, focal=camera.focal, height=camera.height, width=camera.width, tile_h=tile,
                     tile_w=tile)
    nfp = max(1, -(-faces.shape[0] // face_block)) * face_block
    chunk = max(1, tuning.COEF_ELEMS // (NUM_COEFFS * nfp))
    return _FusedRasterize.apply(verts, normals, colors, camera.rotation, camera.eye, faces, st, tile,
                                 face_block, chunk, settings.compile, settings.save_blend_state,
                                 backward_tile(faces.shape[0], camera.height, camera.width))

