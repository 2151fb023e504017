"""Triangle meshes for MuJoCo geom primitives, in the geom's local frame.

MuJoCo's local-frame conventions (after compilation, so ``fromto`` is already resolved):

- sphere:   ``size[0]`` is the radius.
- capsule:  ``size = [radius, half_length]``, axis along local z (cylinder part from -half_length to
  +half_length, hemispherical caps beyond).
- cylinder: ``size = [radius, half_length]``, axis along local z.
- box:      ``size`` are the half extents.
- ellipsoid: ``size`` are the three radii.

Every mesh here is closed, consistently wound with outward normals (right-hand rule), and carries exact
analytic per-vertex normals. Vertices are split where the surface has a crease (box edges, cylinder rims) so
that interpolated normals shade flat faces flat; smooth surfaces (spheres, capsules) share vertices.

Tessellation per ``detail`` level (vertices / faces per mesh):

======  ================  ==================  =================  ========  ====================
detail  sphere (ico)      capsule             cylinder           box       ellipsoid (ico)
======  ================  ==================  =================  ========  ====================
0       42 / 80           38 / 72             34 / 32 (8 sides)  24 / 12   42 / 80
1       162 / 320         66 / 128            66 / 64 (16)       24 / 12   162 / 320
2       642 / 1280        146 / 288           130 / 128 (32)     24 / 12   642 / 1280
3       2562 / 5120       258 / 512           258 / 256 (64)     24 / 12   2562 / 5120
======  ================  ==================  =================  ========  ====================

Detail 1 (the default) gives the ant 1,856 faces (954 vertices), the humanoid 3,008 (1,542), the hopper 512
(264) and the cartpole 36 (72).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

__all__ = [
    "DETAIL_LEVELS",
    "LocalMesh",
    "box_mesh",
    "capsule_mesh",
    "cylinder_mesh",
    "ellipsoid_mesh",
    "latlong_sphere_mesh",
    "sphere_mesh",
]

# detail -> (icosphere subdivisions, capsule count [segments, rings], cylinder sections)
DETAIL_LEVELS: dict[int, tuple[int, tuple[int, int], int]] = {
    0: (1, (6, 6), 8),
    1: (2, (8, 8), 16),
    2: (3, (12, 12), 32),
    3: (4, (16, 16), 64),
}


@dataclass(frozen=True)
class LocalMesh:
    """A closed triangle mesh in a geom's local frame.

    Attributes:
        vertices: (n, 3) float64 [m].
        normals: (n, 3) float64 unit outward vertex normals.
        faces: (m, 3) int64 indices into ``vertices``, counter-clockwise seen from outside.
    """

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])


def _check_detail(detail: int) -> tuple[int, tuple[int, int], int]:
    if detail not in DETAIL_LEVELS:
        raise ValueError(f"detail must be one of {sorted(DETAIL_LEVELS)}, got {detail!r}")
    return DETAIL_LEVELS[detail]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _make(vertices, normals, faces) -> LocalMesh:
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    n = np.ascontiguousarray(normals, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    return LocalMesh(vertices=v, normals=n, faces=f)


def _split_by_normal(mesh: trimesh.Trimesh, normal_of_face_vertex) -> LocalMesh:
    """Unmerge a mesh, give each face corner an analytic normal, and re-merge corners whose position and
    normal agree. This keeps creases sharp (a box corner becomes three vertices) while smooth parts still
    share vertices."""
    faces = np.asarray(mesh.faces)
    corners = np.asarray(mesh.vertices)[faces].reshape(-1, 3)  # (3m, 3)
    face_normals = np.repeat(np.asarray(mesh.face_normals), 3, axis=0)  # (3m, 3)
    normals = normal_of_face_vertex(corners, face_normals)
    key = np.round(np.concatenate([corners, normals], axis=1), 9)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # keep the order of first appearance so the layout is deterministic and cache-friendly
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return _make(corners[first[order]], normals[first[order]], rank[inverse].reshape(-1, 3))


def sphere_mesh(radius: float, *, detail: int = 1) -> LocalMesh:
    """Icosphere of ``radius`` [m] centred at the origin."""
    subdiv, _, _ = _check_detail(detail)
    m = trimesh.creation.icosphere(subdivisions=subdiv, radius=1.0)
    unit = _unit(np.asarray(m.vertices))
    return _make(unit * radius, unit, m.faces)


def ellipsoid_mesh(radii, *, detail: int = 1) -> LocalMesh:
    """Ellipsoid with semi-axes ``radii`` (3,) [m] along local x, y, z."""
    subdiv, _, _ = _check_detail(detail)
    r = np.asarray(radii, dtype=np.float64).reshape(3)
    m = trimesh.creation.icosphere(subdivisions=subdiv, radius=1.0)
    unit = _unit(np.asarray(m.vertices))
    # the gradient of x^2/a^2 + ... is the outward normal
    return _make(unit * r, _unit(unit / r), m.faces)


def capsule_mesh(radius: float, half_length: float, *, detail: int = 1) -> LocalMesh:
    """Capsule along local z: cylinder of ``radius`` from -``half_length`` to +``half_length`` plus caps."""
    _, count, _ = _check_detail(detail)
    m = trimesh.creation.capsule(height=2.0 * half_length, radius=radius, count=list(count))
    v = np.asarray(m.vertices, dtype=np.float64)
    # the closest point of the axis segment gives the exact outward normal on both caps and the side
    axis_point = np.zeros_like(v)
    axis_point[:, 2] = np.clip(v[:, 2], -half_length, half_length)
    return _make(v, _unit(v - axis_point), m.faces)


def cylinder_mesh(radius: float, half_length: float, *, detail: int = 1) -> LocalMesh:
    """Closed cylinder along local z with flat caps (rim vertices split so caps shade flat)."""
    _, _, sections = _check_detail(detail)
    m = trimesh.creation.cylinder(radius=radius, height=2.0 * half_length, sections=sections)

    def normal(corners, face_normals):
        cap = np.abs(face_normals[:, 2]) > 0.99
        cap_normal = np.zeros_like(corners)
        cap_normal[:, 2] = np.sign(face_normals[:, 2])
        radial = corners.copy()
        radial[:, 2] = 0.0
        radial[~cap] = _unit(radial[~cap])  # side corners lie on the rim, never on the axis
        return np.where(cap[:, None], cap_normal, radial)

    return _split_by_normal(m, normal)


def box_mesh(half_extents) -> LocalMesh:
    """Box with ``half_extents`` (3,) [m]; 4 vertices per side so each side shades flat (24 / 12)."""
    h = np.asarray(half_extents, dtype=np.float64).reshape(3)
    m = trimesh.creation.box(extents=2.0 * h)
    return _split_by_normal(m, lambda corners, face_normals: face_normals)


def latlong_sphere_mesh(radius: float, num_vertices: int) -> LocalMesh:
    """Latitude-longitude sphere with about ``num_vertices`` vertices (at least 6), for scene-complexity
    sweeps where the vertex count must be chosen freely. ``rings - 1`` latitude circles of ``2 * rings``
    vertices plus two poles, so ``V = 2 * rings * (rings - 1) + 2`` and ``F = 4 * rings * (rings - 1)``."""
    if num_vertices < 6:
        raise ValueError(f"num_vertices must be >= 6, got {num_vertices}")
    # solve 2 r (r - 1) + 2 ~= num_vertices for r (closed form of the quadratic), then take the best neighbour
    r0 = 0.5 * (1.0 + np.sqrt(1.0 + 2.0 * (num_vertices - 2)))
    cands = [max(2, int(np.floor(r0))), max(2, int(np.ceil(r0)))]
    rings = min(cands, key=lambda r: abs(2 * r * (r - 1) + 2 - num_vertices))
    n_lon = 2 * rings
    theta = np.pi * np.arange(1, rings) / rings  # polar angles of the latitude circles
    phi = 2.0 * np.pi * np.arange(n_lon) / n_lon
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring_pts = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (rings - 1, n_lon))], -1)
    unit = np.concatenate([[[0.0, 0.0, 1.0]], ring_pts.reshape(-1, 3), [[0.0, 0.0, -1.0]]], 0)
    top, bottom = 0, unit.shape[0] - 1

    def idx(i, j):  # ring i (0-based), longitude j
        return 1 + i * n_lon + (j % n_lon)

    faces = []
    for j in range(n_lon):
        faces.append((top, idx(0, j), idx(0, j + 1)))
        faces.append((bottom, idx(rings - 2, j + 1), idx(rings - 2, j)))
    for i in range(rings - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            faces.append((a, c, d))
            faces.append((a, d, b))
    return _make(unit * radius, unit, np.asarray(faces))
