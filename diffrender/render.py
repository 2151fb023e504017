"""``diffrender.render``: input validation and backend dispatch."""

from __future__ import annotations

import functools
import warnings

import torch

from .camera import Camera
from .raster.binning import bin_faces, count_pairs
from .raster.dense import rasterize_dense
from .raster.tiled import chunk_of, measure_capacity, rasterize_tiled, tiled_static
from .settings import RasterSettings

__all__ = ["BinCapacityWarning", "backend_for", "render"]


class BinCapacityWarning(UserWarning):
    """The tiled backend's automatic bin capacity (``RasterSettings(bin_capacity=None)``) was too small for a
    frame and grew. The frame is still rendered completely; the tiled kernel's shapes change with the capacity
    (a recompile under ``torch.compile``). Given once per process, as a moving robot grows it a few times,
    all alike; filter it by this category, or fix the capacity with :func:`diffrender.measure_bin_capacity`."""


# Automatic bin capacities (settings.bin_capacity None), per scene layout: measured once (one sync), then
# static, so later calls neither sync to size buffers nor change shapes (compile / CUDA-graph friendly).
_capacity_cache: dict[tuple, int] = {}


# Faces tensors already checked for out-of-range indices, keyed by identity and version: the index check
# needs a host sync, and the faces of a robot never change, so it runs once per faces tensor.
_checked_faces: dict[tuple, torch.Tensor] = {}


def _check_float(name: str, x, shape_desc: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {shape_desc}, got {type(x).__name__}")
    if x.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"{name} must be float32 or float64, got {x.dtype}")


def _can_sync(device: torch.device) -> bool:
    if torch.compiler.is_compiling():
        return False
    return not (device.type == "cuda" and torch.cuda.is_current_stream_capturing())


def backend_for(settings: RasterSettings, device: torch.device | str) -> str:
    """The backend :func:`render` uses for ``settings`` on ``device``: ``settings.backend`` unless it is
    ``"auto"``, which picks ``"fused"`` on CUDA (Triton installed) and ``"tiled"`` elsewhere."""
    return _backend(settings, torch.device(device))


def _backend(settings: RasterSettings, device: torch.device) -> str:
    if settings.backend != "auto":
        return settings.backend
    if device.type == "cuda" and _triton_installed():
        return "fused"
    return "tiled"


@functools.cache
def _triton_installed() -> bool:
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


def check_inputs(verts: torch.Tensor, faces: torch.Tensor, colors: torch.Tensor, camera: Camera,
                 settings: RasterSettings | None, *, normals: torch.Tensor | None
                 ) -> tuple[RasterSettings, torch.Tensor, Camera]:
    """:func:`render`'s argument checks, shared by every renderer that takes its arguments
    (:func:`diffrender.render_raytraced`): ValueError naming the argument for a wrong type, shape, dtype or device.
    Returns the settings (the defaults for None), ``faces`` as int64 and the camera expanded to the batch."""
    settings = RasterSettings() if settings is None else settings
    if not isinstance(settings, RasterSettings):
        raise ValueError(f"settings must be a RasterSettings, got {type(settings).__name__}")
    _check_float("verts", verts, "(B, V, 3)")
    if verts.ndim != 3 or verts.shape[2] != 3 or verts.shape[0] == 0:
        raise ValueError(f"verts must have shape (B, V, 3) with B >= 1, got {tuple(verts.shape)}")
    b, nv = verts.shape[:2]
    dtype, device = verts.dtype, verts.device
    if not isinstance(faces, torch.Tensor) or faces.dtype not in (torch.int64, torch.int32):
        raise ValueError(f"faces must be an int64/int32 tensor of shape (F, 3), got "
                         f"{getattr(faces, 'dtype', type(faces).__name__)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {tuple(faces.shape)}")
    if faces.device != device:
        raise ValueError(f"faces is on {faces.device} but verts is on {device}")
    faces = faces.long()
    _check_float("colors", colors, "(V, 3) or (B, V, 3)")
    if colors.shape not in ((nv, 3), (b, nv, 3)):
        raise ValueError(f"colors must have shape ({nv}, 3) or ({b}, {nv}, 3), got {tuple(colors.shape)}")
    for name, x in (("colors", colors), ("normals", normals)):
        if x is None:
            continue
        _check_float(name, x, "(B, V, 3)")
        if x.dtype != dtype:
            raise ValueError(f"{name} is {x.dtype} but verts is {dtype}; use one dtype for all inputs")
        if x.device != device:
            raise ValueError(f"{name} is on {x.device} but verts is on {device}")
    if normals is not None and normals.shape != verts.shape:
        raise ValueError(f"normals must have the shape of verts {tuple(verts.shape)}, got {tuple(normals.shape)}")
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a diffrender.Camera, got {type(camera).__name__}")
    if camera.dtype != dtype:
        raise ValueError(f"camera is {camera.dtype} but verts is {dtype}; build the camera from tensors of "
                         "the same dtype")
    if camera.device != device:
        raise ValueError(f"camera is on {camera.device} but verts is on {device}")
    if camera.batch_size not in (1, b):
        raise ValueError(f"camera has {camera.batch_size} views but verts has {b} environments")
    camera = camera.expand(b)
    return settings, faces, camera


def render(
    verts: torch.Tensor,
    faces: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    normals: torch.Tensor | None = None,
) -> torch.Tensor:
    """Rasterize triangle meshes over the analytic floor with the image model ``settings.raster_model``.

    Args:
        verts: (B, V, 3) [m] world-frame vertices, float32 or float64.
        faces: (F, 3) long (or int32) vertex indices, shared by all environments; winding counter-clockwise
            seen from outside (needed for back-face culling).
        colors: (V, 3) or (B, V, 3) albedo in [0, 1], same dtype as ``verts``.
        camera: :class:`~diffrender.Camera` with B (or 1, broadcast) cameras, same dtype/device.
        settings: :class:`~diffrender.RasterSettings` (defaults if None).
        normals: optional (B, V, 3) unit world-frame vertex normals (e.g. ``RobotModel.world_normals``);
            None computes area-weighted normals from the mesh inside the renderer (no extra saved memory).
    Returns:
        (B, 3, H, W) image in [0, 1], differentiable w.r.t. ``verts``, ``normals``, ``colors`` and the
        camera's rotation and eye (hence the look-at eye and target).

    Raises:
        ValueError: wrong types, shapes, dtypes (e.g. float32 mixed with float64) or devices, naming the
            argument; non-finite vertices/normals/colours/camera; face indices out of range.
        RuntimeError: the tiled backend's bins overflowed (the message gives the environment, the counts,
            the capacity and how to raise it).

    Host synchronisation: with ``settings.sync_checks`` (default) one sync at the end of the call reads the
    overflow and finiteness flags (plus one the first time a faces tensor is seen, to range-check it).
    With ``sync_checks=False``, or inside CUDA-graph capture / ``torch.compile``, nothing syncs and an
    overflowing environment renders as NaN.
    """
    settings, faces, camera = check_inputs(verts, faces, colors, camera, settings, normals=normals)
    nv, device = verts.shape[1], verts.device

    sync = settings.sync_checks and _can_sync(device)
    if sync and faces.numel():
        key = (faces.data_ptr(), faces._version, tuple(faces.shape), faces.device, nv)
        if key not in _checked_faces:
            lo, hi = torch.aminmax(faces)
            lo, hi = int(lo), int(hi)
            if lo < 0 or hi >= nv:
                raise ValueError(f"faces index vertices {lo}..{hi} but there are {nv} vertices")
            if len(_checked_faces) > 64:
                _checked_faces.clear()
            # the value keeps the tensor alive: while cached, its storage cannot be freed and reused by another
            # faces tensor at the same address, which would then skip its check
            _checked_faces[key] = faces

    named = [("verts", verts), ("colors", colors), ("normals", normals),
             ("camera.eye", camera.eye), ("camera.rotation", camera.rotation)]
    if sync:
        nonfinite = torch.stack([(~torch.isfinite(x)).any() for _, x in named if x is not None])

    backend = _backend(settings, device)
    if backend == "fused":
        from .raster import fused  # imports triton: only when used

        img = fused.rasterize_fused(verts, normals, colors, camera, faces, settings)
        count = capacity = None
    elif backend == "dense":
        img = rasterize_dense(verts, normals, colors, camera, faces, settings)
        count = capacity = None
    else:
        auto = settings.bin_capacity is None
        if auto:
            key = (faces.data_ptr(), faces.shape[0], nv, camera.height, camera.width, camera.focal,
                   settings.tile_size, settings.cutoff_radius, settings.cull_backfaces, device)
            capacity = _capacity_cache.get(key)
            if capacity is None:
                st = tiled_static(settings, camera)
                if sync:  # measure once (one extra sync the first time this scene layout is rendered)
                    _, capacity = measure_capacity(verts, camera.rotation, camera.eye, faces, settings, st)
                else:  # cannot measure inside capture: a generous guess; overflow shows as NaN
                    capacity = max(4096, 4 * faces.shape[0])
                _capacity_cache[key] = capacity
        else:
            capacity = settings.bin_capacity
        img, count = rasterize_tiled(verts, normals, colors, camera, faces, settings, capacity)

    if sync:
        flags = nonfinite.long()
        if count is not None:
            flags = torch.cat([flags, count.max().reshape(1)])
        flags = flags.tolist()  # the one host synchronisation of the call
        bad = [name for (name, x), f in zip([nx for nx in named if nx[1] is not None], flags) if f]
        if bad:
            raise ValueError(f"{', '.join(bad)} contain(s) NaN or inf values; the image would be meaningless")
        if count is not None and flags[-1] > capacity:
            if not auto:
                raise RuntimeError(_overflow_message(verts, camera, faces, settings, count, capacity))
            # automatic capacity: grow it for this scene layout and render again (never an incomplete image)
            _, new_capacity = measure_capacity(verts, camera.rotation, camera.eye, faces, settings,
                                               tiled_static(settings, camera))
            new_capacity = max(new_capacity, capacity + 64)
            global _growth_warned
            if not _growth_warned:  # once per process: a moving robot grows it a few times, all alike
                _growth_warned = True
                warnings.warn(f"diffrender: automatic bin capacity grown from {capacity} to {new_capacity} "
                              f"(pairs needed {flags[-1]}); the tiled kernel's shapes change with it (further "
                              "growths are not reported)", BinCapacityWarning, stacklevel=2)
            _capacity_cache[key] = new_capacity
            img, _ = rasterize_tiled(verts, normals, colors, camera, faces, settings, new_capacity)
    return img


_growth_warned = False  # the automatic capacity's growth has been reported in this process


def _overflow_message(verts, camera, faces, settings, need, capacity) -> str:
    st = tiled_static(settings, camera)
    worst = int(torch.argmax(need))
    sl = chunk_of(worst, verts.shape[0], settings, st, capacity)
    nb = sl.stop - sl.start
    v, rot, eye = verts[sl].detach(), camera.rotation[sl].detach(), camera.eye[sl].detach()
    per_env = count_pairs(v, rot, eye, faces, st)
    busiest = int(torch.argmax(per_env))
    bins = bin_faces(v[busiest:busiest + 1], rot[busiest:busiest + 1], eye[busiest:busiest + 1], faces, st,
                     int(per_env[busiest]))
    per_tile = torch.bincount(bins.tile[bins.valid], minlength=st.num_tiles)
    tile = int(torch.argmax(per_tile))
    per_env_need = int(need[worst])
    n_over = int((need > capacity).sum())
    return (
        f"tiled rasterizer bin overflow: environments {sl.start}..{sl.stop - 1} (rendered together) need "
        f"{int(per_env.sum())} (tile, face) pairs, {per_env_need} per environment, but bin_capacity is "
        f"{capacity} per environment ({capacity * nb} slots; {n_over} of {need.numel()} environments overflow; "
        f"{faces.shape[0]} faces, {st.num_tiles} tiles of {st.tile_h}x{st.tile_w} px). The busiest environment, "
        f"{sl.start + busiest}, needs {int(per_env[busiest])}; its busiest tile, {tile} (tile row "
        f"{tile // st.tiles_x}, column {tile % st.tiles_x}), holds {int(per_tile[tile])} faces. Raise "
        f"RasterSettings(bin_capacity=...) to at least {per_env_need} (e.g. {int(per_env_need * 1.25) + 1} for "
        f"headroom), leave it None for an automatic capacity, or use a larger tile_size (fewer tiles per face). "
        f"No image was returned because it would be incomplete."
    )
