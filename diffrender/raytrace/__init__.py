"""A forward-only ray tracer (NVIDIA Warp) for images that need no gradient.

In decoupled mode the policy's image carries no gradient, so it need not come from the soft rasterizer.
:class:`RayTracer` renders the same scene as :func:`diffrender.render` - the same inputs, pinhole camera,
Lambert shading of interpolated vertex normals, analytic checker floor and background - in the rasterizer's
sharp limit (sigma, gamma -> 0): one ray per pixel centre, nearest surface wins.

Design:

- One ``wp.Mesh`` holds the triangles of all B environments; environment b's triangles are BVH group b, and
  the rays of environment b traverse only that group's subtree, so there is one BVH, one refit and one kernel
  launch over all B x H x W pixels per frame. The subtree roots are found once when the BVH is built (a refit
  keeps the tree's topology), not per pixel.
- Threads are grouped by pixel tiles (``tile``, 4 x 8 by default): the 32 rays of a warp start close together
  and walk the same BVH nodes, where a warp along an image row would spread over 32 pixels.
- :meth:`RayTracer.refit` (posed vertices into the BVH) and :meth:`RayTracer.trace` (the image of the last
  refitted geometry) are the two halves of a call, public so that each can be timed
  (``benchmarks/raytrace.py``).
- Persistent buffers per instance: a frame copies the posed vertices into the mesh's point buffer (and the
  normals, colours and camera into theirs), refits the BVH and launches the kernel. Nothing is allocated but
  the returned image (and the normals where they are computed), and with ``sync_checks=False`` nothing waits
  for the device.
- On CUDA, Warp launches on PyTorch's current stream (``wp.ScopedStream(wp.stream_from_torch(...))``), so a
  frame orders correctly with the surrounding PyTorch work and can be captured in a ``torch.cuda.graph``.
  The BVH is built by the first call (from that frame's poses; later frames refit it) and the kernel module is
  loaded by the constructor: make one call before capturing. Inside capture, ``sync_checks`` is skipped as in
  :func:`diffrender.render`.

Where the sharp limit of the rasterizer and the ray tracer differ: the rasterizer drops a whole face with a
vertex nearer than ``znear``, the ray tracer clips at the near plane (only faces straddling it differ), and
the rasterizer also drops faces under 1e-9 px^2 of projected area. Images are computed in float32 and
returned in the dtype of ``verts``. There is no gradient: asking for one is an error (see
:meth:`RayTracer.__call__`).
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any

import torch

from ..camera import Camera
from ..raster.kernel import vertex_normals
from ..render import _can_sync, _check_float, check_inputs
from ..settings import RasterSettings
from ..shading import unit_light

__all__ = ["BVH_CONSTRUCTORS", "RayTracer", "render_raytraced", "warp_on_torch_stream"]

#: Warp's BVH builders that a grouped mesh supports (``RayTracer(bvh_constructor=...)``).
BVH_CONSTRUCTORS = ("sah", "median", "lbvh")

# Far limit [m] of faces in the "alpha" model, where the rasterizer keeps faces beyond zfar.
_NO_FAR_LIMIT = 1.0e30


@functools.cache
def _warp() -> tuple[Any, Any]:
    """Import Warp (quietly) and the kernels: ``(warp, kernels module)``. Deferred so that importing
    diffrender does not import Warp."""
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    else:
        wp.config.quiet = True
    wp.init()
    from . import kernels

    return wp, kernels


def _not_int(x) -> bool:
    return isinstance(x, bool) or not isinstance(x, int)


def warp_on_torch_stream(wp: Any, device: torch.device, wp_device: Any, streams: dict):
    """A context in which Warp launches go on PyTorch's current stream of ``device`` (CUDA; a no-op elsewhere),
    so they are ordered with the surrounding PyTorch work and captured with it in a CUDA graph. ``streams`` caches
    one Warp stream per torch stream handle. The stream is taken at call time: the autograd engine runs a
    backward on its own thread and stream."""
    if device.type != "cuda":
        return contextlib.nullcontext()
    torch_stream = torch.cuda.current_stream(device)
    stream = streams.get(torch_stream.cuda_stream)
    if stream is None:
        stream = streams[torch_stream.cuda_stream] = wp.stream_from_torch(torch_stream)
    # no sync on entry: the work is already ordered on this one stream, and a cross-stream wait would
    # pull Warp's own stream into a graph being captured
    scope = wp.ScopedStream(stream, sync_enter=False)
    if not torch.cuda.is_current_stream_capturing():
        return scope
    # Inside a torch.cuda.graph capture Warp must know that a capture is under way (external=True), so that
    # it allocates and launches in the capture-safe way instead of invalidating the capture.
    stack = contextlib.ExitStack()
    stack.enter_context(scope)
    stack.enter_context(wp.ScopedCapture(device=wp_device, stream=stream, external=True))
    return stack


class RayTracer:
    """Ray-traced images of B environments sharing one triangle topology.

    Args:
        faces: (F, 3) long or int32 vertex indices shared by all environments, counter-clockwise seen from
            outside (back faces are culled with ``settings.cull_backfaces``).
        num_envs: B, environments per frame (every call renders exactly B).
        num_verts: V, vertices per environment.
        device: where the inputs live (default: the device of ``faces``); CPU or CUDA.
        settings: :class:`~diffrender.RasterSettings` (defaults if None). Used: znear, zfar, background,
            floor, light_dir, ambient, diffuse, cull_backfaces, sync_checks and raster_model: ``"hard"`` and
            ``"softmax"`` give the hard model (what the soft model tends to as sigma, gamma -> 0); with
            ``"alpha"`` the floor never hides faces and faces beyond zfar stay visible, as in that model's
            limit. The softness and backend fields have no meaning here.
        shadows: cast a shadow ray towards the light from every visible robot or floor point; a point whose
            ray hits the robot of its environment gets only the ambient term. Off by default (the rasterizer
            has no shadows).
        bvh_constructor: how the BVH's tree is built (once, at the first call; later frames refit it):
            ``"sah"`` (surface-area heuristic, built on the host: the best tree for rays), ``"median"`` (host,
            faster to build, worse tree) or ``"lbvh"`` (built on the GPU, fastest to build; on the CPU Warp has
            no LBVH and ``"sah"`` is built instead). The tree changes which triangle a ray meets first only
            where two meet it at the same distance (a shared edge), so images agree to float rounding.
        bvh_leaf_size: triangles per BVH leaf (None: Warp's default for meshes, 4). Fewer: more tree to
            refit and walk, fewer triangle tests per leaf.
        tile: (rows, columns) of the pixel block that consecutive threads shade, e.g. (4, 8) for one 32-thread
            warp; None: image rows (thread order b, i, j). Same image whatever the tile.
        rays_per_thread: pixels per thread, ``tile`` rows apart (1: one pixel per thread). Same image.
        block_dim: CUDA threads per block of the trace kernel (a multiple of 32); ignored on the CPU.

    Raises:
        ValueError: bad faces (type, shape, indices outside ``0 .. num_verts - 1``), sizes, settings or options
            (naming the option).
        ImportError: Warp (``warp-lang``) is not installed.

    The constructor compiles (first use on a machine, then cached in Warp's kernel cache) and loads the kernel
    on the device; the first call builds the BVH.

    Work per frame on CUDA: five small copies (points, normals, colours, camera rotation and eye), Warp's mesh
    refit (triangle edge lengths and their scan, triangle bounds, a counter reset and the bottom-up refit:
    about seven launches) and one trace launch.
    """

    def __init__(
        self,
        faces: torch.Tensor,
        *,
        num_envs: int,
        num_verts: int,
        device: torch.device | str | None = None,
        settings: RasterSettings | None = None,
        shadows: bool = False,
        bvh_constructor: str = "sah",
        bvh_leaf_size: int | None = None,
        tile: tuple[int, int] | None = (4, 8),
        rays_per_thread: int = 1,
        block_dim: int = 256,
    ):
        settings = RasterSettings() if settings is None else settings
        if not isinstance(settings, RasterSettings):
            raise ValueError(f"settings must be a RasterSettings, got {type(settings).__name__}")
        if not isinstance(faces, torch.Tensor) or faces.dtype not in (torch.int64, torch.int32):
            raise ValueError(f"faces must be an int64/int32 tensor of shape (F, 3), got "
                             f"{getattr(faces, 'dtype', type(faces).__name__)}")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got {tuple(faces.shape)}")
        for name, n in (("num_envs", num_envs), ("num_verts", num_verts)):
            if isinstance(n, bool) or not isinstance(n, int) or n < 1:
                raise ValueError(f"{name} must be a positive int, got {n!r}")
        if not isinstance(shadows, bool):
            raise ValueError(f"shadows must be a bool, got {shadows!r}")
        if bvh_constructor not in BVH_CONSTRUCTORS:
            raise ValueError(f"bvh_constructor must be one of {', '.join(BVH_CONSTRUCTORS)}, got {bvh_constructor!r}")
        if bvh_leaf_size is not None and (_not_int(bvh_leaf_size) or bvh_leaf_size < 1):
            raise ValueError(f"bvh_leaf_size must be None or a positive int, got {bvh_leaf_size!r}")
        if tile is not None and (not isinstance(tile, (tuple, list)) or len(tile) != 2
                                 or any(_not_int(t) or t < 1 for t in tile)):
            raise ValueError(f"tile must be None or (rows, columns) of positive ints, got {tile!r}")
        if _not_int(rays_per_thread) or rays_per_thread < 1:
            raise ValueError(f"rays_per_thread must be a positive int, got {rays_per_thread!r}")
        if _not_int(block_dim) or block_dim < 32 or block_dim % 32 or block_dim > 1024:
            raise ValueError(f"block_dim must be a multiple of 32 in 32..1024, got {block_dim!r}")
        device = faces.device if device is None else torch.device(device)
        if device.type not in ("cpu", "cuda"):
            raise ValueError(f"device must be a CPU or CUDA device, got {device}")
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        if faces.numel():
            lo, hi = (int(x) for x in torch.aminmax(faces))
            if lo < 0 or hi >= num_verts:
                raise ValueError(f"faces index vertices {lo}..{hi} but num_verts is {num_verts}")

        wp, kernels = _warp()
        self._wp, self._kernel, self._roots_kernel = wp, kernels.trace, kernels.group_roots
        self._wp_device = wp.device_from_torch(device)
        self.settings, self.shadows, self.device = settings, shadows, device
        # Warp has no LBVH builder on the host: build what it would fall back to, without its warning
        self.bvh_constructor = "sah" if bvh_constructor == "lbvh" and device.type == "cpu" else bvh_constructor
        self.bvh_leaf_size = bvh_leaf_size
        self.tile = None if tile is None else (int(tile[0]), int(tile[1]))
        self.rays_per_thread, self.block_dim = rays_per_thread, block_dim
        self.num_envs, self.num_verts = num_envs, num_verts
        self.faces = faces.to(device=device, dtype=torch.long)
        self.num_faces = int(faces.shape[0])
        b, nv, nf = num_envs, num_verts, self.num_faces

        f32 = dict(dtype=torch.float32, device=device)
        self._points = torch.zeros(b * nv, 3, **f32)  # the mesh's vertex buffer, refitted in place
        self._normals = torch.zeros(b * nv, 3, **f32)
        self._colors = torch.zeros(b * nv, 3, **f32)
        self._rotation = torch.zeros(b, 3, 3, **f32)
        self._eye = torch.zeros(b, 3, **f32)
        offsets = (torch.arange(b, device=device) * nv).view(b, 1, 1)
        self._indices = (self.faces[None] + offsets).to(torch.int32).reshape(-1).contiguous()
        self._groups = torch.arange(b, device=device, dtype=torch.int32).repeat_interleave(nf)
        self._wp_points = wp.from_torch(self._points, dtype=wp.vec3)
        self._wp_normals = wp.from_torch(self._normals, dtype=wp.vec3)
        self._wp_colors = wp.from_torch(self._colors, dtype=wp.vec3)
        self._wp_rotation = wp.from_torch(self._rotation, dtype=wp.mat33)
        self._wp_eye = wp.from_torch(self._eye, dtype=wp.vec3)
        self._wp_indices = wp.from_torch(self._indices, dtype=wp.int32)
        self._wp_groups = wp.from_torch(self._groups, dtype=wp.int32)
        self._roots = torch.full((b,), -1, dtype=torch.int32, device=device)  # group b's subtree root node
        self._wp_roots = wp.from_torch(self._roots, dtype=wp.int32)
        self._mesh = None  # built by the first call, from its poses
        self._streams: dict[int, Any] = {}
        self._launches: dict[tuple[int, int], Any] = {}

        s = settings
        floor = s.floor
        self._scene = scene = kernels.Scene()
        scene.indices, scene.points = self._wp_indices, self._wp_points
        scene.normals, scene.colors = self._wp_normals, self._wp_colors
        for name, value in dict(
            znear=float(s.znear),
            zfar=_NO_FAR_LIMIT if s.raster_model == "alpha" else float(s.zfar),
            light=wp.vec3(*unit_light(s.light_dir)),
            ambient=float(s.ambient),
            diffuse=float(s.diffuse),
            background=wp.vec3(*(float(c) for c in s.background)),
            has_floor=int(floor is not None),
            square_size=float(floor.square_size) if floor is not None else 1.0,
            color_a=wp.vec3(*(float(c) for c in floor.color_a)) if floor is not None else wp.vec3(),
            color_b=wp.vec3(*(float(c) for c in floor.color_b)) if floor is not None else wp.vec3(),
            edge_px=float(floor.edge_px) if floor is not None else 1.0,
            cull_backfaces=int(s.cull_backfaces),
            floor_occludes=int(s.raster_model != "alpha"),
            shadows=int(shadows),
        ).items():
            setattr(scene, name, value)
        wp.load_module(kernels, device=self._wp_device)

    def __call__(self, verts: torch.Tensor, colors: torch.Tensor, camera: Camera, *,
                 normals: torch.Tensor | None = None) -> torch.Tensor:
        """Render one frame of all B environments.

        Args:
            verts: (B, V, 3) [m] world-frame vertices, float32 or float64.
            colors: (V, 3) or (B, V, 3) albedo in [0, 1], same dtype as ``verts``.
            camera: :class:`~diffrender.Camera` with B (or 1, broadcast) cameras, same dtype and device.
            normals: optional (B, V, 3) world-frame vertex normals (unit, e.g. ``RobotModel.world_normals``);
                None computes area-weighted normals from the mesh.
        Returns:
            (B, 3, H, W) image in [0, 1] (for ``ambient + diffuse <= 1``), in the dtype of ``verts``, with no
            gradient.

        Raises:
            RuntimeError: an input requires grad while grad mode is enabled (the ray tracer has no gradient;
                detach the inputs, call it under ``torch.no_grad()``, or use :func:`diffrender.render`).
            ValueError: wrong types, shapes, dtypes or devices, naming the argument; with
                ``settings.sync_checks`` (one host synchronisation, skipped inside CUDA-graph capture and
                ``torch.compile``), non-finite vertices, normals, colours or camera.
        """
        b, nv = self.num_envs, self.num_verts
        _check_float("verts", verts, f"({b}, {nv}, 3)")
        if tuple(verts.shape) != (b, nv, 3):
            raise ValueError(f"verts must have shape ({b}, {nv}, 3) (num_envs, num_verts, 3), got "
                             f"{tuple(verts.shape)}")
        dtype = verts.dtype
        if verts.device != self.device:
            raise ValueError(f"verts is on {verts.device} but the ray tracer is on {self.device}")
        _check_float("colors", colors, f"({nv}, 3) or ({b}, {nv}, 3)")
        if tuple(colors.shape) not in ((nv, 3), (b, nv, 3)):
            raise ValueError(f"colors must have shape ({nv}, 3) or ({b}, {nv}, 3), got {tuple(colors.shape)}")
        if normals is not None:
            _check_float("normals", normals, f"({b}, {nv}, 3)")
            if normals.shape != verts.shape:
                raise ValueError(f"normals must have the shape of verts {tuple(verts.shape)}, got "
                                 f"{tuple(normals.shape)}")
        for name, x in (("colors", colors), ("normals", normals)):
            if x is None:
                continue
            if x.dtype != dtype:
                raise ValueError(f"{name} is {x.dtype} but verts is {dtype}; use one dtype for all inputs")
            if x.device != self.device:
                raise ValueError(f"{name} is on {x.device} but verts is on {self.device}")
        if not isinstance(camera, Camera):
            raise ValueError(f"camera must be a diffrender.Camera, got {type(camera).__name__}")
        if camera.dtype != dtype:
            raise ValueError(f"camera is {camera.dtype} but verts is {dtype}; build the camera from tensors of "
                             "the same dtype")
        if camera.device != self.device:
            raise ValueError(f"camera is on {camera.device} but verts is on {self.device}")
        if camera.batch_size not in (1, b):
            raise ValueError(f"camera has {camera.batch_size} views but the ray tracer renders {b} environments")
        named = [("verts", verts), ("colors", colors), ("normals", normals), ("camera.eye", camera.eye),
                 ("camera.rotation", camera.rotation)]
        named = [(n, x) for n, x in named if x is not None]
        if torch.is_grad_enabled():
            needs = [n for n, x in named if x.requires_grad]
            if needs:
                raise RuntimeError(
                    f"the ray tracer has no gradient, but {', '.join(needs)} require(s) grad: detach the inputs "
                    "or render under torch.no_grad() (diffrender.render is the differentiable renderer)")
        if self.settings.sync_checks and _can_sync(self.device):
            flags = torch.stack([(~torch.isfinite(x)).any() for _, x in named]).tolist()
            bad = [n for (n, _), f in zip(named, flags) if f]
            if bad:
                raise ValueError(f"{', '.join(bad)} contain(s) NaN or inf values; the image would be meaningless")

        with torch.no_grad():
            if normals is None:
                normals = vertex_normals(verts, self.faces)
            self._refit(verts)
            return self._trace(colors, camera, normals, dtype)

    def refit(self, verts: torch.Tensor) -> None:
        """Move the BVH to new vertices: copy ``verts`` (B, V, 3) [m] into the mesh's point buffer and refit
        (the first call builds the tree). The first half of :meth:`__call__`, which also checks the inputs."""
        b, nv = self.num_envs, self.num_verts
        _check_float("verts", verts, f"({b}, {nv}, 3)")
        if tuple(verts.shape) != (b, nv, 3) or verts.device != self.device:
            raise ValueError(f"verts must have shape ({b}, {nv}, 3) on {self.device}, got {tuple(verts.shape)} on "
                             f"{verts.device}")
        with torch.no_grad():
            self._refit(verts)

    def trace(self, colors: torch.Tensor, camera: Camera, *, normals: torch.Tensor) -> torch.Tensor:
        """The image (B, 3, H, W), float32, of the geometry of the last :meth:`refit`, shaded with ``colors``
        ((V, 3) or (B, V, 3)) and ``normals`` (B, V, 3) seen by ``camera``. The second half of
        :meth:`__call__`, without its input checks (use the call unless timing the halves)."""
        if self._mesh is None and self.num_faces:
            raise RuntimeError("RayTracer.trace before the first refit: there is no BVH yet")
        with torch.no_grad():
            return self._trace(colors, camera, normals, torch.float32)

    def rebuild(self) -> None:
        """Build the BVH anew from the current point buffer with ``bvh_constructor`` (as the first
        :meth:`refit` does). Allocates device memory, so it cannot run inside a CUDA-graph capture; a frame
        refits instead, which keeps the tree's topology."""
        if not self.num_faces:
            return
        with self._stream_scope():
            self._build()

    def _build(self) -> None:
        wp = self._wp
        self._mesh = wp.Mesh(points=self._wp_points, indices=self._wp_indices, groups=self._wp_groups,
                             bvh_constructor=self.bvh_constructor, bvh_leaf_size=self.bvh_leaf_size)
        wp.launch(self._roots_kernel, dim=self.num_envs, inputs=[self._mesh.id, self._wp_roots],
                  device=self._wp_device)
        self._launches.clear()  # they hold the old mesh's id

    def _refit(self, verts: torch.Tensor) -> None:
        self._points.view(self.num_envs, self.num_verts, 3).copy_(verts)
        if not self.num_faces:
            return
        with self._stream_scope():
            if self._mesh is None:
                self._build()
            else:
                self._mesh.refit()

    def _trace(self, colors: torch.Tensor, camera: Camera, normals: torch.Tensor,
               dtype: torch.dtype) -> torch.Tensor:
        b, nv = self.num_envs, self.num_verts
        wp = self._wp
        self._normals.view(b, nv, 3).copy_(normals)
        self._colors.view(b, nv, 3).copy_(colors.expand(b, nv, 3))
        self._rotation.copy_(camera.rotation.expand(b, 3, 3))
        self._eye.copy_(camera.eye.expand(b, 3))
        height, width = camera.height, camera.width
        image = torch.empty(b, 3, height, width, dtype=torch.float32, device=self.device)
        with self._stream_scope():
            launch = self._launches.get((height, width))
            if launch is None:
                tile_h, tile_w = self.tile if self.tile is not None else (1, width)
                rows = tile_h * self.rays_per_thread
                dim = (b, -(-height // rows), -(-width // tile_w), tile_h * tile_w)
                # recorded once per image size and replayed with the changing arguments set: far less host
                # work per frame than a full wp.launch
                launch = self._launches[(height, width)] = wp.launch(
                    self._kernel, dim=dim, device=self._wp_device, record_cmd=True,
                    block_dim=self.block_dim if self.device.type == "cuda" else None, inputs=[
                        self._mesh.id if self._mesh is not None else 0, int(self._mesh is not None),
                        self._wp_roots, tile_h, tile_w, self.rays_per_thread,
                        self._wp_rotation, self._wp_eye, float(camera.focal), self._scene, wp.from_torch(image)])
            else:
                launch.set_param_by_name("focal", float(camera.focal))
                launch.set_param_by_name_from_ctype("image", wp.from_torch(image, return_ctype=True))
            launch.launch()
        return image if dtype == torch.float32 else image.to(dtype)

    def _stream_scope(self):
        """Run Warp's work on PyTorch's current stream (:func:`warp_on_torch_stream`)."""
        return warp_on_torch_stream(self._wp, self.device, self._wp_device, self._streams)

    def __repr__(self) -> str:
        return (f"RayTracer(num_envs={self.num_envs}, num_verts={self.num_verts}, num_faces={self.num_faces}, "
                f"device={self.device}, shadows={self.shadows}, bvh_constructor={self.bvh_constructor!r}, "
                f"bvh_leaf_size={self.bvh_leaf_size}, tile={self.tile}, rays_per_thread={self.rays_per_thread}, "
                f"block_dim={self.block_dim})")


# Ray tracers of render_raytraced, keyed by the faces tensor (held with the tracer, so its storage cannot be
# reused by another tensor while cached), sizes, device and options.
_tracers: dict[tuple, tuple[torch.Tensor, RayTracer]] = {}
_MAX_CACHED_TRACERS = 8


def render_raytraced(
    verts: torch.Tensor,
    faces: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    normals: torch.Tensor | None = None,
    shadows: bool = False,
) -> torch.Tensor:
    """Ray-trace what :func:`diffrender.render` would rasterize, in its sharp limit, without a gradient.

    Takes :func:`diffrender.render`'s arguments (same shapes, dtypes and conventions, checked by the same
    :func:`diffrender.render.check_inputs`) plus ``shadows`` (see :class:`RayTracer`); returns (B, 3, H, W) in the dtype
    of ``verts``. A :class:`RayTracer` per faces tensor, batch size, vertex count, device, settings and ``shadows`` is
    kept and reused, so repeated calls refit one BVH; for full control (and to drop the cache's references) use
    :class:`RayTracer` directly.

    Raises:
        RuntimeError: an input requires grad while grad mode is enabled.
        ValueError: see :class:`RayTracer` and :meth:`RayTracer.__call__`.
    """
    settings, _, _ = check_inputs(verts, faces, colors, camera, settings, normals=normals)
    if verts.shape[1] == 0:
        raise ValueError(f"verts must have shape (B, V, 3) with V >= 1, got {tuple(verts.shape)}")
    b, nv = int(verts.shape[0]), int(verts.shape[1])
    key = (faces.data_ptr(), faces._version, tuple(faces.shape), faces.dtype, verts.device, b, nv, settings,
           bool(shadows))
    entry = _tracers.get(key)
    if entry is None:
        entry = (faces, RayTracer(faces, num_envs=b, num_verts=nv, device=verts.device, settings=settings,
                                  shadows=shadows))
        if len(_tracers) >= _MAX_CACHED_TRACERS:
            _tracers.pop(next(iter(_tracers)))
        _tracers[key] = entry
    return entry[1](verts, colors, camera, normals=normals)
