"""Articulated-body model read from a compiled ``mujoco.MjModel``.

MuJoCo is used only as the MJCF compiler: defaults, ``fromto``, inertias from geoms and the joint/dof layout
are resolved by it, and this module copies the result into plain numpy arrays (float64) plus the constant
index and mask arrays the vectorised dynamics in :mod:`tasks.dynamics` needs. Nothing here depends on torch;
:class:`tasks.dynamics.Simulator` moves the arrays to a device and dtype.

Conventions are MuJoCo's: bodies are numbered as in ``MjModel`` minus the world body (``b = body_id - 1``),
joints keep MuJoCo's order, ``qpos``/``qvel`` keep MuJoCo's layout (free joint: position, quaternion w,x,y,z;
linear velocity in the world frame, angular velocity in the body frame).

Supported joints: ``free`` (only on bodies whose parent is the world, and alone on their body), ``hinge`` and
``slide`` (several per body, anchors at ``jnt_pos``). ``ball`` joints raise :class:`UnsupportedModelError`.
Supported contact geoms (dflex's point contacts against the ground plane): sphere (its centre, distance =
radius), capsule (its two end-cap centres, distance = radius) and box (its 8 corners, distance 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

__all__ = ["ArticulatedModel", "UnsupportedModelError", "load_model"]

_JOINT_NAMES = {0: "free", 1: "ball", 2: "slide", 3: "hinge"}


class UnsupportedModelError(ValueError):
    """The MJCF uses a feature the simulator does not implement (the message names the element)."""


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z). (4,) -> (3, 3)."""
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(q, dtype=np.float64))
    return out.reshape(3, 3)


def _name(m: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, obj, i) or f"<unnamed {i}>"


@dataclass(frozen=True)
class ArticulatedModel:
    """Everything the simulator needs, as numpy arrays. Shapes use ``nb`` bodies (world excluded), ``nh``
    hinge/slide joints, ``nf`` free joints, ``nv`` dofs, ``nc`` contact points, ``nu`` actuators.

    Kinematic tree (bodies):
      body_parent (nb,) int: parent body index, -1 for the world.
      body_pos (nb, 3) [m], body_rot (nb, 3, 3): body frame in the parent frame (MuJoCo body_pos/body_quat).
      body_free (nb,) int: index of the body's free joint or -1.
      body_slots (nb, K) int: the body's hinge/slide joints in order, padded with ``nh`` (identity).
    Inertia: body_mass (nb,) [kg], body_ipos (nb, 3) [m] (centre of mass in the body frame),
      body_inertia (nb, 3, 3) [kg m^2] (rotational inertia about the centre of mass, body frame).
    Hinge/slide joints (index h):
      hs_hinge (nh,) bool, hs_axis (nh, 3) unit axis and hs_anchor (nh, 3) [m] in the frame before the joint,
      hs_body, hs_slot, hs_qadr, hs_dof (nh,) int, hs_qpos0 (nh,) (MuJoCo's qpos0: the angle is qpos - qpos0),
      hs_stiffness (nh,) [N m/rad or N/m], hs_springref (nh,) (MuJoCo's qpos_spring),
      hs_limited (nh,) bool, hs_range (nh, 2).
    Free joints (index f): free_body, free_qadr, free_dof (nf,) int.
    Dofs: dof_body (nv,), dof_armature (nv,), dof_damping (nv,).
    Masks (0/1 float64):
      body_dof_anc (nb, nv): dof d moves body b (d's body is b or an ancestor of b).
      dof_anc (nv, nv): [i, j] = 1 if dof i is an ancestor of dof j or i == j (MuJoCo's dof_parentid tree).
      dof_vel (nv, nv): [j, i] = 1 if dof i contributes to the velocity of the frame that carries dof j's
        motion axis (used for the axis' time derivative): ancestors-or-self of j, except that the three
        rotational dofs of a free joint see only the dofs before that joint's rotation.
      body_desc (nb, nb): [a, b] = 1 if b is a or a descendant of a.
    Contact points: contact_body (nc,), contact_pos (nc, 3) [m] in the body frame, contact_dist (nc,) [m].
    Actuators: act_dof (nu,), act_gear (nu,).
    """

    path: str
    name: str
    nq: int
    nv: int
    nb: int
    gravity: np.ndarray
    ground_height: float | None
    body_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    body_parent: np.ndarray
    body_pos: np.ndarray
    body_rot: np.ndarray
    body_free: np.ndarray
    body_slots: np.ndarray
    body_mass: np.ndarray
    body_ipos: np.ndarray
    body_inertia: np.ndarray
    hs_names: tuple[str, ...]
    hs_hinge: np.ndarray
    hs_axis: np.ndarray
    hs_anchor: np.ndarray
    hs_body: np.ndarray
    hs_slot: np.ndarray
    hs_qadr: np.ndarray
    hs_dof: np.ndarray
    hs_qpos0: np.ndarray
    hs_stiffness: np.ndarray
    hs_springref: np.ndarray
    hs_limited: np.ndarray
    hs_range: np.ndarray
    free_body: np.ndarray
    free_qadr: np.ndarray
    free_dof: np.ndarray
    dof_body: np.ndarray
    dof_armature: np.ndarray
    dof_damping: np.ndarray
    body_dof_anc: np.ndarray
    dof_anc: np.ndarray
    dof_vel: np.ndarray
    body_desc: np.ndarray
    contact_body: np.ndarray
    contact_pos: np.ndarray
    contact_dist: np.ndarray
    act_names: tuple[str, ...]
    act_dof: np.ndarray
    act_gear: np.ndarray
    qpos0: np.ndarray

    @property
    def nh(self) -> int:
        return len(self.hs_names)

    @property
    def nf(self) -> int:
        return len(self.free_body)

    @property
    def nc(self) -> int:
        return len(self.contact_body)

    @property
    def nu(self) -> int:
        return len(self.act_dof)


def load_model(path: str | Path) -> ArticulatedModel:
    """Compile ``path`` with MuJoCo and return the simulator's :class:`ArticulatedModel`."""
    path = str(path)
    m = mujoco.MjModel.from_xml_path(path)
    return from_mjmodel(m, path=path)


def from_mjmodel(m: mujoco.MjModel, *, path: str = "") -> ArticulatedModel:
    """Build an :class:`ArticulatedModel` from a compiled ``MjModel`` (see the module docstring)."""
    nb = m.nbody - 1
    nv = m.nv
    body_names = tuple(_name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, m.nbody))
    joint_names = tuple(_name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt))

    # --- joints: check support, split into free and hinge/slide -----------------------------------------
    hs_ids, free_ids = [], []
    for j in range(m.njnt):
        jt = int(m.jnt_type[j])
        b = int(m.jnt_bodyid[j])
        where = f"joint '{joint_names[j]}' (body '{_name(m, mujoco.mjtObj.mjOBJ_BODY, b)}')"
        if jt == mujoco.mjtJoint.mjJNT_BALL:
            raise UnsupportedModelError(
                f"{where} is a ball joint; tasks supports free, hinge and slide joints only ({path})"
            )
        if jt == mujoco.mjtJoint.mjJNT_FREE:
            if m.body_parentid[b] != 0:
                raise UnsupportedModelError(f"{where}: a free joint must be on a child of the world ({path})")
            if m.body_jntnum[b] != 1:
                raise UnsupportedModelError(f"{where}: a free joint must be the only joint of its body ({path})")
            if m.jnt_stiffness[j] != 0:
                raise UnsupportedModelError(f"{where}: free-joint stiffness is not supported ({path})")
            free_ids.append(j)
        elif jt in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            hs_ids.append(j)
        else:  # pragma: no cover - MuJoCo has no other joint types today
            raise UnsupportedModelError(f"{where} has unknown joint type {jt} ({path})")
    nh = len(hs_ids)
    hs_index = {j: h for h, j in enumerate(hs_ids)}

    # --- bodies --------------------------------------------------------------------------------------------
    body_parent = np.asarray(m.body_parentid[1:], dtype=np.int64) - 1
    body_pos = np.array(m.body_pos[1:], dtype=np.float64)
    body_rot = np.stack([_quat_to_mat(m.body_quat[i]) for i in range(1, m.nbody)]) if nb else np.zeros((0, 3, 3))
    body_free = -np.ones(nb, dtype=np.int64)
    for f, j in enumerate(free_ids):
        body_free[m.jnt_bodyid[j] - 1] = f
    n_slots = max([int(m.body_jntnum[i]) for i in range(1, m.nbody) if body_free[i - 1] < 0] + [1])
    body_slots = np.full((nb, n_slots), nh, dtype=np.int64)
    hs_slot = np.zeros(nh, dtype=np.int64)
    for i in range(1, m.nbody):
        if body_free[i - 1] >= 0:
            continue
        for k in range(int(m.body_jntnum[i])):
            j = int(m.body_jntadr[i]) + k
            body_slots[i - 1, k] = hs_index[j]
            hs_slot[hs_index[j]] = k

    body_mass = np.array(m.body_mass[1:], dtype=np.float64)
    body_ipos = np.array(m.body_ipos[1:], dtype=np.float64)
    body_inertia = np.zeros((nb, 3, 3))
    for b in range(nb):
        r = _quat_to_mat(m.body_iquat[b + 1])
        body_inertia[b] = r @ np.diag(m.body_inertia[b + 1]) @ r.T

    # --- hinge/slide joints -----------------------------------------------------------------------------------
    hs_hinge = np.array([m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE for j in hs_ids], dtype=bool)
    hs_axis = np.array([m.jnt_axis[j] for j in hs_ids], dtype=np.float64).reshape(nh, 3)
    hs_axis = hs_axis / np.linalg.norm(hs_axis, axis=1, keepdims=True).clip(1e-12)
    hs_anchor = np.array([m.jnt_pos[j] for j in hs_ids], dtype=np.float64).reshape(nh, 3)
    hs_body = np.array([m.jnt_bodyid[j] - 1 for j in hs_ids], dtype=np.int64)
    hs_qadr = np.array([m.jnt_qposadr[j] for j in hs_ids], dtype=np.int64)
    hs_dof = np.array([m.jnt_dofadr[j] for j in hs_ids], dtype=np.int64)
    hs_qpos0 = np.array(m.qpos0[hs_qadr], dtype=np.float64)
    hs_stiffness = np.array([m.jnt_stiffness[j] for j in hs_ids], dtype=np.float64)
    hs_springref = np.array(m.qpos_spring[hs_qadr], dtype=np.float64)
    hs_limited = np.array([bool(m.jnt_limited[j]) for j in hs_ids], dtype=bool)
    hs_range = np.array([m.jnt_range[j] for j in hs_ids], dtype=np.float64).reshape(nh, 2)

    free_body = np.array([m.jnt_bodyid[j] - 1 for j in free_ids], dtype=np.int64)
    free_qadr = np.array([m.jnt_qposadr[j] for j in free_ids], dtype=np.int64)
    free_dof = np.array([m.jnt_dofadr[j] for j in free_ids], dtype=np.int64)

    # --- dofs and masks ---------------------------------------------------------------------------------------
    dof_body = np.asarray(m.dof_bodyid, dtype=np.int64) - 1
    dof_parent = np.asarray(m.dof_parentid, dtype=np.int64)
    dof_anc = np.zeros((nv, nv))
    for j in range(nv):
        i = j
        while i >= 0:
            dof_anc[i, j] = 1.0
            i = dof_parent[i]
    dof_vel = dof_anc.T.copy()
    for f in range(len(free_ids)):
        rot = free_dof[f] + np.arange(3, 6)
        for j in rot:
            dof_vel[j, rot] = 0.0  # the frame of a free joint's rotation axes moves with the dofs before it
    body_desc = np.zeros((nb, nb))
    for b in range(nb):
        a = b
        while a >= 0:
            body_desc[a, b] = 1.0
            a = body_parent[a]
    body_dof_anc = body_desc.T[:, dof_body] if nv else np.zeros((nb, 0))

    # --- ground-contact points --------------------------------------------------------------------------------
    ground_height = None
    planes = [g for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    plane_conaff, plane_contype = 0, 0
    if planes:
        g = planes[0]
        if m.geom_bodyid[g] != 0:
            raise UnsupportedModelError(f"plane geom '{_name(m, mujoco.mjtObj.mjOBJ_GEOM, g)}' must be static")
        zaxis = _quat_to_mat(m.geom_quat[g])[:, 2]
        if not np.allclose(zaxis, [0.0, 0.0, 1.0]):
            raise UnsupportedModelError("only a horizontal ground plane (normal +z) is supported")
        ground_height = float(m.geom_pos[g][2])
        plane_conaff, plane_contype = int(m.geom_conaffinity[g]), int(m.geom_contype[g])
    contact_body, contact_pos, contact_dist = [], [], []
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if b == 0 or ground_height is None:
            continue
        collides = (m.geom_contype[g] & plane_conaff) or (m.geom_conaffinity[g] & plane_contype)
        if not collides:
            continue
        gt = int(m.geom_type[g])
        rot = _quat_to_mat(m.geom_quat[g])
        pos = np.asarray(m.geom_pos[g], dtype=np.float64)
        size = np.asarray(m.geom_size[g], dtype=np.float64)
        if gt == mujoco.mjtGeom.mjGEOM_SPHERE:
            pts, dist = [pos], size[0]
        elif gt == mujoco.mjtGeom.mjGEOM_CAPSULE:
            half = rot[:, 2] * size[1]
            pts, dist = [pos - half, pos + half], size[0]
        elif gt == mujoco.mjtGeom.mjGEOM_BOX:
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
            pts, dist = list(pos + corners @ rot.T), 0.0
        else:
            raise UnsupportedModelError(
                f"geom '{_name(m, mujoco.mjtObj.mjOBJ_GEOM, g)}' of type "
                f"{mujoco.mjtGeom(gt).name} collides with the ground; contact points exist for sphere, capsule "
                "and box only (set contype/conaffinity to 0 to exclude it)"
            )
        for p in pts:
            contact_body.append(b - 1)
            contact_pos.append(p)
            contact_dist.append(dist)

    # --- actuators --------------------------------------------------------------------------------------------
    act_dof, act_gear, act_names = [], [], []
    for u in range(m.nu):
        name = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, u)
        if int(m.actuator_trntype[u]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            raise UnsupportedModelError(f"actuator '{name}': only joint transmissions are supported")
        j = int(m.actuator_trnid[u, 0])
        if int(m.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise UnsupportedModelError(f"actuator '{name}': only hinge/slide joints can be actuated")
        if int(m.actuator_gaintype[u]) != int(mujoco.mjtGain.mjGAIN_FIXED) or int(m.actuator_biastype[u]) != 0:
            raise UnsupportedModelError(f"actuator '{name}': only plain motors are supported")
        act_dof.append(int(m.jnt_dofadr[j]))
        act_gear.append(float(m.actuator_gear[u, 0]))
        act_names.append(name)

    return ArticulatedModel(
        path=path,
        name=Path(path).stem if path else "",
        nq=int(m.nq),
        nv=int(nv),
        nb=nb,
        gravity=np.array(m.opt.gravity, dtype=np.float64),
        ground_height=ground_height,
        body_names=body_names,
        joint_names=joint_names,
        body_parent=body_parent,
        body_pos=body_pos,
        body_rot=body_rot,
        body_free=body_free,
        body_slots=body_slots,
        body_mass=body_mass,
        body_ipos=body_ipos,
        body_inertia=body_inertia,
        hs_names=tuple(joint_names[j] for j in hs_ids),
        hs_hinge=hs_hinge,
        hs_axis=hs_axis,
        hs_anchor=hs_anchor,
        hs_body=hs_body,
        hs_slot=hs_slot,
        hs_qadr=hs_qadr,
        hs_dof=hs_dof,
        hs_qpos0=hs_qpos0,
        hs_stiffness=hs_stiffness,
        hs_springref=hs_springref,
        hs_limited=hs_limited,
        hs_range=hs_range,
        free_body=free_body,
        free_qadr=free_qadr,
        free_dof=free_dof,
        dof_body=dof_body,
        dof_armature=np.array(m.dof_armature, dtype=np.float64),
        dof_damping=np.array(m.dof_damping, dtype=np.float64),
        body_dof_anc=body_dof_anc,
        dof_anc=dof_anc,
        dof_vel=dof_vel,
        body_desc=body_desc,
        contact_body=np.array(contact_body, dtype=np.int64),
        contact_pos=np.array(contact_pos, dtype=np.float64).reshape(-1, 3),
        contact_dist=np.array(contact_dist, dtype=np.float64),
        act_names=tuple(act_names),
        act_dof=np.array(act_dof, dtype=np.int64),
        act_gear=np.array(act_gear, dtype=np.float64),
        qpos0=np.array(m.qpos0, dtype=np.float64),
    )
