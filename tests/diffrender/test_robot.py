"""RobotModel: forward kinematics against MuJoCo, meshes, gradients, errors."""

import mujoco
import numpy as np
import pytest
import torch

import diffrender as dr

from .helpers import F64, ROBOTS, asset


def _random_qpos(model: mujoco.MjModel, batch: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.tensor(model.qpos0, dtype=F64).repeat(batch, 1)
    q = q + torch.randn(batch, model.nq, dtype=F64, generator=g)  # quaternions left unnormalised on purpose
    return q


@pytest.mark.parametrize("robot", ROBOTS)
def test_poses_match_mujoco_kinematics(robot):
    model = mujoco.MjModel.from_xml_path(asset(robot))
    data = mujoco.MjData(model)
    rm = dr.RobotModel.from_mjcf(asset(robot), dtype=F64)
    q = _random_qpos(model, 6, seed=hash(robot) % 1000)
    geom, link = rm.geom_poses(q), rm.link_poses(q)
    assert geom.shape == (6, model.ngeom, 4, 4) and link.shape == (6, model.nbody, 4, 4)
    for b in range(q.shape[0]):
        data.qpos[:] = q[b].numpy()
        mujoco.mj_kinematics(model, data)
        np.testing.assert_allclose(geom[b, :, :3, 3].numpy(), data.geom_xpos, atol=1e-10, rtol=0)
        np.testing.assert_allclose(geom[b, :, :3, :3].reshape(-1, 9).numpy(), data.geom_xmat, atol=1e-10, rtol=0)
        np.testing.assert_allclose(link[b, :, :3, 3].numpy(), data.xpos, atol=1e-10, rtol=0)
        np.testing.assert_allclose(link[b, :, :3, :3].reshape(-1, 9).numpy(), data.xmat, atol=1e-10, rtol=0)
    np.testing.assert_array_equal(geom[:, :, 3].numpy(), np.broadcast_to([0, 0, 0, 1.0], (6, model.ngeom, 4)))


@pytest.mark.parametrize("robot", ROBOTS)
def test_vertices_follow_geom_poses(robot):
    """World vertices are the geom-local primitive vertices moved by the geom pose; normals likewise."""
    model = mujoco.MjModel.from_xml_path(asset(robot))
    rm = dr.RobotModel.from_mjcf(asset(robot), dtype=F64, detail=0)
    q = _random_qpos(model, 3, seed=1)
    verts, normals = rm.world_vertices_and_normals(q)
    assert verts.shape == (3, rm.num_vertices, 3) and normals.shape == verts.shape
    assert rm.faces.shape == (rm.num_faces, 3) and rm.faces.dtype == torch.long
    assert int(rm.faces.min()) == 0 and int(rm.faces.max()) == rm.num_vertices - 1
    assert rm.colors.shape == (rm.num_vertices, 3) and 0 <= float(rm.colors.min()) <= float(rm.colors.max()) <= 1
    poses = rm.geom_poses(q)
    meshed = [g for g in range(model.ngeom) if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE]
    assert rm.mesh_names == [rm.geom_names[g] for g in meshed]
    for g, (start, stop) in zip(meshed, rm.vertex_ranges):
        local = torch.einsum("bji,bnj->bni", poses[:, g, :3, :3], verts[:, start:stop] - poses[:, g, None, :3, 3])
        # the local vertices are the same for every environment and lie on the primitive's surface
        assert torch.allclose(local, local[:1], atol=1e-12)
        size = model.geom_size[g]
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
            assert torch.allclose(local.norm(dim=-1), torch.full_like(local[..., 0], size[0]))
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            assert torch.allclose(local.abs().amax(1)[0], torch.tensor(size[:3], dtype=F64))
        np.testing.assert_allclose(rm.colors[start:stop].numpy(), np.broadcast_to(model.geom_rgba[g, :3],
                                                                                     (stop - start, 3)))
    assert torch.allclose(normals.norm(dim=-1), torch.ones_like(normals[..., 0]))


@pytest.mark.parametrize("robot", ["humanoid", "hopper"])
def test_fk_gradients_match_finite_differences(robot):
    """pk's analytic FK backward plus our free-base composition: gradcheck on the humanoid (free root,
    multi-joint bodies, joint anchors) and the hopper (slides with ref)."""
    model = mujoco.MjModel.from_xml_path(asset(robot))
    rm = dr.RobotModel.from_mjcf(asset(robot), dtype=F64, detail=0)
    q = _random_qpos(model, 2, seed=3).requires_grad_()
    torch.autograd.gradcheck(lambda x: rm.geom_poses(x)[..., :3, :], (q,), eps=1e-6, atol=1e-8, fast_mode=True)
    torch.autograd.gradcheck(lambda x: rm.world_vertices(x)[:, ::17], (q,), eps=1e-6, atol=1e-8, fast_mode=True)


@pytest.mark.parametrize("robot", ["ant", "hopper"])
def test_one_pose_gives_links_geoms_and_meshes_of_one_fk_pass(robot, monkeypatch):
    model = mujoco.MjModel.from_xml_path(asset(robot))
    rm = dr.RobotModel.from_mjcf(asset(robot), dtype=F64, detail=0)
    q = _random_qpos(model, 3, seed=5)
    links, geoms, (verts, normals) = rm.link_poses(q), rm.geom_poses(q), rm.world_vertices_and_normals(q)

    calls = []
    fk = dr.RobotModel.frame_poses
    monkeypatch.setattr(dr.RobotModel, "frame_poses", lambda self, x: calls.append(1) or fk(self, x))
    pose = rm.pose(q)
    assert isinstance(pose, dr.RobotPose) and pose.batch_size == 3
    assert torch.equal(pose.link_poses(), links) and torch.equal(pose.geom_poses(), geoms)
    pv, pn = pose.world_vertices_and_normals()
    assert torch.equal(pv, verts) and torch.equal(pn, normals)
    assert len(calls) == 1


def test_dtype_device_and_shape_checks():
    rm = dr.RobotModel.from_mjcf(asset("ant"))
    assert rm.dtype == torch.float32 and rm.world_vertices(rm.qpos0[None]).dtype == torch.float32
    with pytest.raises(ValueError, match="dtype"):
        rm.geom_poses(rm.qpos0[None].double())
    with pytest.raises(ValueError, match=r"shape \(B, 15\)"):
        rm.geom_poses(rm.qpos0)
    with pytest.raises(ValueError, match=r"shape \(B, 15\)"):
        rm.geom_poses(torch.zeros(2, 14))
    with pytest.raises(ValueError, match=r"shape \(B, 15\)"):
        rm.check_qpos(torch.zeros(2, 14))
    with pytest.raises(ValueError, match=r"torch\.Tensor"):
        rm.pose(rm.qpos0.tolist())
    rm.check_qpos(rm.qpos0[None])  # a valid qpos passes
    r64 = rm.to(dtype=F64)
    q = rm.qpos0[None].double()
    assert torch.allclose(r64.world_vertices(q).float(), rm.world_vertices(rm.qpos0[None]), atol=1e-6)


def test_extra_meshes_move_with_bodies():
    rm = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64)
    big = rm.with_extra_meshes(30, 100, seed=4)
    assert big.num_vertices > rm.num_vertices + 30 * 80 and len(big.mesh_names) == len(rm.mesh_names) + 30
    assert rm.num_vertices == rm.faces.max() + 1  # the original is untouched
    q0 = rm.qpos0[None].clone()
    q1 = q0.clone()
    q1[0, 7:] += 0.3  # joints only
    v0, v1 = big.world_vertices(q0), big.world_vertices(q1)
    # the robot's own vertices come first and are unchanged by the extra meshes
    assert torch.equal(v0[:, : rm.num_vertices], rm.world_vertices(q0))
    start = rm.num_vertices
    extra_moved = [(v1[0, a:b] - v0[0, a:b]).abs().max() > 1e-6 for a, b in big.vertex_ranges[len(rm.mesh_names):]]
    # ... exactly when the body it is attached to moved
    body_moved = (rm.link_poses(q1) - rm.link_poses(q0)).abs().amax((0, 2, 3)) > 1e-6
    attached = [rm.body_names.index(n.split(":")[1]) for n in big.mesh_names[len(rm.mesh_names):]]
    assert extra_moved == [bool(body_moved[b]) for b in attached] and any(extra_moved)
    # every extra mesh moves with the root
    q2 = q0.clone()
    q2[0, 0] += 1.0
    assert torch.allclose(big.world_vertices(q2)[0, start:, 0] - v0[0, start:, 0], torch.ones(1, dtype=F64))
    # same seed, same meshes; attached to moving bodies only
    assert torch.equal(rm.with_extra_meshes(30, 100, seed=4).world_vertices(q1), v1)
    assert set(n.split(":")[1] for n in big.mesh_names[len(rm.mesh_names):]) <= set(rm.moving_bodies)


def test_mjcf_errors_name_the_problem(tmp_path):
    with pytest.raises(dr.MJCFError, match=r"nonexistent\.xml"):
        dr.RobotModel.from_mjcf(tmp_path / "nonexistent.xml")
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><body><geom type='sphere'/></body></worldbody>")
    with pytest.raises(dr.MJCFError, match=r"bad\.xml"):
        dr.RobotModel.from_mjcf(bad)
    mesh = tmp_path / "mesh.xml"
    mesh.write_text("""<mujoco><asset><mesh name="tet" vertex="0 0 0 1 0 0 0 1 0 0 0 1"/></asset>
        <worldbody><body name="b"><joint type="hinge"/><geom name="blob" type="mesh" mesh="tet"/>
        </body></worldbody></mujoco>""")
    with pytest.raises(dr.MJCFError, match=r"geom 0 'blob'.*type 'mesh'"):
        dr.RobotModel.from_mjcf(mesh)
    # an invisible unsupported geom is fine (it is not drawn) and still has a pose
    mesh.write_text(mesh.read_text().replace('mesh="tet"', 'mesh="tet" rgba="1 1 1 0"'))
    rm = dr.RobotModel.from_mjcf(mesh)
    assert rm.num_faces == 0 and rm.geom_poses(torch.zeros(1, 1)).shape == (1, 1, 4, 4)
    ball = tmp_path / "ball.xml"
    ball.write_text("""<mujoco><worldbody><body name="b"><joint name="sock" type="ball"/>
        <geom type="sphere" size="0.1"/></body></worldbody></mujoco>""")
    with pytest.raises(dr.MJCFError, match=r"'sock'.*ball"):
        dr.RobotModel.from_mjcf(ball)


def test_supported_geom_types_and_static_bodies(tmp_path):
    """Ellipsoid and cylinder geoms, a jointless body attached to the world, a slide with ref, a joint
    with an anchor: all still match MuJoCo."""
    xml = tmp_path / "zoo.xml"
    xml.write_text("""<mujoco><worldbody>
        <geom type="plane" size="1 1 .1"/>
        <body name="post" pos="1 0 0.5" quat="0.9 0.1 0.3 0"><geom type="cylinder" size="0.05 0.5"/></body>
        <body name="a" pos="0 0 1"><joint name="s" type="slide" axis="0 1 1" ref="0.3"/>
          <joint name="h" type="hinge" pos="0.1 0.2 0" axis="1 1 0"/>
          <geom type="ellipsoid" size="0.1 0.2 0.3" pos="0.2 0 0" quat="0.5 0.5 0.5 0.5"/>
          <body name="c" pos="0 0 -0.4"><geom type="box" size="0.1 0.1 0.1"/></body></body>
        </worldbody></mujoco>""")
    model = mujoco.MjModel.from_xml_path(str(xml))
    data = mujoco.MjData(model)
    rm = dr.RobotModel.from_mjcf(xml, dtype=F64)
    q = torch.tensor([[0.7, -1.1]], dtype=F64)
    data.qpos[:] = q[0].numpy()
    mujoco.mj_kinematics(model, data)
    np.testing.assert_allclose(rm.geom_poses(q)[0, :, :3, 3].numpy(), data.geom_xpos, atol=1e-12)
    np.testing.assert_allclose(rm.geom_poses(q)[0, :, :3, :3].reshape(-1, 9).numpy(), data.geom_xmat, atol=1e-12)
    assert rm.moving_bodies == ["a", "c"]
