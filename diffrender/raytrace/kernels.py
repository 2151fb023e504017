"""Warp kernels of the ray tracer: a thread per pixel (or a few pixels) of every environment.

Imported only by :class:`diffrender.raytrace.RayTracer` (importing this module imports and configures Warp).
The image model is :func:`diffrender.render`'s in its sharp limit (sigma, gamma -> 0), evaluated by casting
one camera ray per pixel centre into a BVH instead of blending soft candidates; see
:mod:`diffrender.raytrace` for what is and is not identical.
"""

# Variables that the kernel reassigns in branches and loops are declared with typed constructors
# (``int(0)``, ``float(0.0)``), as Warp's code generation requires of mutable locals.
# ruff: noqa: UP018, RUF046

from __future__ import annotations

import warp as wp

from ..floor import _MAX_SHARPNESS

__all__ = ["Scene", "group_roots", "trace"]

# Back faces skipped along one ray when culling (a ray leaving a closed mesh meets at most a few).
_MAX_CULLED = wp.constant(16)
# Distance [m] per metre of depth by which a ray restarts beyond a culled face, and by which a shadow ray
# starts off its surface: well above float32 rounding of world positions, well below any robot feature.
_RAY_EPSILON = wp.constant(1.0e-4)
# Length [m] of a shadow ray towards the (directional) light: beyond any scene.
_SHADOW_RAY_LENGTH = wp.constant(1.0e4)
_CHECKER_MAX_SHARPNESS = wp.constant(float(_MAX_SHARPNESS))


@wp.func
def _lambert(n: wp.vec3, light: wp.vec3, ambient: float, diffuse: float) -> float:
    """``ambient + diffuse * max(0, n . l / |n|)`` as :func:`diffrender.shading.lambert_shade`."""
    n_dot_l = wp.dot(n, light)
    return ambient + diffuse * wp.max(n_dot_l / wp.sqrt(wp.dot(n, n) + 1.0e-20), 0.0)


@wp.kernel(enable_backward=False)
def group_roots(mesh: wp.uint64, roots: wp.array(dtype=wp.int32)):
    """``roots[b]``: the BVH node under which environment b's triangles (group b) lie. A refit keeps the
    tree's topology, so these stay valid until the BVH is built anew; the trace kernel reads them instead of
    searching the leaves and climbing to their common ancestor for every pixel."""
    b = wp.tid()
    roots[b] = wp.mesh_get_group_root(mesh, b)


@wp.struct
class Scene:
    """What every pixel's shading reads besides its own ray and the camera's focal length, the same for every
    frame of a tracer: the meshes' vertex data (``indices``: the mesh's (B * F * 3) global vertex ids;
    ``points`` (the mesh's), ``normals``, ``colors``: (B * V) per global vertex), the clip planes [m], the
    light, the background colour, the floor's checker and the flags (0/1 ints)."""

    indices: wp.array(dtype=wp.int32)
    points: wp.array(dtype=wp.vec3)
    normals: wp.array(dtype=wp.vec3)
    colors: wp.array(dtype=wp.vec3)
    znear: float
    zfar: float
    light: wp.vec3
    ambient: float
    diffuse: float
    background: wp.vec3
    has_floor: int
    square_size: float
    color_a: wp.vec3
    color_b: wp.vec3
    edge_px: float
    cull_backfaces: int
    floor_occludes: int
    shadows: int


@wp.func
def _shade(
    b: int,
    i: int,
    j: int,
    height: int,
    width: int,
    mesh: wp.uint64,
    has_mesh: int,
    root: int,
    rot: wp.mat33,
    origin: wp.vec3,
    focal: float,
    scene: Scene,
) -> wp.vec3:
    """The colour of pixel (i, j) of environment b (see :func:`trace`)."""
    dxc = (float(j) + 0.5 - 0.5 * float(width)) / focal
    dyc = (float(i) + 0.5 - 0.5 * float(height)) / focal
    # world ray direction R^T (dxc, dyc, 1): its camera z is 1, so a ray parameter is the camera depth [m]
    d = wp.transpose(rot) @ wp.vec3(dxc, dyc, 1.0)

    # the analytic floor z = 0 where the ray meets it beyond znear (also beyond zfar: it reaches the horizon)
    floor_hit = int(0)
    t_floor = float(0.0)
    if scene.has_floor != 0 and wp.abs(d[2]) > 1.0e-12:
        t_floor = -origin[2] / d[2]
        if t_floor > scene.znear:
            floor_hit = 1

    # faces between znear and zfar, and in front of the floor where the floor occludes them
    far = scene.zfar
    if floor_hit != 0 and scene.floor_occludes != 0:
        far = wp.min(far, t_floor)
    face = int(-1)
    bu = float(0.0)
    bv = float(0.0)
    depth = float(0.0)
    if has_mesh != 0 and far > scene.znear:
        start = scene.znear
        for _ in range(_MAX_CULLED):
            q = wp.mesh_query_ray(mesh, origin + start * d, d, far - start, root)
            if not q.result:
                break
            if scene.cull_backfaces != 0 and q.sign < 0.0:
                start = start + q.t + _RAY_EPSILON * (1.0 + start + q.t)
                if start >= far:
                    break
                continue
            face = q.face
            bu = q.u
            bv = q.v
            depth = start + q.t
            break

    color = scene.background
    if face >= 0:
        # barycentric weights of the face's corners: the hit is bu * p0 + bv * p1 + (1 - bu - bv) * p2
        v0 = scene.indices[3 * face]
        v1 = scene.indices[3 * face + 1]
        v2 = scene.indices[3 * face + 2]
        bw = 1.0 - bu - bv
        n = bu * scene.normals[v0] + bv * scene.normals[v1] + bw * scene.normals[v2]
        albedo = bu * scene.colors[v0] + bv * scene.colors[v1] + bw * scene.colors[v2]
        shade = _lambert(n, scene.light, scene.ambient, scene.diffuse)
        if scene.shadows != 0 and shade > scene.ambient:
            p = origin + depth * d
            # leave the surface on the side facing the light (the geometric normal, not the interpolated one,
            # decides which side the shadow ray starts on)
            ng = wp.normalize(wp.cross(scene.points[v1] - scene.points[v0], scene.points[v2] - scene.points[v0]))
            if wp.dot(ng, scene.light) < 0.0:
                ng = -ng
            eps = _RAY_EPSILON * (1.0 + depth)
            if wp.mesh_query_ray_anyhit(mesh, p + eps * (ng + scene.light), scene.light, _SHADOW_RAY_LENGTH,
                                        root):
                shade = scene.ambient
        color = albedo * shade
    elif floor_hit != 0:
        x = origin[0] + t_floor * d[0]
        y = origin[1] + t_floor * d[1]
        # the checker of diffrender.floor.floor_candidate: an edge spans edge_px pixels at this depth
        footprint = t_floor / (focal * wp.abs(d[2]))
        sharpness = wp.min(scene.square_size / (wp.pi * scene.edge_px * footprint), _CHECKER_MAX_SHARPNESS)
        mix = 0.5 + 0.5 * wp.tanh(sharpness * wp.sin(wp.pi * x / scene.square_size)
                                  * wp.sin(wp.pi * y / scene.square_size))
        shade = scene.ambient + scene.diffuse * wp.max(scene.light[2], 0.0)
        if scene.shadows != 0 and has_mesh != 0 and scene.light[2] > 0.0:
            eps = _RAY_EPSILON * (1.0 + t_floor)
            p = wp.vec3(x, y, 0.0) + eps * (wp.vec3(0.0, 0.0, 1.0) + scene.light)
            if wp.mesh_query_ray_anyhit(mesh, p, scene.light, _SHADOW_RAY_LENGTH, root):
                shade = scene.ambient
        color = (scene.color_b + mix * (scene.color_a - scene.color_b)) * shade
    return color


@wp.kernel(enable_backward=False)
def trace(
    mesh: wp.uint64,
    has_mesh: int,
    roots: wp.array(dtype=wp.int32),
    tile_h: int,
    tile_w: int,
    rays_per_thread: int,
    rotation: wp.array(dtype=wp.mat33),
    eye: wp.array(dtype=wp.vec3),
    focal: float,
    scene: Scene,
    image: wp.array4d(dtype=wp.float32),
):
    """Shade ``rays_per_thread`` pixels of environment b into ``image[b, :, i, j]`` (B, 3, H, W).

    Launched over (B, tiles down, tiles across, tile_h * tile_w): the threads of one tile (consecutive, so
    one warp for a 32-pixel tile) cover a tile_h x tile_w block of pixels, whose rays are close together and
    so walk the same BVH nodes; a thread shades its pixel in ``rays_per_thread`` such blocks stacked
    downwards. Pixels beyond the image (a partial last tile) are skipped.

    ``mesh`` holds every environment's triangles, environment b's as group b, whose subtree is ``roots[b]``;
    ``scene``: its vertex data and the settings (:class:`Scene`). ``rotation``, ``eye``: (B) world -> camera.
    Flags are 0/1 ints.
    """
    b, ty, tx, lane = wp.tid()
    height = image.shape[2]
    width = image.shape[3]
    j = tx * tile_w + lane % tile_w
    if j >= width:
        return
    rot = rotation[b]
    origin = eye[b]
    root = int(-1)
    if has_mesh != 0:
        root = roots[b]
    i0 = ty * tile_h * rays_per_thread + lane // tile_w
    for r in range(rays_per_thread):
        i = i0 + r * tile_h
        if i < height:
            color = _shade(b, i, j, height, width, mesh, has_mesh, root, rot, origin, focal, scene)
            image[b, 0, i, j] = color[0]
            image[b, 1, i, j] = color[1]
            image[b, 2, i, j] = color[2]
