"""Batched, differentiable reduced-coordinate rigid-body dynamics (the dflex model SHAC trained with).

One :class:`Simulator` holds the constant tensors of one :class:`~tasks.model.ArticulatedModel` on a device
and dtype and evaluates, for a batch of ``B`` states (``qpos: (B, nq)``, ``qvel: (B, nv)``):

* forward kinematics (body and joint frames),
* the joint-space inertia matrix ``M (B, nv, nv)`` plus armature,
* the bias forces (Coriolis, centrifugal, gravity) by Newton-Euler,
* passive joint forces (damping, stiffness springs), joint-limit penalties and dflex's ground contact,
* ``qacc = M^-1 (tau - bias)`` by a batched Cholesky solve,
* a semi-implicit Euler substep.

Algorithm (why it looks the way it does). Everything is expressed in world-aligned spatial coordinates
with the reference point at the first body's origin (not the world origin: the numbers stay small however
far the robot walks, which keeps float32 accurate). In that frame the motion subspace ``S_j (6,)`` of every
dof, the velocity of every body and every body's spatial inertia are computed for all dofs/bodies at once;
the recursions of CRBA and RNEA over the tree become products with constant 0/1 ancestor masks:

* composite inertias ``Ic = desc @ I`` (one matmul over bodies) and ``M_ij = S_i . Ic[body j] S_j`` for
  ``i`` an ancestor of ``j`` (the composite-rigid-body algorithm without its backward loop);
* body velocities ``v_b = sum_{j anc b} S_j qd_j`` and accelerations from ``dS_j/dt = v_j x S_j``;
* Newton-Euler body forces ``f_b = I_b a_b + v_b x* I_b v_b - f_ext_b`` and joint forces
  ``tau_j = S_j . sum_{b desc j} f_b``.

Only forward kinematics walks the tree, level by level (depth <= 6 here), vectorised over the bodies of a
level. There are no data-dependent branches or host synchronisations, the shapes are static, and the whole
substep is a few dozen batched kernels, so it compiles with ``torch.compile`` and captures in a CUDA graph.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import torch

from .model import ArticulatedModel
from .spatial import cross, cross_force, cross_motion, quat_mul, quat_to_mat, skew

__all__ = ["ContactParams", "Frames", "LimitParams", "Simulator"]


@dataclass(frozen=True)
class ContactParams:
    """dflex ground-contact penalty: stiffness ke [N/m], damping kd [N s/m^2], viscous friction kf [N s/m],
    Coulomb coefficient mu. The force on the body at a contact point with penetration ``d = max(-c, 0)``:
    normal ``ke d - kd min(v_n, 0) d`` along +z, friction ``-v_t/|v_t| min(kf |v_t|, mu ke d)``."""

    ke: float
    kd: float
    kf: float
    mu: float


@dataclass(frozen=True)
class LimitParams:
    """Joint-limit penalty on limited hinge/slide joints: force ``ke (clamp(q, lo, hi) - q)``.

    ``damping="always"`` reproduces dflex (``jcalc_tau``): ``-kd qd`` on EVERY hinge/slide dof, limited or
    not, so it acts as extra joint damping (dflex's comment says "only active when violated", its code applies
    it always). ``damping="violated"`` applies ``-kd qd`` only while a limited joint is outside its range.
    """

    ke: float
    kd: float
    damping: Literal["always", "violated"] = "always"


class Frames(NamedTuple):
    """Kinematics of a batch of states.

    rot: (B, nb, 3, 3) body orientations (world from body). pos: (B, nb, 3) [m] body origins, world frame.
    origin: (B, 3) [m] reference point of the spatial quantities (the first body's origin).
    rel: (B, nb, 3) [m] body origins relative to ``origin``. S: (B, nv, 6) motion subspace of every dof,
    world-aligned, about ``origin``.
    """

    rot: torch.Tensor
    pos: torch.Tensor
    origin: torch.Tensor
    rel: torch.Tensor
    S: torch.Tensor


class _SPDSolve(torch.autograd.Function):
    """``x = M^-1 b`` for symmetric positive-definite ``M (B, n, n)``, ``b (B, n)``.

    Forward: one Cholesky factorisation (``cholesky_ex``: no error check, hence no host sync) and two
    triangular solves. Backward reuses the factor: ``gb = M^-1 gx``, ``gM = -gb x^T``; cheaper than
    differentiating through the factorisation.
    """

    @staticmethod
    def forward(M: torch.Tensor, b: torch.Tensor):  # type: ignore[override]
        L = torch.linalg.cholesky_ex(M)[0]
        x = _chol_solve(L, b)
        return x, L

    @staticmethod
    def setup_context(ctx, inputs, output):
        x, L = output
        ctx.save_for_backward(x, L)
        ctx.mark_non_differentiable(L)

    @staticmethod
    def backward(ctx, gx, gL):  # type: ignore[override]
        x, L = ctx.saved_tensors
        gb = _chol_solve(L, gx)
        gM = -gb.unsqueeze(-1) * x.unsqueeze(-2)
        return gM, gb


def _chol_solve(L: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve ``L L^T x = b``; L: (B, n, n) lower, b: (B, n) -> (B, n)."""
    y = torch.linalg.solve_triangular(L, b.unsqueeze(-1), upper=False)
    return torch.linalg.solve_triangular(L.mT, y, upper=True).squeeze(-1)


def spd_solve(M: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``M^-1 b`` for a batch of SPD matrices (see :class:`_SPDSolve`). M: (B, n, n), b: (B, n) -> (B, n)."""
    return _SPDSolve.apply(M, b)[0]


class Simulator:
    """Differentiable dynamics of one articulated model for batches of states.

    Args:
        model: the articulated model (:func:`tasks.model.load_model`).
        device, dtype: where and in which precision all tensors live (float32 or float64).
        contact: ground-contact parameters, or None for no contact.
        limits: joint-limit penalty, or None for no limits.
    """

    def __init__(
        self,
        model: ArticulatedModel,
        *,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        contact: ContactParams | None = None,
        limits: LimitParams | None = None,
    ) -> None:
        self.model = model
        self.device = torch.device(device)
        self.dtype = dtype
        self.contact = contact if (contact is not None and model.nc > 0) else None
        self.limits = limits
        self.nq, self.nv, self.nb = model.nq, model.nv, model.nb
        nb, nh, nf, nv = model.nb, model.nh, model.nf, model.nv

        def f(x) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype, device=self.device)

        def i(x) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, dtype=np.int64), dtype=torch.long, device=self.device)

        # hinge/slide joints
        self._hs_qadr = i(model.hs_qadr)
        self._hs_dof = i(model.hs_dof)
        self._hs_qpos0 = f(model.hs_qpos0)
        self._hs_hinge = f(model.hs_hinge.astype(np.float64))
        self._hs_axis = f(model.hs_axis)
        self._hs_anchor = f(model.hs_anchor)
        k1 = skew(torch.as_tensor(model.hs_axis, dtype=torch.float64))
        self._hs_k1 = k1.to(device=self.device, dtype=dtype)
        self._hs_k2 = (k1 @ k1).to(device=self.device, dtype=dtype)
        self._hs_body = i(model.hs_body)
        self._hs_slot = i(model.hs_slot)
        par = model.body_parent[model.hs_body] if nh else np.zeros(0, dtype=np.int64)
        self._hs_parent = i(np.where(par < 0, nb, par))  # nb indexes an appended identity (world) frame
        self._hs_stiffness = f(model.hs_stiffness)
        self._hs_springref = f(model.hs_springref)
        big = 1e10  # "unlimited": clamp(q, -big, big) == q; finite so that no inf * 0 can appear
        lo = np.where(model.hs_limited, model.hs_range[:, 0], -big) if nh else np.zeros(0)
        hi = np.where(model.hs_limited, model.hs_range[:, 1], big) if nh else np.zeros(0)
        self._hs_lo, self._hs_hi = f(lo), f(hi)
        self._hs_limited = f(model.hs_limited.astype(np.float64))
        self._has_stiffness = bool(np.any(model.hs_stiffness != 0))

        # free joints
        self._free_body = i(model.free_body)
        self._root_free = int(model.body_free[0]) if nb else -1
        self._free_dof = i(model.free_dof)
        self._free_pos_idx = i((model.free_qadr[:, None] + np.arange(3)).reshape(nf, 3))
        self._free_quat_idx = i((model.free_qadr[:, None] + np.arange(3, 7)).reshape(nf, 4))
        self._free_lin_idx = i((model.free_dof[:, None] + np.arange(3)).reshape(nf, 3))
        self._free_ang_idx = i((model.free_dof[:, None] + np.arange(3, 6)).reshape(nf, 3))
        self._free_S_trans = f(np.concatenate([np.zeros((3, 3)), np.eye(3)], axis=1))  # (3, 6)

        # bodies
        self._body_rot = f(model.body_rot)
        self._body_pos = f(model.body_pos)
        off_src = np.arange(nb)
        for fj, b in enumerate(model.free_body):
            off_src[b] = nb + fj
        self._off_src = i(off_src)
        self._slots = i(model.body_slots)
        self._n_slots = model.body_slots.shape[1]
        perm = np.concatenate(model.levels) if nb else np.zeros(0, dtype=np.int64)
        pos_in_perm = np.empty(nb, dtype=np.int64)
        pos_in_perm[perm] = np.arange(nb)
        self._perm = i(perm)
        self._inv_perm = i(pos_in_perm)
        self._level_slices: list[tuple[int, int, torch.Tensor]] = []
        start = 0
        for lv in model.levels:
            end = start + len(lv)
            self._level_slices.append((start, end, i(pos_in_perm[np.maximum(model.body_parent[lv], 0)])))
            start = end
        self._body_mass = f(model.body_mass)
        self._body_ipos = f(model.body_ipos)
        self._body_inertia = f(model.body_inertia)
        self._composite_mass = f(model.body_desc @ model.body_mass)

        # dofs: S and generalized forces are assembled from [hinge/slide (nh), free (6 nf)] blocks
        dof_src = np.empty(nv, dtype=np.int64)
        dof_src[model.hs_dof] = np.arange(nh)
        for fj, d in enumerate(model.free_dof):
            dof_src[d : d + 6] = nh + 6 * fj + np.arange(6)
        self._dof_src = i(dof_src)
        qpos_src = np.empty(model.nq, dtype=np.int64)
        qpos_src[model.hs_qadr] = np.arange(nh)
        for fj, a in enumerate(model.free_qadr):
            qpos_src[a : a + 3] = nh + 3 * fj + np.arange(3)
            qpos_src[a + 3 : a + 7] = nh + 3 * nf + 4 * fj + np.arange(4)
        self._qpos_src = i(qpos_src)
        self._dof_body = i(model.dof_body)
        self._armature = f(model.dof_armature)
        self._damping = f(model.dof_damping)
        self._body_dof_anc = f(model.body_dof_anc)
        self._body_desc = f(model.body_desc)
        self._dof_vel = f(model.dof_vel)
        self._upper = f(model.dof_anc).bool()  # [i, j]: i ancestor-or-self of j
        self._strict_upper = f(model.dof_anc - np.eye(nv)).bool()
        g = np.concatenate([np.zeros(3), -model.gravity])
        self._a0 = f(g)  # base acceleration -g: gravity enters Newton-Euler as an upward acceleration

        # contact points
        self._c_body = i(model.contact_body)
        self._c_pos = f(model.contact_pos)
        self._c_dist = f(model.contact_dist)
        one_hot = np.zeros((nb, model.nc))
        one_hot[model.contact_body, np.arange(model.nc)] = 1.0
        self._c_to_body = f(one_hot)
        self._ground = float(model.ground_height or 0.0)

        # actuators: ctrl (B, nu) @ act_map -> generalized force (B, nv)
        act_map = np.zeros((model.nu, nv))
        act_map[np.arange(model.nu), model.act_dof] = model.act_gear
        self._act_map = f(act_map)

    # ------------------------------------------------------------------------------------------------------
    # kinematics
    def frames(self, qpos: torch.Tensor) -> Frames:
        """Forward kinematics. qpos: (B, nq) -> :class:`Frames` (equal to MuJoCo's ``xmat``/``xpos``)."""
        B = qpos.shape[0]
        dt, dev = qpos.dtype, qpos.device
        eye = torch.eye(3, dtype=dt, device=dev)

        # joint transforms of all hinge/slide joints at once, in the frame before each joint:
        # hinge about the axis through the anchor a: x -> R x + (a - R a); slide: x -> x + u q
        theta = qpos[:, self._hs_qadr] - self._hs_qpos0  # (B, nh)
        h = self._hs_hinge
        s = torch.sin(theta)[..., None, None]
        c = torch.cos(theta)[..., None, None]
        Rj = eye + h[:, None, None] * (s * self._hs_k1 + (1.0 - c) * self._hs_k2)  # (B, nh, 3, 3)
        Ra = (Rj @ self._hs_anchor[..., None]).squeeze(-1)
        tj = h[:, None] * (self._hs_anchor - Ra) + (1.0 - h)[:, None] * self._hs_axis * theta[..., None]
        Rj = torch.cat((Rj, eye.expand(B, 1, 3, 3)), dim=1)  # index nh = identity (empty slot)
        tj = torch.cat((tj, tj.new_zeros(B, 1, 3)), dim=1)

        # body frames in their parent's frame: offset (or the free joint's pose) then the joints in order
        free_R = quat_to_mat(qpos[:, self._free_quat_idx])  # (B, nf, 3, 3)
        free_p = qpos[:, self._free_pos_idx]  # (B, nf, 3)
        if self._root_free >= 0:
            # floating base: work relative to its position from the start, so that a robot far from the
            # world origin loses no float32 precision in its internal geometry
            origin = free_p[:, self._root_free]
            free_p = free_p - origin[:, None]
        LR = torch.cat((self._body_rot.expand(B, -1, -1, -1), free_R), dim=1)[:, self._off_src]
        Lp = torch.cat((self._body_pos.expand(B, -1, -1), free_p), dim=1)[:, self._off_src]
        pre_R, pre_p = [], []
        for k in range(self._n_slots):
            idx = self._slots[:, k]
            pre_R.append(LR)
            pre_p.append(Lp)
            Lp = Lp + (LR @ tj[:, idx, :, None]).squeeze(-1)
            LR = LR @ Rj[:, idx]

        # world frames, one tree level at a time (bodies permuted so that each level is a contiguous block)
        LR, Lp = LR[:, self._perm], Lp[:, self._perm]
        s0, e0, _ = self._level_slices[0]
        WR, Wp = LR[:, s0:e0], Lp[:, s0:e0]
        for start, end, par in self._level_slices[1:]:
            PR, Pp = WR[:, par], Wp[:, par]
            WR = torch.cat((WR, PR @ LR[:, start:end]), dim=1)
            Wp = torch.cat((Wp, Pp + (PR @ Lp[:, start:end, :, None]).squeeze(-1)), dim=1)
        WR, Wp = WR[:, self._inv_perm], Wp[:, self._inv_perm]
        if self._root_free >= 0:
            rel, Wp = Wp, Wp + origin[:, None]
        else:
            origin = Wp[:, 0]
            rel = Wp - origin[:, None]

        # motion subspaces. Hinge/slide: axis and anchor in the frame just before the joint
        PR = torch.stack(pre_R, dim=1)[:, self._hs_slot, self._hs_body]  # (B, nh, 3, 3)
        Pp = torch.stack(pre_p, dim=1)[:, self._hs_slot, self._hs_body]
        axis_l = (PR @ self._hs_axis[..., None]).squeeze(-1)
        anchor_l = Pp + (PR @ self._hs_anchor[..., None]).squeeze(-1)
        WRx = torch.cat((WR, eye.expand(B, 1, 3, 3)), dim=1)[:, self._hs_parent]
        Wpx = torch.cat((rel, rel.new_zeros(B, 1, 3) - origin[:, None]), dim=1)[:, self._hs_parent]
        axis = (WRx @ axis_l[..., None]).squeeze(-1)
        anchor = Wpx + (WRx @ anchor_l[..., None]).squeeze(-1)
        S_hs = torch.cat((h[:, None] * axis, h[:, None] * cross(anchor, axis) + (1.0 - h)[:, None] * axis), -1)
        # free joints: world-frame translation, then rotation about the body axes through the body origin
        nf = free_R.shape[1]
        rot_axes = WR[:, self._free_body].transpose(-1, -2)  # (B, nf, 3, 3): rows = body axes
        r_free = rel[:, self._free_body]
        S_rot = torch.cat((rot_axes, cross(r_free[:, :, None, :], rot_axes)), dim=-1)  # (B, nf, 3, 6)
        S_free = torch.cat((self._free_S_trans.expand(B, nf, 3, 6), S_rot), dim=2).reshape(B, 6 * nf, 6)
        S = torch.cat((S_hs, S_free), dim=1)[:, self._dof_src]
        return Frames(WR, Wp, origin, rel, S)

    # ------------------------------------------------------------------------------------------------------
    # inertia
    def _body_inertias(self, fr: Frames) -> tuple[torch.Tensor, torch.Tensor]:
        """First moments h = m c (B, nb, 3) and rotational inertias about the reference point (B, nb, 3, 3)."""
        com = fr.rel + (fr.rot @ self._body_ipos[..., None]).squeeze(-1)
        m = self._body_mass
        I_c = fr.rot @ self._body_inertia @ fr.rot.mT
        cc = (com * com).sum(-1)[..., None, None] * torch.eye(3, dtype=com.dtype, device=com.device)
        I_o = I_c + m[:, None, None] * (cc - com[..., :, None] * com[..., None, :])
        return m[:, None] * com, I_o

    def _mass_matrix(self, fr: Frames, h: torch.Tensor, I_o: torch.Tensor) -> torch.Tensor:
        B, nb = h.shape[:2]
        packed = torch.cat((h, I_o.reshape(B, nb, 9)), dim=-1)
        comp = torch.einsum("ab,xbk->xak", self._body_desc, packed)  # composite (subtree) inertias
        hc, Ic = comp[..., :3][:, self._dof_body], comp[..., 3:].reshape(B, nb, 3, 3)[:, self._dof_body]
        mc = self._composite_mass[self._dof_body][:, None]
        w, v = fr.S[..., :3], fr.S[..., 3:]
        F = torch.cat(((Ic @ w[..., None]).squeeze(-1) + cross(hc, v), mc * v - cross(hc, w)), dim=-1)
        G = fr.S @ F.mT  # G[i, j] = S_i . Ic[body j] S_j: M_ij when i is an ancestor-or-self of j
        M = torch.where(self._upper, G, 0.0)
        M = M + torch.where(self._strict_upper, G, 0.0).mT
        return M + torch.diag_embed(self._armature)

    def mass_matrix(self, qpos: torch.Tensor) -> torch.Tensor:
        """Joint-space inertia including armature (MuJoCo's ``qM``, dense). qpos: (B, nq) -> (B, nv, nv)."""
        fr = self.frames(qpos)
        h, I_o = self._body_inertias(fr)
        return self._mass_matrix(fr, h, I_o)

    # ------------------------------------------------------------------------------------------------------
    # forces
    @staticmethod
    def _apply_inertia(m, h, I_o, x):
        """Spatial inertia (m, h, I_o) times motion x: (B, nb, 6) -> momentum (B, nb, 6)."""
        w, v = x[..., :3], x[..., 3:]
        return torch.cat(((I_o @ w[..., None]).squeeze(-1) + cross(h, v), m[:, None] * v - cross(h, w)), dim=-1)

    def _bias(self, fr, h, I_o, Sq, vb, f_ext):
        """Newton-Euler: generalized bias force minus generalized external force (B, nv).

        Sq: (B, nv, 6) S_j qd_j; vb: (B, nb, 6) body spatial velocities; f_ext: (B, nb, 6) spatial forces
        about the reference point, or None.
        """
        m = self._body_mass
        vd = torch.einsum("jn,xnk->xjk", self._dof_vel, Sq)
        ab = torch.einsum("bn,xnk->xbk", self._body_dof_anc, cross_motion(vd, Sq)) + self._a0
        fb = self._apply_inertia(m, h, I_o, ab) + cross_force(vb, self._apply_inertia(m, h, I_o, vb))
        if f_ext is not None:
            fb = fb - f_ext
        fd = torch.einsum("bn,xbk->xnk", self._body_dof_anc, fb)
        return (fr.S * fd).sum(-1)

    def _contact_forces(self, fr: Frames, vb: torch.Tensor) -> torch.Tensor:
        """dflex ground contact at every contact point; returns body spatial forces (B, nb, 6)."""
        cp = self.contact
        assert cp is not None
        R = fr.rot[:, self._c_body]
        p = fr.rel[:, self._c_body] + (R @ self._c_pos[..., None]).squeeze(-1)
        p = torch.cat((p[..., :2], p[..., 2:] - self._c_dist[:, None]), dim=-1)  # p = X c - n dist
        height = p[..., 2] + fr.origin[:, None, 2] - self._ground
        v6 = vb[:, self._c_body]
        vel = v6[..., 3:] + cross(v6[..., :3], p)  # velocity of the point p
        depth = torch.clamp(-height, min=0.0)
        vn = vel[..., 2]
        fn = cp.ke * depth - cp.kd * torch.clamp(vn, max=0.0) * depth
        vt = torch.cat((vel[..., :2], torch.zeros_like(vel[..., 2:])), dim=-1)
        vt2 = (vt * vt).sum(-1)
        # Coulomb cap on viscous friction: coef = min(kf, mu ke d / |v_t|); at |v_t| ~ 0 the viscous branch is
        # exact and the division is never evaluated, so values and gradients stay finite.
        moving = vt2 > 1e-12
        inv_norm = torch.rsqrt(torch.where(moving, vt2, 1.0))
        coef = torch.where(moving, torch.clamp(cp.mu * cp.ke * depth * inv_norm, max=cp.kf), cp.kf)
        coef = torch.where(depth > 0, coef, 0.0)
        force = -coef[..., None] * vt
        force = torch.cat((force[..., :2], force[..., 2:] + fn[..., None]), dim=-1)
        spatial = torch.cat((cross(p, force), force), dim=-1)  # (B, nc, 6) about the reference point
        return torch.einsum("bc,xck->xbk", self._c_to_body, spatial)

    def _scatter_hs(self, x: torch.Tensor) -> torch.Tensor:
        """Per hinge/slide joint values (B, nh) -> generalized force vector (B, nv) (zeros on free dofs)."""
        return torch.cat((x, x.new_zeros(x.shape[0], 6 * self.model.nf)), dim=1)[:, self._dof_src]

    def passive_force(self, qpos: torch.Tensor, qvel: torch.Tensor, *, limits: bool) -> torch.Tensor:
        """Joint damping, stiffness springs and (if ``limits``) the joint-limit penalty. -> (B, nv)."""
        tau = -self._damping * qvel
        q = qpos[:, self._hs_qadr]
        hs = None
        if self._has_stiffness:
            hs = -self._hs_stiffness * (q - self._hs_springref)
        if limits and self.limits is not None:
            lp = self.limits
            lim = lp.ke * (torch.clamp(q, self._hs_lo, self._hs_hi) - q)
            qd = qvel[:, self._hs_dof]
            if lp.damping == "always":
                lim = lim - lp.kd * qd
            else:
                outside = (q < self._hs_lo) | (q > self._hs_hi)
                lim = lim - lp.kd * torch.where(outside, qd, 0.0)
            hs = lim if hs is None else hs + lim
        if hs is not None:
            tau = tau + self._scatter_hs(hs)
        return tau

    # ------------------------------------------------------------------------------------------------------
    # dynamics
    def forward_dynamics(self, qpos: torch.Tensor, qvel: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """Joint accelerations with contacts and limits OFF: ``M^-1 (tau + passive - bias)``.

        Equals MuJoCo's ``mj_forward`` ``qacc`` with constraints disabled and ``qfrc_applied = tau`` (joint
        damping, stiffness springs and armature included). qpos: (B, nq), qvel: (B, nv), tau: (B, nv)
        [N or N m] -> qacc: (B, nv).
        """
        return self.acceleration(qpos, qvel, tau, contact=False, limits=False)

    def acceleration(
        self, qpos: torch.Tensor, qvel: torch.Tensor, tau: torch.Tensor, *, contact: bool = True, limits: bool = True
    ) -> torch.Tensor:
        """Joint accelerations with generalized applied force ``tau (B, nv)``, including ground contact and
        joint limits when enabled here and configured on the simulator. -> qacc (B, nv)."""
        fr = self.frames(qpos)
        h, I_o = self._body_inertias(fr)
        M = self._mass_matrix(fr, h, I_o)
        Sq = fr.S * qvel[..., None]  # (B, nv, 6)
        vb = torch.einsum("bn,xnk->xbk", self._body_dof_anc, Sq)  # body spatial velocities
        f_ext = self._contact_forces(fr, vb) if (contact and self.contact is not None) else None
        bias = self._bias(fr, h, I_o, Sq, vb, f_ext)
        rhs = tau + self.passive_force(qpos, qvel, limits=limits) - bias
        return spd_solve(M, rhs)

    def integrate(self, qpos: torch.Tensor, qvel: torch.Tensor, dt: float) -> torch.Tensor:
        """Positions after ``dt`` [s] at constant velocity ``qvel`` (the second half of semi-implicit Euler).

        Hinge/slide: ``q + dt qd``. Free joints: position ``+ dt v`` (world frame), quaternion
        ``q + dt/2 q (0, w_body)`` renormalised. qpos: (B, nq), qvel: (B, nv) -> (B, nq).
        """
        q_hs = qpos[:, self._hs_qadr] + dt * qvel[:, self._hs_dof]
        pos = qpos[:, self._free_pos_idx] + dt * qvel[:, self._free_lin_idx]  # (B, nf, 3)
        quat = qpos[:, self._free_quat_idx]
        w = qvel[:, self._free_ang_idx]
        dq = quat_mul(quat, torch.cat((torch.zeros_like(w[..., :1]), w), dim=-1))
        quat = quat + (0.5 * dt) * dq
        quat = quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True)
        B = qpos.shape[0]
        return torch.cat((q_hs, pos.reshape(B, -1), quat.reshape(B, -1)), dim=1)[:, self._qpos_src]

    def substep(
        self, qpos: torch.Tensor, qvel: torch.Tensor, tau: torch.Tensor, dt: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One semi-implicit Euler step: ``qvel += dt qacc`` then ``qpos`` from the new ``qvel``.

        qpos: (B, nq), qvel: (B, nv), tau: (B, nv) generalized applied force, dt [s] -> (qpos, qvel).
        """
        qacc = self.acceleration(qpos, qvel, tau)
        qvel = qvel + dt * qacc
        return self.integrate(qpos, qvel, dt), qvel

    def actuator_force(self, ctrl: torch.Tensor) -> torch.Tensor:
        """Motor controls (B, nu) times gears -> generalized force (B, nv)."""
        return ctrl @ self._act_map
