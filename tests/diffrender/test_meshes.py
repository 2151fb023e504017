"""Primitive meshes: closed, outward-wound, exact normals, documented sizes."""

import numpy as np
import pytest

from diffrender import meshes as M


def _check_closed_outward(mesh: M.LocalMesh):
    v, f, n = mesh.vertices, mesh.faces, mesh.normals
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    # signed volume > 0 <=> counter-clockwise seen from outside
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    assert volume > 0
    # closed: every undirected edge is used by exactly two faces, once in each direction
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.round(np.concatenate([v[edges[:, 0]], v[edges[:, 1]]], 1), 9)
    fwd = {tuple(k) for k in key}
    rev = {tuple(np.concatenate([k[3:], k[:3]])) for k in key}
    assert fwd == rev
    # unit vertex normals agree with the winding of every face using them
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    fn = np.cross(b - a, c - a)
    for k in range(3):
        assert (np.einsum("ij,ij->i", fn, n[f[:, k]]) > 0).all()
    return volume


@pytest.mark.parametrize("detail", sorted(M.DETAIL_LEVELS))
def test_primitives_closed_outward_and_sized_as_documented(detail):
    # (vertices, faces) per detail level, as the module docstring documents
    table = {
        0: {"sphere": (42, 80), "capsule": (38, 72), "cylinder": (34, 32)},
        1: {"sphere": (162, 320), "capsule": (66, 128), "cylinder": (66, 64)},
        2: {"sphere": (642, 1280), "capsule": (146, 288), "cylinder": (130, 128)},
        3: {"sphere": (2562, 5120), "capsule": (258, 512), "cylinder": (258, 256)},
    }[detail]
    sphere = M.sphere_mesh(0.3, detail=detail)
    capsule = M.capsule_mesh(0.1, 0.4, detail=detail)
    cylinder = M.cylinder_mesh(0.1, 0.4, detail=detail)
    ellipsoid = M.ellipsoid_mesh([0.1, 0.2, 0.3], detail=detail)
    for name, mesh in (("sphere", sphere), ("capsule", capsule), ("cylinder", cylinder)):
        assert (mesh.num_vertices, mesh.num_faces) == table[name], name
    assert (ellipsoid.num_vertices, ellipsoid.num_faces) == table["sphere"]
    # volumes converge to the analytic ones from below (inscribed polyhedra)
    for mesh, exact in ((sphere, 4 / 3 * np.pi * 0.3**3), (capsule, np.pi * 0.01 * 0.8 + 4 / 3 * np.pi * 1e-3),
                        (cylinder, np.pi * 0.01 * 0.8), (ellipsoid, 4 / 3 * np.pi * 0.006)):
        vol = _check_closed_outward(mesh)
        assert 0.7 * exact < vol <= exact * (1 + 1e-12)


def test_box_has_flat_sides():
    box = M.box_mesh([0.1, 0.2, 0.3])
    assert (box.num_vertices, box.num_faces) == (24, 12)
    assert np.isclose(_check_closed_outward(box), 0.2 * 0.4 * 0.6)
    # every vertex normal is an axis and each vertex lies on the side its normal names
    axis = np.argmax(np.abs(box.normals), axis=1)
    assert np.allclose(np.abs(box.normals).max(1), 1.0)
    assert np.allclose(np.abs(box.vertices[np.arange(24), axis]), np.array([0.1, 0.2, 0.3])[axis])


def test_capsule_and_ellipsoid_normals_are_exact():
    cap = M.capsule_mesh(0.1, 0.4, detail=1)
    # every vertex is at distance r from the axis segment, along its normal
    axis_pt = np.zeros_like(cap.vertices)
    axis_pt[:, 2] = np.clip(cap.vertices[:, 2], -0.4, 0.4)
    assert np.allclose(cap.vertices - axis_pt, 0.1 * cap.normals)
    ell = M.ellipsoid_mesh([0.1, 0.2, 0.3], detail=1)
    grad = ell.vertices / np.array([0.1, 0.2, 0.3]) ** 2
    assert np.allclose(grad / np.linalg.norm(grad, axis=1, keepdims=True), ell.normals)


@pytest.mark.parametrize("target", [6, 40, 100, 500, 2000])
def test_latlong_sphere_vertex_count(target):
    mesh = M.latlong_sphere_mesh(0.05, target)
    _check_closed_outward(mesh)
    rings = round(0.5 * (1 + np.sqrt(1 + 2 * (mesh.num_vertices - 2))))
    assert mesh.num_vertices == 2 * rings * (rings - 1) + 2
    assert mesh.num_faces == 4 * rings * (rings - 1)
    # the closest achievable count: the neighbouring ring counts are not closer
    for r in (rings - 1, rings + 1):
        if r >= 2:
            assert abs(2 * r * (r - 1) + 2 - target) >= abs(mesh.num_vertices - target)


def test_bad_detail_and_size():
    with pytest.raises(ValueError, match="detail"):
        M.sphere_mesh(1.0, detail=7)
    with pytest.raises(ValueError, match="num_vertices"):
        M.latlong_sphere_mesh(1.0, 3)
