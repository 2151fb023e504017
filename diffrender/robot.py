"""Robot model: compiled MuJoCo model -> pytorch-kinematics chain -> posed triangle meshes.

Why not pytorch-kinematics' own MJCF parser: with mujoco 4 it fails to load, and even where it loads it drops
free/ball joints, rejects bodies with several joints, places joints with a non-zero ``pos`` about the wrong
point and ignores ``ref``. We therefore read the *compiled* ``mujoco.MjModel`` (defaults, ``fromto``, body and
geom frames already resolved) and build pk ``Frame``/``Link``/``Joint`` objects ourselves:

* one pk frame per hinge/slide joint; a body with several joints becomes a chain of nested frames, in
  MuJoCo's joint order;
* MuJoCo rotates a hinge about its anchor ``p`` (``jnt_pos``, body frame): the body frame becomes
  ``T(p) R(q) T(-p)``. pk composes ``link_offset @ joint_offset @ J(q)``, so a joint frame gets
  ``joint_offset = T(p)`` and the ``T(-p)`` goes into whatever hangs below it (the next joint's link offset,
  the body's constant offset);
* ``ref`` (``qpos0``): pk gets ``qpos - qpos0`` for hinge/slide joints, as ``mj_kinematics`` uses;
* a free joint (top-level bodies only, as MuJoCo requires) is not a pk joint: its subtree is computed
  relative to the free body and left-multiplied by ``T(qpos[:3]) R(normalize(qpos[3:7]))`` (w, x, y, z);
* bodies without joints add no frame: they are a constant offset from their parent's frame.

Geoms are read from ``MjModel`` (``geom_type/size/pos/quat/bodyid/rgba``) and meshed with
:mod:`diffrender.meshes`. Plane geoms are not meshed (the renderer draws the floor analytically), nor are
geoms with ``rgba`` alpha 0 (invisible in MuJoCo's viewer); both still appear in :meth:`geom_poses`.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import pytorch_kinematics as pk
import torch
from pytorch_kinematics.transforms import Transform3d

from . import meshes as _meshes

__all__ = ["MJCFError", "RobotModel", "RobotPose"]


class MJCFError(ValueError):
    """An MJCF file that does not compile, or that uses something diffrender does not support."""


_GEOM_NAMES = {int(v): k.removeprefix("mjGEOM_").lower() for k, v in mujoco.mjtGeom.__members__.items()}


@dataclass(frozen=True)
class _Item:
    """One rigid triangle mesh attached to a kinematic frame (a visible geom or an extra mesh)."""

    name: str
    frame: int  # pk frame index the mesh moves with
    offset: np.ndarray  # (4, 4) float64, frame -> mesh local
    mesh: _meshes.LocalMesh
    rgb: tuple[float, float, float]


def _quat_to_mat_np(q) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, dtype=np.float64))
    return m.reshape(3, 3)


def _pose_np(pos, quat) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = _quat_to_mat_np(quat)
    t[:3, 3] = pos
    return t


def _translation_np(p) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = p
    return t


def _quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternion (w, x, y, z), any norm -> (..., 3, 3) rotation of the normalised quaternion."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def _name(model: mujoco.MjModel, obj: str, i: int) -> str:
    n = mujoco.mj_id2name(model, getattr(mujoco.mjtObj, f"mjOBJ_{obj.upper()}"), i)
    return n if n else f"{obj}{i}"


def _mesh_for_geom(model: mujoco.MjModel, g: int, detail: int, path: str) -> _meshes.LocalMesh:
    t = int(model.geom_type[g])
    size = np.asarray(model.geom_size[g], dtype=np.float64)
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return _meshes.sphere_mesh(size[0], detail=detail)
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return _meshes.capsule_mesh(size[0], size[1], detail=detail)
    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return _meshes.cylinder_mesh(size[0], size[1], detail=detail)
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        return _meshes.box_mesh(size)
    if t == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return _meshes.ellipsoid_mesh(size, detail=detail)
    body = _name(model, "body", int(model.geom_bodyid[g]))
    raise MJCFError(
        f"{path}: geom {g} '{_name(model, 'geom', g)}' (body '{body}') has type "
        f"'{_GEOM_NAMES.get(t, t)}', which diffrender cannot mesh; supported visible geom types are "
        "sphere, capsule, cylinder, box, ellipsoid (planes are drawn as the analytic floor). Make the geom "
        "invisible (rgba alpha 0) or replace it with primitives."
    )


class RobotModel:
    """Differentiable forward kinematics and posed meshes of a MuJoCo robot.

    Build with :meth:`from_mjcf` (or :meth:`from_mjmodel`). All methods take ``qpos: (B, nq)`` in MuJoCo's
    layout, in the model's dtype and on its device, and are differentiable in ``qpos`` (pk's analytic
    Jacobian backward for the chain, plain autograd for the free base and the mesh transforms).

    Attributes:
        nq: number of generalised coordinates.
        qpos0: (nq,) MuJoCo's reference configuration ``qpos0``.
        faces: (F, 3) long, indices into the vertices of :meth:`world_vertices`.
        colors: (V, 3) in [0, 1], per-vertex albedo from the geom ``rgba``.
        num_vertices, num_faces: V and F.
        body_names, geom_names, joint_names: MuJoCo names in model order (``body3`` etc. where unnamed).
        mesh_names: one name per meshed item (visible geoms, then extra meshes).
        vertex_ranges: per meshed item, ``(start, stop)`` of its vertices in the vertex arrays.
    """

    def __init__(self) -> None:  # use from_mjcf / from_mjmodel
        raise TypeError("use RobotModel.from_mjcf(path) or RobotModel.from_mjmodel(model)")

    # ------------------------------------------------------------------------------------------ building
    @classmethod
    def from_mjcf(
        cls,
        path: str | os.PathLike,
        *,
        detail: int = 1,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
    ) -> RobotModel:
        """Compile the MJCF at ``path`` with MuJoCo and build the model.

        Args:
            path: MJCF file.
            detail: tessellation level 0-3 (vertex/face counts per primitive in :mod:`diffrender.meshes`).
            dtype: float32 or float64 for all tensors.
            device: where all tensors live.

        Raises:
            MJCFError: the file does not exist or does not compile (the message names the file), or the
                model uses ball joints, nested free joints or visible geoms that cannot be meshed.
        """
        path = os.fspath(path)
        try:
            model = mujoco.MjModel.from_xml_path(path)
        except Exception as err:  # mujoco raises ValueError with the compiler's message
            raise MJCFError(f"could not compile MJCF file '{path}': {err}") from err
        return cls.from_mjmodel(model, detail=detail, dtype=dtype, device=device, source=path)

    @classmethod
    def from_mjmodel(
        cls,
        model: mujoco.MjModel,
        *,
        detail: int = 1,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
        source: str = "<MjModel>",
    ) -> RobotModel:
        """Build from an already compiled ``mujoco.MjModel`` (see :meth:`from_mjcf`)."""
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self = object.__new__(cls)
        self.source = source
        self.detail = detail
        self.nq = int(model.nq)
        self.nbody = int(model.nbody)
        self.ngeom = int(model.ngeom)
        self.body_names = [_name(model, "body", i) for i in range(model.nbody)]
        self.geom_names = [_name(model, "geom", i) for i in range(model.ngeom)]
        self.joint_names = [_name(model, "joint", i) for i in range(model.njnt)]
        self._qpos0_np = np.array(model.qpos0, dtype=np.float64)

        # ---- kinematic tree: pk frames for hinge/slide joints, constant offsets for everything else
        root = pk.Frame(name="world", link=pk.Link(name="world"), joint=pk.Joint(name="world_fixed",
                                                                                  dtype=torch.float64))
        frames = [root]
        frame_base = [0]  # per frame: 0 = world, k > 0 = k-th free joint's base transform
        free_qadr: list[int] = []
        pk_joint_qadr: dict[str, int] = {}
        body_frame = np.zeros(model.nbody, dtype=np.int64)
        body_offset = np.tile(np.eye(4), (model.nbody, 1, 1))

        def add_frame(parent: int, name: str, link_offset: np.ndarray, joint: pk.Joint, base: int) -> int:
            f = pk.Frame(name=name, link=pk.Link(name=name, offset=Transform3d(
                matrix=torch.as_tensor(link_offset, dtype=torch.float64), dtype=torch.float64)), joint=joint)
            frames[parent].add_child(f)
            frames.append(f)
            frame_base.append(base)
            return len(frames) - 1

        for b in range(1, model.nbody):
            parent = int(model.body_parentid[b])
            pframe, poff = int(body_frame[parent]), body_offset[parent]
            local = _pose_np(model.body_pos[b], model.body_quat[b])
            jnt_ids = range(int(model.body_jntadr[b]), int(model.body_jntadr[b]) + int(model.body_jntnum[b]))
            types = [int(model.jnt_type[j]) for j in jnt_ids]
            if mujoco.mjtJoint.mjJNT_BALL in types:
                j = jnt_ids[types.index(mujoco.mjtJoint.mjJNT_BALL)]
                raise MJCFError(f"{source}: joint {j} '{self.joint_names[j]}' (body '{self.body_names[b]}') "
                                "is a ball joint; diffrender supports free, hinge and slide joints")
            if mujoco.mjtJoint.mjJNT_FREE in types:
                if parent != 0 or len(types) != 1:
                    raise MJCFError(f"{source}: body '{self.body_names[b]}' has a free joint below another "
                                    "body or together with other joints; only top-level free bodies are "
                                    "supported (as in MuJoCo)")
                free_qadr.append(int(model.jnt_qposadr[jnt_ids[0]]))
                # mj_kinematics ignores body_pos/quat of a free body: its pose is qpos itself
                f = add_frame(0, f"free:{self.body_names[b]}", np.eye(4),
                              pk.Joint(name=f"free:{self.body_names[b]}_fixed", dtype=torch.float64),
                              len(free_qadr))
                body_frame[b], body_offset[b] = f, np.eye(4)
                continue
            pre = poff @ local
            frame = pframe
            for j in jnt_ids:
                p = np.asarray(model.jnt_pos[j], dtype=np.float64)
                jname = f"jnt{j}:{self.joint_names[j]}"
                joint = pk.Joint(
                    name=jname,
                    offset=Transform3d(matrix=torch.as_tensor(_translation_np(p)), dtype=torch.float64),
                    joint_type="revolute" if int(model.jnt_type[j]) == mujoco.mjtJoint.mjJNT_HINGE
                    else "prismatic",
                    axis=torch.as_tensor(np.asarray(model.jnt_axis[j], dtype=np.float64)),
                    dtype=torch.float64,
                )
                frame = add_frame(frame, f"{self.body_names[b]}/{jname}", pre, joint, frame_base[frame])
                pk_joint_qadr[jname] = int(model.jnt_qposadr[j])
                pre = _translation_np(-p)
            body_frame[b], body_offset[b] = frame, pre

        chain = pk.Chain(root, dtype=torch.float64)
        # pk numbers frames breadth-first; map our creation order onto its indices
        pk_index = np.array([chain.frame_to_idx[f.name] for f in frames], dtype=np.int64)
        self._pk_of_frame = pk_index
        joint_order = chain.get_joint_parameter_names()
        self._chain64 = chain if joint_order else None  # float64 CPU master copy; _finalize converts
        self._num_frames = len(frames)
        self._theta_qadr_np = np.array([pk_joint_qadr[n] for n in joint_order], dtype=np.int64)
        self._free_qadr_np = np.array(free_qadr, dtype=np.int64)
        # reorder per-frame data into pk's frame order so FK output can be indexed directly
        base_pk = np.zeros(len(frames), dtype=np.int64)
        base_pk[pk_index] = frame_base
        self._frame_base_np = base_pk
        self._body_frame_np = pk_index[body_frame]
        self._body_offset_np = body_offset

        # ---- geoms: constant offset from their body's frame
        geom_offset = np.stack([
            body_offset[int(model.geom_bodyid[g])] @ _pose_np(model.geom_pos[g], model.geom_quat[g])
            for g in range(model.ngeom)
        ]) if model.ngeom else np.zeros((0, 4, 4))
        self._geom_frame_np = self._body_frame_np[np.asarray(model.geom_bodyid, dtype=np.int64)]
        self._geom_offset_np = geom_offset

        items = []
        for g in range(model.ngeom):
            if int(model.geom_type[g]) == mujoco.mjtGeom.mjGEOM_PLANE or float(model.geom_rgba[g, 3]) == 0.0:
                continue
            mesh = _mesh_for_geom(model, g, detail, source)
            rgb = tuple(float(c) for c in np.clip(model.geom_rgba[g, :3], 0.0, 1.0))
            items.append(_Item(self.geom_names[g], int(self._geom_frame_np[g]), geom_offset[g], mesh, rgb))
        self._items = items
        self._moving_bodies = [b for b in range(1, model.nbody) if self._body_frame_np[b] != pk_index[0]]
        self._finalize(dtype, device)
        return self

    def with_extra_meshes(self, num_meshes: int, verts_per_mesh: int, *, seed: int = 0,
                          radius: float = 0.03) -> RobotModel:
        """A copy with ``num_meshes`` extra closed spheres of about ``verts_per_mesh`` vertices each, rigidly
        attached round-robin to the bodies that move with ``qpos``, at seeded random offsets within 5 cm of
        the body origin, so their vertices depend on ``qpos``. For scene-complexity (memory) sweeps.

        Vertex/face counts per sphere: see :func:`diffrender.meshes.latlong_sphere_mesh`. The extra meshes
        appear in vertices/faces/colors (after the geoms), not in :meth:`geom_poses`.
        """
        if num_meshes < 0:
            raise ValueError(f"num_meshes must be >= 0, got {num_meshes}")
        if num_meshes and not self._moving_bodies:
            raise ValueError("with_extra_meshes: the model has no body that moves with qpos")
        rng = np.random.default_rng(seed)
        mesh = _meshes.latlong_sphere_mesh(radius, verts_per_mesh) if num_meshes else None
        extra = []
        for i in range(num_meshes):
            b = self._moving_bodies[i % len(self._moving_bodies)]
            off = self._body_offset_np[b] @ _translation_np(rng.uniform(-0.05, 0.05, size=3))
            rgb = tuple(float(c) for c in rng.uniform(0.2, 0.9, size=3))
            extra.append(_Item(f"extra{i}:{self.body_names[b]}", int(self._body_frame_np[b]), off, mesh, rgb))
        new = copy.copy(self)
        new._items = list(self._items) + extra
        new._finalize(self.dtype, self.device)
        return new

    def to(self, *, dtype: torch.dtype | None = None, device: str | torch.device | None = None) -> RobotModel:
        """A copy with all tensors in ``dtype`` on ``device``."""
        new = copy.copy(self)
        new._finalize(dtype or self.dtype, device if device is not None else self.device)
        return new

    def _finalize(self, dtype: torch.dtype, device) -> None:
        """(Re)create every tensor from the float64 numpy description."""
        self.dtype = dtype
        self.device = torch.device(device)
        if self.device.type == "cuda" and self.device.index is None:  # 'cuda' and 'cuda:0' must compare equal
            self.device = torch.device("cuda", torch.cuda.current_device())
        kw = dict(dtype=dtype, device=self.device)
        self._chain = None
        if self._chain64 is not None:
            self._chain = copy.deepcopy(self._chain64).to(dtype=dtype, device=self.device)
        self.qpos0 = torch.as_tensor(self._qpos0_np, **kw)
        self._theta_qadr = torch.as_tensor(self._theta_qadr_np, device=self.device)
        self._theta_qpos0 = self.qpos0[self._theta_qadr]
        self._free_qadr = torch.as_tensor(self._free_qadr_np, device=self.device)
        self._frame_base = torch.as_tensor(self._frame_base_np, device=self.device)
        self._body_frame = torch.as_tensor(self._body_frame_np, device=self.device)
        self._body_offset = torch.as_tensor(self._body_offset_np, **kw)
        self._geom_frame = torch.as_tensor(self._geom_frame_np, device=self.device)
        self._geom_offset = torch.as_tensor(self._geom_offset_np, **kw)
        # the root frame's static pose (identity here, but kept general) for models without pk joints
        self._identity = torch.eye(4, **kw)

        # Vertex layout: items in order (geoms in MjModel order, then extra meshes), transformed in runs of
        # consecutive items with equal vertex counts, each run one einsum of (B, G_k, 3, 3) frame rotations
        # with (G_k, n_k, 3) local blocks (no per-vertex gather). Local blocks are pre-transformed into their
        # frame's coordinates (item offset baked in).
        runs: list[tuple[int, list[int]]] = []
        for i, it in enumerate(self._items):
            if runs and runs[-1][0] == it.mesh.num_vertices:
                runs[-1][1].append(i)
            else:
                runs.append((it.mesh.num_vertices, [i]))
        self._groups = []
        faces, colors, names = [], [], []
        ranges: list[tuple[int, int]] = [(0, 0)] * len(self._items)
        start = 0
        for n, idx in runs:
            local_v, local_n = [], []
            for i in idx:
                it = self._items[i]
                r, t = it.offset[:3, :3], it.offset[:3, 3]
                local_v.append(it.mesh.vertices @ r.T + t)
                local_n.append(it.mesh.normals @ r.T)
                faces.append(it.mesh.faces + start)
                colors.append(np.broadcast_to(np.asarray(it.rgb), (n, 3)))
                ranges[i] = (start, start + n)
                start += n
            frames = torch.as_tensor([self._items[i].frame for i in idx], device=self.device)
            self._groups.append((frames, torch.as_tensor(np.stack(local_v), **kw),
                                 torch.as_tensor(np.stack(local_n), **kw)))
        names = [it.name for it in self._items]
        self.mesh_names = names
        self.vertex_ranges = ranges
        self.faces = torch.as_tensor(np.concatenate(faces) if faces else np.zeros((0, 3), np.int64),
                                     dtype=torch.long, device=self.device)
        self.colors = torch.as_tensor(np.concatenate(colors) if colors else np.zeros((0, 3)), **kw)
        self.num_vertices = int(start)
        self.num_faces = int(self.faces.shape[0])

    # ------------------------------------------------------------------------------------------ kinematics
    def check_qpos(self, qpos: torch.Tensor) -> None:
        """Raise ``ValueError`` naming what is wrong unless ``qpos`` is a (B, nq) tensor in the model's dtype
        on its device. Every method that takes ``qpos`` calls it; callers that compile their own code around
        the model call it first to get the clear error before any compiled work."""
        if not isinstance(qpos, torch.Tensor):
            raise ValueError(f"qpos must be a torch.Tensor of shape (B, {self.nq}), got {type(qpos).__name__}")
        if qpos.ndim != 2 or qpos.shape[1] != self.nq:
            raise ValueError(f"qpos must have shape (B, {self.nq}), got {tuple(qpos.shape)}")
        if qpos.dtype != self.dtype:
            raise ValueError(f"qpos has dtype {qpos.dtype} but the model is {self.dtype}; "
                             "convert one of them (RobotModel.to(dtype=...))")
        if qpos.device != self.device:
            raise ValueError(f"qpos is on {qpos.device} but the model is on {self.device}")

    def frame_poses(self, qpos: torch.Tensor) -> torch.Tensor:
        """Forward kinematics: world poses of the kinematic frames (pk's frame order).

        Args:
            qpos: (B, nq).
        Returns:
            (B, num_frames, 4, 4) homogeneous transforms frame -> world [m].
        """
        self.check_qpos(qpos)
        b = qpos.shape[0]
        if self._chain is not None:
            theta = qpos[:, self._theta_qadr] - self._theta_qpos0
            fk = self._chain.forward_kinematics_tensor(theta).transpose(0, 1)  # (B, NF, 4, 4)
        else:
            fk = self._identity.expand(b, self._num_frames, 4, 4)
        if self._free_qadr.numel() == 0:
            return fk
        # free bases: (B, K + 1, 4, 4), index 0 is the identity (frames not under a free body)
        q = qpos[:, self._free_qadr[:, None] + torch.arange(7, device=qpos.device)]  # (B, K, 7)
        top = torch.cat([_quat_to_mat(q[..., 3:]), q[..., :3, None]], dim=-1)  # (B, K, 3, 4)
        bottom = self._identity[3:].expand(b, q.shape[1], 1, 4)
        base = torch.cat([self._identity.expand(b, 1, 4, 4), torch.cat([top, bottom], dim=-2)], dim=1)
        return base[:, self._frame_base] @ fk

    def pose(self, qpos: torch.Tensor) -> RobotPose:
        """One forward-kinematics pass at ``qpos: (B, nq)``, from which link poses, geom poses and the posed
        meshes are all read (a renderer that needs both the meshes and a camera anchored to a link runs FK
        once per frame this way)."""
        return RobotPose(model=self, frames=self.frame_poses(qpos))

    def link_poses(self, qpos: torch.Tensor) -> torch.Tensor:
        """Body frames in the world, equal to MuJoCo's ``xpos``/``xmat`` after ``mj_kinematics``.

        Args:
            qpos: (B, nq).
        Returns:
            (B, nbody, 4, 4) homogeneous transforms body -> world [m], MuJoCo body order (world first).
        """
        return self.pose(qpos).link_poses()

    def geom_poses(self, qpos: torch.Tensor) -> torch.Tensor:
        """All geoms (planes and world geoms included) in MjModel order, equal to ``geom_xpos``/``geom_xmat``.

        Args:
            qpos: (B, nq).
        Returns:
            (B, ngeom, 4, 4) homogeneous transforms geom -> world [m].
        """
        return self.pose(qpos).geom_poses()

    def world_vertices_and_normals(self, qpos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed mesh vertices and unit normals, sharing one forward-kinematics pass.

        Args:
            qpos: (B, nq).
        Returns:
            verts: (B, V, 3) [m] world frame; normals: (B, V, 3) unit, world frame.
        """
        return self.pose(qpos).world_vertices_and_normals()

    def world_vertices(self, qpos: torch.Tensor) -> torch.Tensor:
        """Posed mesh vertices: (B, V, 3) [m], world frame, indexed by :attr:`faces`."""
        return self.world_vertices_and_normals(qpos)[0]

    def world_normals(self, qpos: torch.Tensor) -> torch.Tensor:
        """Exact (analytic, not mesh-averaged) unit vertex normals: (B, V, 3), world frame."""
        return self.world_vertices_and_normals(qpos)[1]

    def __repr__(self) -> str:
        return (f"RobotModel('{self.source}', nq={self.nq}, nbody={self.nbody}, ngeom={self.ngeom}, "
                f"meshes={len(self._items)}, V={self.num_vertices}, F={self.num_faces}, detail={self.detail}, "
                f"dtype={self.dtype}, device={self.device})")

    @property
    def moving_bodies(self) -> Sequence[str]:
        """Names of the bodies whose pose depends on ``qpos``."""
        return [self.body_names[b] for b in self._moving_bodies]


@dataclass(frozen=True, eq=False)
class RobotPose:
    """A robot at one batch of configurations: the kinematic frames of one forward-kinematics pass
    (:meth:`RobotModel.pose`), and everything posed that is read off them without running FK again.

    Attributes:
        model: the :class:`RobotModel` the frames belong to.
        frames: (B, num_frames, 4, 4) homogeneous transforms frame -> world [m] (pk's frame order), in the
            autograd graph of the ``qpos`` they were computed from.
    """

    model: RobotModel
    frames: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.frames.shape[0])

    def link_poses(self) -> torch.Tensor:
        """(B, nbody, 4, 4) body -> world [m], MuJoCo body order (see :meth:`RobotModel.link_poses`)."""
        m = self.model
        return self.frames[:, m._body_frame] @ m._body_offset

    def geom_poses(self) -> torch.Tensor:
        """(B, ngeom, 4, 4) geom -> world [m], MjModel order (see :meth:`RobotModel.geom_poses`)."""
        m = self.model
        return self.frames[:, m._geom_frame] @ m._geom_offset

    def world_vertices_and_normals(self) -> tuple[torch.Tensor, torch.Tensor]:
        """verts: (B, V, 3) [m] and unit normals: (B, V, 3), world frame, indexed by ``model.faces``."""
        vs, ns = [], []
        for frames, local_v, local_n in self.model._groups:
            pose = self.frames[:, frames]  # (B, G_k, 4, 4)
            rot, trans = pose[..., :3, :3], pose[..., :3, 3]
            vs.append((torch.einsum("bgij,gnj->bgni", rot, local_v) + trans[:, :, None]).flatten(1, 2))
            ns.append(torch.einsum("bgij,gnj->bgni", rot, local_n).flatten(1, 2))
        if not vs:
            empty = self.frames.new_zeros(self.batch_size, 0, 3)
            return empty, empty
        return torch.cat(vs, dim=1), torch.cat(ns, dim=1)
