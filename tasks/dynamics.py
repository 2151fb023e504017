"""Batched, differentiable reduced-coordinate rigid-body dynamics (the dflex model SHAC trained with).

One :class:`Simulator` holds the constant tensors of one :class:`~tasks.model.ArticulatedModel` on a device
and dtype and evaluates, for a batch of ``B`` states (``qpos: (B, nq)``, ``qvel: (B, nv)``):

* forward kinematics (body and joint frames),
* the joint-space inertia matrix ``M (B, nv, nv)`` plus armature,
* the bias forces (Coriolis, centrifugal, gravity) by Newton-Euler,
* passive joint forces (damping, stiffness springs), joint-limit penalties and dflex's ground contact,
* ``qacc = M^-1 (tau - bias)`` with ``M^-1`` from a batched Cholesky factorisation (cached over substeps
  as dflex did, so a substep is matrix-vector products only),
* a semi-implicit Euler substep.

Algorithm (why it looks the way it does). Everything is expressed in world-aligned spatial coordinates
with the reference point at the floating base (else the first body's origin), not the world origin: the
numbers stay small however far the robot walks, which keeps float32 accurate. In that frame the motion
subspace ``S_j (6,)`` of every dof, the velocity of every body and every body's spatial inertia are computed
for all dofs/bodies at once; the recursions of CRBA and RNEA over the tree become products with constant 0/1
ancestor masks:

* composite inertias ``Ic = desc @ I`` (one matmul over bodies) and ``M_ij = S_i . Ic[body j] S_j`` for
  ``i`` an ancestor of ``j`` (the composite-rigid-body algorithm without its backward loop);
* body velocities ``v_b = sum_{j anc b} S_j qd_j`` and accelerations from ``dS_j/dt = v_j x S_j``;
* Newton-Euler body forces ``f_b = I_b a_b + v_b x* I_b v_b - f_ext_b`` and joint forces
  ``tau_j = S_j . sum_{b desc j} f_b``.

Only forward kinematics walks the tree: one 4x4 product per joint slot (at most 3 joints per body here) and
one per tree level (depth <= 6 here), each over all bodies and joint frames at once; its backward does not
walk the tree but sums over subtrees with one constant mask (:class:`_WorldFrames`). There are no
data-dependent branches or host synchronisations, the shapes are static, and with the mass-matrix inverse
cached a substep contains no library call, so it compiles with ``torch.compile`` and captures in a CUDA
graph. The gradient of the solve goes to ``M`` analytically (``gM = -(M^-1 gx) x^T``), not through the
factorisation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import torch

from .model import ArticulatedModel
from .spatial import RowGather, bmm, bmv, contract, cross, cross_force, cross_motion, quat_mul, quat_to_mat, skew

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

    X: (B, nb, 4, 4) body poses as homogeneous transforms, world-aligned, translations [m] relative to
    ``origin``. origin: (B, 3) [m] world position of the reference point (the floating base, else the first
    body's origin). S: (B, nv, 6) motion subspace of every dof, world-aligned, about ``origin``.
    """

    X: torch.Tensor
    origin: torch.Tensor
    S: torch.Tensor

    @property
    def rot(self) -> torch.Tensor:
        """(B, nb, 3, 3) body orientations (world from body), MuJoCo's ``xmat``."""
        return self.X[..., :3, :3]

    @property
    def pos(self) -> torch.Tensor:
        """(B, nb, 3) [m] body origins in the world frame, MuJoCo's ``xpos``."""
        return self.X[..., :3, 3] + self.origin[:, None]


class _WorldFrames(torch.autograd.Function):
    """World frames of a kinematic tree from its local frames, with a backward that has no tree recursion.

    Forward, the depth rounds: ``X_e = P_a0 P_a1 ... P_e`` over the entry's ancestor chain (``chain (D, E)``,
    row ``d`` the ancestor at depth ``d`` or ``E``, the appended identity ``eye4``). Compiled, each round is one
    kernel with a thread per matrix element of every entry. Written entry by entry instead, the rounds fuse into
    one kernel with a thread per frame, but inductor gives each thread 8 frames and the simulator is slower at
    4096 ants.

    Backward, subtree sums instead of a leaf-to-root sweep. Entry ``d`` in the subtree of ``k`` has
    ``X_d = X_k (X_k^-1 X_d)``, so everything below ``k`` sends ``k`` the gradient
    ``G_k = sum_{d in subtree(k)} gX_d X_d^T X_k^-T``: one constant-mask contraction (``subtree (E, E)``) of
    ``gX X^T`` for every entry at once, then ``gP_k = X_parent(k)^T G_k`` (``parent (E,)``, ``E`` for the
    identity). A level-by-level backward needs one dependent kernel per tree level; this needs two, and no
    atomics. It requires rigid frames (``X^-1`` from ``R^T``), which the simulator's always are: quaternions
    are normalised and hinge transforms are rotations.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        P: torch.Tensor, chain: torch.Tensor, parent: torch.Tensor, subtree: torch.Tensor, eye4: torch.Tensor
    ) -> torch.Tensor:
        P = torch.cat((P, eye4.expand(P.shape[0], 1, 4, 4)), dim=1)
        X = P[:, chain[0]]
        for r in range(1, chain.shape[0]):
            X = bmm(X, P[:, chain[r]])
        return X

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(output, *inputs[2:])

    @staticmethod
    def backward(ctx, gX):  # type: ignore[override]
        X, parent, subtree, eye4 = ctx.saved_tensors
        B, E = X.shape[:2]
        below = contract(subtree, bmm(gX, X.mT).reshape(B, E, 16)).reshape(B, E, 4, 4)
        # times X^-T = [[R, 0], [-t^T R, 1]] (X rigid), written out: [(b - c t^T) R | c] for below = [b | c]
        R, t = X[..., :3, :3], X[..., :3, 3:]
        b, c = below[..., :3], below[..., 3:]
        G = torch.cat((bmm(b - bmm(c, t.mT), R), c), dim=-1)
        X_parent = torch.cat((X, eye4.expand(B, 1, 4, 4)), dim=1)[:, parent]
        return bmm(X_parent.mT, G), None, None, None, None


class _InverseSolve(torch.autograd.Function):
    """``x = M^-1 b`` given SPD ``M (B, n, n)``, its inverse ``Minv`` (computed without grad) and ``b (B, n)``.

    Forward and backward are batched matrix-vector products: ``x = Minv b``; ``gb = Minv gx`` and
    ``gM = -gb x^T`` (the derivative of ``M^-1 b``), so gradients reach ``M`` although ``Minv`` was computed
    outside autograd. With the inverse cached for several substeps (dflex's mass-matrix caching) a substep
    contains no linear-algebra library call at all: everything fuses under ``torch.compile`` and nothing
    in it can trip CUDA-graph capture.
    """

    @staticmethod
    def forward(M: torch.Tensor, Minv: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return bmv(Minv, b)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(output, inputs[1])

    @staticmethod
    def backward(ctx, gx):  # type: ignore[override]
        x, Minv = ctx.saved_tensors
        gb = bmv(Minv, gx)  # Minv is symmetric
        return -gb.unsqueeze(-1) * x.unsqueeze(-2), None, gb


def spd_inverse(M: torch.Tensor, *, method: Literal["library", "torch"] = "library") -> torch.Tensor:
    """Inverse of SPD ``M (B, n, n)`` through its Cholesky factor, outside autograd (gradients reach ``M``
    through :func:`spd_solve`).

    ``method="library"``: ``cholesky_ex`` (no error check, hence no host synchronisation) and a cuBLAS/LAPACK
    triangular solve. ``method="torch"``: the same factorisation written as n column steps of plain tensor
    ops, for back ends where a solver library cannot be captured in a CUDA graph.
    """
    with torch.no_grad():
        M = M.detach()
        n = M.shape[-1]
        eye = torch.eye(n, dtype=M.dtype, device=M.device).expand_as(M)
        if method == "library":
            L = torch.linalg.cholesky_ex(M)[0]
            Linv = torch.linalg.solve_triangular(L, eye, upper=False)
        else:
            L = torch.zeros_like(M)
            for j in range(n):  # column j of L from the columns before it
                v = M[:, j:, j] - (L[:, j:, :j] * L[:, j : j + 1, :j]).sum(-1)
                L[:, j:, j] = v / torch.sqrt(v[:, :1])
            Linv = torch.zeros_like(M)
            for i in range(n):  # forward substitution, row by row: L Linv = I
                row = eye[:, i] - (L[:, i, :i, None] * Linv[:, :i]).sum(1)
                Linv[:, i] = row / L[:, i, i : i + 1]
        return Linv.mT @ Linv


def spd_solve(M: torch.Tensor, b: torch.Tensor, Minv: torch.Tensor | None = None) -> torch.Tensor:
    """``M^-1 b`` for a batch of SPD matrices. M: (B, n, n), b: (B, n), optional ``Minv = spd_inverse(M)``."""
    return _InverseSolve.apply(M, spd_inverse(M) if Minv is None else Minv, b)


def _index(arr: np.ndarray, device: torch.device) -> slice | torch.Tensor:
    """Column selector for ``x[:, sel]``: a slice when ``arr`` is a contiguous increasing range (a view, and a
    cheap backward), else a LongTensor (a gather)."""
    arr = np.asarray(arr, dtype=np.int64)
    if len(arr) and np.array_equal(arr, np.arange(arr[0], arr[0] + len(arr))):
        return slice(int(arr[0]), int(arr[0]) + len(arr))
    return torch.as_tensor(arr, dtype=torch.long, device=device)


class Simulator:
    """Differentiable dynamics of one articulated model for batches of states.

    Args:
        model: the articulated model (:func:`tasks.model.load_model`).
        device, dtype: where and in which precision all tensors live (float32 or float64).
        contact: ground-contact parameters, or None for no contact.
        limits: joint-limit penalty, or None for no limits.
        linalg: how the mass matrix is inverted (:func:`spd_inverse`): "library" (cuSOLVER/LAPACK Cholesky)
            or "torch" (the same algorithm in plain tensor ops).
    """

    def __init__(
        self,
        model: ArticulatedModel,
        *,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        contact: ContactParams | None = None,
        limits: LimitParams | None = None,
        linalg: Literal["library", "torch"] = "library",
    ) -> None:
        if linalg not in ("library", "torch"):
            raise ValueError(f"linalg must be 'library' or 'torch', got {linalg!r}")
        self.linalg = linalg
        self.model = model
        self.device = torch.device(device)
        self.dtype = dtype
        self.contact = contact if (contact is not None and model.nc > 0) else None
        self.limits = limits
        self.nq, self.nv, self.nb = model.nq, model.nv, model.nb
        nb, nh, nf, nv = model.nb, model.nh, model.nf, model.nv
        self._nf = nf

        def f(x) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype, device=self.device)

        def i(x) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, dtype=np.int64), dtype=torch.long, device=self.device)

        def idx(x) -> slice | torch.Tensor:
            return _index(x, self.device)

        def free_idx(adr: np.ndarray, first: int, n: int) -> slice | torch.Tensor:
            """Columns [adr + first, adr + first + n) of every free joint: a slice for one joint, else (nf, n)."""
            if len(adr) == 1:
                return slice(int(adr[0]) + first, int(adr[0]) + first + n)
            return i((adr[:, None] + first + np.arange(n)).reshape(len(adr), n))

        # --- hinge/slide joint transforms: J(q) = I + sin(q) A1 + (1 - cos(q)) A2 + q A3 (4x4, frame before
        # the joint). Hinge about axis u through anchor a: R = I + s K + (1-c) K^2 (K = [u]x), translation
        # a - R a = -(s K + (1-c) K^2) a. Slide along u: translation u q. Entry nh is an identity "joint" that
        # pads bodies with fewer joints.
        hinge = model.hs_hinge.astype(np.float64)
        K = np.array([[[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]] for u in model.hs_axis]).reshape(nh, 3, 3)
        A1 = np.zeros((nh + 1, 4, 4))
        A2 = np.zeros((nh + 1, 4, 4))
        A3 = np.zeros((nh + 1, 4, 4))
        for h in range(nh):
            k1, k2, a = K[h], K[h] @ K[h], model.hs_anchor[h]
            A1[h, :3, :3], A1[h, :3, 3] = hinge[h] * k1, -hinge[h] * (k1 @ a)
            A2[h, :3, :3], A2[h, :3, 3] = hinge[h] * k2, -hinge[h] * (k2 @ a)
            A3[h, :3, 3] = (1.0 - hinge[h]) * model.hs_axis[h]
        self._J_tables = f(np.stack([A1, A2, A3]))  # (3, nh + 1, 4, 4)
        self._hs_q = idx(model.hs_qadr)  # a slice when contiguous: no gather, and no scatter in backward
        self._hs_v = idx(model.hs_dof)
        self._hs_qpos0 = f(model.hs_qpos0)
        self._hs_hinge = f(hinge)
        # axis (homogeneous direction) and anchor (homogeneous point) as the two columns of a (nh, 4, 2) table
        ua = np.zeros((nh, 4, 2))
        ua[:, :3, 0], ua[:, :3, 1], ua[:, 3, 1] = model.hs_axis, model.hs_anchor, 1.0
        self._hs_axis_anchor = f(ua)
        self._hs_stiffness = f(model.hs_stiffness)
        self._hs_springref = f(model.hs_springref)
        big = 1e10  # "unlimited": clamp(q, -big, big) == q; finite so that no inf * 0 can appear
        self._hs_lo = f(np.where(model.hs_limited, model.hs_range[:, 0], -big) if nh else np.zeros(0))
        self._hs_hi = f(np.where(model.hs_limited, model.hs_range[:, 1], big) if nh else np.zeros(0))
        self._has_stiffness = bool(np.any(model.hs_stiffness != 0))

        # --- free joints
        self._free_body = RowGather(model.free_body, nb + nh, device=self.device)  # rows of all entries
        self._root_free = int(model.body_free[0]) if nb else -1
        self._free_pos = free_idx(model.free_qadr, 0, 3)
        self._free_quat = free_idx(model.free_qadr, 3, 4)
        self._free_lin = free_idx(model.free_dof, 0, 3)
        self._free_ang = free_idx(model.free_dof, 3, 3)
        self._free_S_trans = f(np.concatenate([np.zeros((3, 3)), np.eye(3)], axis=1))  # (3, 6)
        self._bottom_row = f(np.array([[0.0, 0.0, 0.0, 1.0]]))
        self._eye4 = f(np.eye(4))

        # --- kinematic "entries": the nb bodies, then one pre-joint frame per hinge/slide joint (the joint's
        # frame just before it moves, where its axis and anchor are constant). Local frames come from prefix
        # products of the body offset and the body's joint transforms ("slot rounds", one per joint slot);
        # world frames from products along the ancestor chain ("depth rounds", one per tree level) for all
        # entries at once (:class:`_WorldFrames`, whose backward sums over subtrees instead of walking the tree).
        # Gathers are RowGathers: their compiled backward sums without atomics.
        off = np.tile(np.eye(4), (nb, 1, 1))
        off[:, :3, :3], off[:, :3, 3] = model.body_rot, model.body_pos
        owner = np.concatenate([np.arange(nb), model.hs_body]).astype(np.int64)
        n_prefix = np.concatenate([(model.body_slots < nh).sum(1), model.hs_slot]).astype(np.int64)
        n_prefix[:nb][model.body_free >= 0] = 0
        E = nb + nh
        self._n_slots = int(n_prefix.max()) if len(n_prefix) else 0
        self._slot_take = [
            RowGather(
                np.where(r < n_prefix, model.body_slots[owner, min(r, model.body_slots.shape[1] - 1)], nh),
                nh + 1,
                device=self.device,
                no_grad_rows=(nh,),  # the identity "joint" is a constant
            )
            for r in range(self._n_slots)
        ]
        off_src = np.arange(E)  # initial local frame: the owner's offset, or its free joint's pose
        for fj, b in enumerate(model.free_body):
            off_src[b] = E + fj
        self._entry_off = f(off[owner])
        self._off_take = RowGather(off_src, E + nf, device=self.device, no_grad_rows=range(E))
        depth = np.zeros(nb, dtype=np.int64)
        for b in range(nb):
            depth[b] = 0 if model.body_parent[b] < 0 else depth[model.body_parent[b]] + 1
        n_depth = int(depth.max()) + 1 if nb else 0
        chain = np.full((n_depth, E), E, dtype=np.int64)  # E: an appended identity
        for e in range(E):
            b, d = owner[e], depth[owner[e]]
            chain[d, e] = e
            for r in range(d - 1, -1, -1):
                b = model.body_parent[b]
                chain[r, e] = b
        parent = np.where(depth[owner] > 0, chain[np.maximum(depth[owner] - 1, 0), np.arange(E)], E)
        subtree = np.zeros((E, E))  # [k, e] = 1: entry k is on e's chain (e itself included)
        for r in range(n_depth):
            on = chain[r] < E
            subtree[chain[r][on], np.arange(E)[on]] = 1.0
        self._chain, self._entry_parent, self._subtree = i(chain), i(parent), f(subtree)
        self._body_mass = f(model.body_mass)
        self._body_ipos_h = f(np.concatenate([model.body_ipos, np.ones((nb, 1))], axis=1))  # homogeneous
        self._body_inertia = f(model.body_inertia)
        self._mass_eye = f(model.body_mass[:, None, None] * np.eye(3))

        # --- dofs: S and generalized forces are assembled from [free (6 nf), hinge/slide (nh)] blocks, and
        # qpos from [free (7 nf), hinge/slide (nh)]; for MuJoCo's usual layouts that order is already MuJoCo's
        # and no permutation is needed (None)
        dof_src = np.empty(nv, dtype=np.int64)
        dof_src[model.hs_dof] = 6 * nf + np.arange(nh)
        for fj, d in enumerate(model.free_dof):
            dof_src[d : d + 6] = 6 * fj + np.arange(6)
        self._dof_src = None if np.array_equal(dof_src, np.arange(nv)) else i(dof_src)
        qpos_src = np.empty(model.nq, dtype=np.int64)
        qpos_src[model.hs_qadr] = 7 * nf + np.arange(nh)
        for fj, a in enumerate(model.free_qadr):
            qpos_src[a : a + 7] = 7 * fj + np.arange(7)
        self._qpos_src = None if np.array_equal(qpos_src, np.arange(model.nq)) else i(qpos_src)
        self._dof_body = RowGather(model.dof_body, nb, device=self.device)
        self._armature = f(np.diag(model.dof_armature))
        self._damping = f(model.dof_damping)
        self._body_dof_anc = f(model.body_dof_anc)  # (nb, nv)
        self._dof_body_anc = f(model.body_dof_anc.T.copy())  # (nv, nb)
        self._body_desc = f(model.body_desc)
        self._dof_vel = f(model.dof_vel)
        self._upper = f(model.dof_anc)  # [i, j] = 1: i ancestor-or-self of j
        self._strict_upper = f(model.dof_anc - np.eye(nv))
        self._a0 = f(np.concatenate([np.zeros(3), -model.gravity]))  # gravity as an upward base acceleration

        # --- contact points (homogeneous, body frame) and their body
        self._c_body = RowGather(model.contact_body, nb, device=self.device)
        self._c_pos_h = f(np.concatenate([model.contact_pos, np.ones((model.nc, 1))], axis=1))
        c_off = np.zeros((model.nc, 3))
        c_off[:, 2] = model.contact_dist
        self._c_offset = f(c_off)  # p = X c - n dist, n = +z
        one_hot = np.zeros((nb, model.nc))
        one_hot[model.contact_body, np.arange(model.nc)] = 1.0
        self._c_to_body = f(one_hot)
        self._ground = float(model.ground_height or 0.0)
        self._xy_mask = f(np.array([1.0, 1.0, 0.0]))
        self._z_unit = f(np.array([0.0, 0.0, 1.0]))

        # --- actuators: ctrl (B, nu) @ act_map -> generalized force (B, nv)
        act_map = np.zeros((model.nu, nv))
        act_map[np.arange(model.nu), model.act_dof] = model.act_gear
        self._act_map = f(act_map)

    # ------------------------------------------------------------------------------------------------------
    # kinematics
    def _homogeneous(self, R: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """(..., 3, 3), (..., 3) -> (..., 4, 4)."""
        top = torch.cat((R, p.unsqueeze(-1)), dim=-1)
        return torch.cat((top, self._bottom_row.expand(*top.shape[:-2], 1, 4)), dim=-2)

    def frames(self, qpos: torch.Tensor) -> Frames:
        """Forward kinematics. qpos: (B, nq) -> :class:`Frames` (equal to MuJoCo's ``xmat``/``xpos``)."""
        B = qpos.shape[0]
        eye4 = self._eye4

        # all hinge/slide joint transforms at once (entry nh: identity)
        theta = qpos[:, self._hs_q] - self._hs_qpos0  # (B, nh)
        theta = torch.cat((theta, theta.new_zeros(B, 1)), dim=1)[..., None, None]
        A1, A2, A3 = self._J_tables
        J = eye4 + torch.sin(theta) * A1 + (1.0 - torch.cos(theta)) * A2 + theta * A3  # (B, nh + 1, 4, 4)

        # local frames of all entries: offset (or free pose) x the owner's joints before the entry's slot
        P = self._entry_off.expand(B, -1, -1, -1)
        if self._nf:
            free_p = self._free_take(qpos, self._free_pos)  # (B, nf, 3)
            if self._root_free >= 0:
                # floating base: work relative to its position from the start, so that a robot far from the
                # world origin loses no float32 precision in its internal geometry
                origin = free_p[:, self._root_free]
                free_p = free_p - origin[:, None]
            free_T = self._homogeneous(quat_to_mat(self._free_take(qpos, self._free_quat)), free_p)
            P = self._off_take(torch.cat((P, free_T), dim=1))
        for take in self._slot_take:
            P = bmm(P, take(J))
        X = _WorldFrames.apply(P, self._chain, self._entry_parent, self._subtree, eye4)  # (B, E, 4, 4)
        if self._root_free < 0:  # fixed or planar base: reference point = first body's origin
            origin = X[:, 0, :3, 3]
            X = X - torch.nn.functional.pad(origin[:, None, :, None], (3, 0, 0, 1))  # translations -= origin

        # motion subspaces (world-aligned, about the origin)
        nb = self.nb
        parts = []
        if self._nf:
            # free joints: world-frame translation, then rotation about the body axes through the body origin
            Xf = self._free_body(X)
            axes = Xf[..., :3, :3].mT  # (B, nf, 3, 3): rows are the body axes
            S_rot = torch.cat((axes, cross(Xf[..., None, :3, 3], axes)), dim=-1)  # (B, nf, 3, 6)
            S_free = torch.cat((self._free_S_trans.expand(B, self._nf, 3, 6), S_rot), dim=2)
            parts.append(S_free.reshape(B, 6 * self._nf, 6))
        if self.model.nh:
            aa = bmm(X[:, nb:], self._hs_axis_anchor)  # (B, nh, 4, 2): axis, anchor
            axis, anchor = aa[..., :3, 0], aa[..., :3, 1]
            h = self._hs_hinge[:, None]
            parts.append(torch.cat((h * axis, h * cross(anchor, axis) + (1.0 - h) * axis), dim=-1))
        S = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        if self._dof_src is not None:
            S = S[:, self._dof_src]
        return Frames(X[:, :nb], origin, S)

    def _free_take(self, x: torch.Tensor, idx) -> torch.Tensor:
        """Columns of the free joints: a slice (one free joint) -> (B, 1, k), or an index (nf, k) -> (B, nf, k)."""
        return x[:, idx].unsqueeze(1) if isinstance(idx, slice) else x[:, idx]

    # ------------------------------------------------------------------------------------------------------
    # inertia
    def _inertia_parts(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotational inertias about the centres of mass, world-aligned, ``I_c (B, nb, 3, 3)`` [kg m^2], and the
        centres of mass relative to the reference point ``c (B, nb, 3)`` [m]. X: (B, nb, 4, 4)."""
        R = X[..., :3, :3]
        c = bmv(X, self._body_ipos_h)[..., :3]
        return bmm(bmm(R, self._body_inertia), R.mT), c

    def _spatial_inertia(self, I_c: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """Body spatial inertias about the reference point, world-aligned, from :meth:`_inertia_parts`
        -> (B, nb, 6, 6).

        [[I_c + m ([c]x [c]x^T), m [c]x], [m [c]x^T, m 1]] with c the centre of mass relative to the
        reference point and I_c the rotational inertia about the centre of mass.
        """
        m = self._body_mass[:, None, None]
        cx = skew(c)
        top = torch.cat((I_c - m * bmm(cx, cx), m * cx), dim=-1)
        bottom = torch.cat((-m * cx, self._mass_eye.expand_as(cx)), dim=-1)
        return torch.cat((top, bottom), dim=-2)

    def _inertia_times(self, I_c: torch.Tensor, c: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Spatial inertia times motion, ``I6 v``, without forming ``I6``: for ``v = (w, u)``, with
        ``h = m (u - c x w)`` (the momentum of the centre of mass), ``I6 v = (I_c w + c x h, h)``.
        I_c: (B, nb, 3, 3), c: (B, nb, 3), v: (..., B, nb, 6) (leading dims: several motions) -> (..., B, nb, 6).
        Per body it reads 12 numbers instead of 36, and nothing of size (nb, 6, 6) is saved for the backward."""
        w, u = v[..., :3], v[..., 3:]
        h = self._body_mass[:, None] * (u - cross(c, w))
        return torch.cat((bmv(I_c, w) + cross(c, h), h), dim=-1)

    def _mass_matrix(self, S: torch.Tensor, I6: torch.Tensor) -> torch.Tensor:
        B, nb = I6.shape[:2]
        Ic = contract(self._body_desc, I6.reshape(B, nb, 36)).reshape(B, nb, 6, 6)  # composite inertias
        F = bmv(self._dof_body(Ic), S)  # (B, nv, 6)
        G = bmm(S, F.mT)  # G[i, j] = S_i . Ic[body j] S_j = M_ij when i is an ancestor-or-self of j
        return G * self._upper + (G * self._strict_upper).mT + self._armature

    def mass_matrix(self, qpos: torch.Tensor) -> torch.Tensor:
        """Joint-space inertia including armature (MuJoCo's ``qM``, dense). qpos: (B, nq) -> (B, nv, nv)."""
        fr = self.frames(qpos)
        return self._mass_matrix(fr.S, self._spatial_inertia(*self._inertia_parts(fr.X)))

    # ------------------------------------------------------------------------------------------------------
    # forces
    def _bias(self, S, inertia, Sq, vb, f_ext):
        """Newton-Euler: generalized bias force minus generalized external force (B, nv).

        inertia: ``(I_c, c)`` from :meth:`_inertia_parts`; Sq: (B, nv, 6) S_j qd_j; vb: (B, nb, 6) body
        spatial velocities; f_ext: (B, nb, 6) spatial forces about the reference point, or None. Body
        accelerations use dS_j/dt = v_j x S_j with v_j the velocity of the frame that carries S_j (the dof_vel
        mask).
        """
        vd = contract(self._dof_vel, Sq)
        ab = contract(self._body_dof_anc, cross_motion(vd, Sq)) + self._a0
        # both products in one call, on stacked motions: one pass over the body inertias. Compiled, this left fewer
        # kernels per substep (inductor's Triton code counted on the CPU: ant 74 -> 71, humanoid 82 -> 80)
        I_ab, I_vb = self._inertia_times(*inertia, torch.stack((ab, vb))).unbind(0)
        fb = I_ab + cross_force(vb, I_vb)
        if f_ext is not None:
            fb = fb - f_ext
        return (S * contract(self._dof_body_anc, fb)).sum(-1)

    def _contact_forces(self, fr: Frames, vb: torch.Tensor) -> torch.Tensor:
        """dflex ground contact at every contact point; returns body spatial forces (B, nb, 6)."""
        cp = self.contact
        assert cp is not None
        p = bmv(self._c_body(fr.X), self._c_pos_h)[..., :3] - self._c_offset  # p = X c - n dist
        height = p[..., 2] + (fr.origin[:, None, 2] - self._ground)
        v6 = self._c_body(vb)
        vel = v6[..., 3:] + cross(v6[..., :3], p)  # velocity of the point p
        depth = torch.clamp(-height, min=0.0)
        fn = (cp.ke - cp.kd * torch.clamp(vel[..., 2], max=0.0)) * depth
        vt = vel * self._xy_mask
        vt2 = (vt * vt).sum(-1)
        # Coulomb cap on viscous friction: coef = min(kf, mu ke d / |v_t|); at |v_t| ~ 0 the viscous branch is
        # exact and the division is never evaluated, so values and gradients stay finite.
        moving = vt2 > 1e-12
        inv_norm = torch.rsqrt(torch.where(moving, vt2, 1.0))
        coef = torch.where(moving, torch.clamp(cp.mu * cp.ke * depth * inv_norm, max=cp.kf), cp.kf)
        coef = torch.where(depth > 0, coef, 0.0)
        force = fn.unsqueeze(-1) * self._z_unit - coef.unsqueeze(-1) * vt
        spatial = torch.cat((cross(p, force), force), dim=-1)  # (B, nc, 6) about the reference point
        return contract(self._c_to_body, spatial)

    def _scatter_hs(self, x: torch.Tensor) -> torch.Tensor:
        """Per hinge/slide joint values (B, nh) -> generalized force vector (B, nv) (zeros on free dofs)."""
        if self._nf:
            x = torch.cat((x.new_zeros(x.shape[0], 6 * self._nf), x), dim=1)
        return x if self._dof_src is None else x[:, self._dof_src]

    def passive_force(self, qpos: torch.Tensor, qvel: torch.Tensor, *, limits: bool) -> torch.Tensor:
        """Joint damping, stiffness springs and (if ``limits``) the joint-limit penalty. -> (B, nv)."""
        tau = -self._damping * qvel
        q = qpos[:, self._hs_q]
        hs = None
        if self._has_stiffness:
            hs = -self._hs_stiffness * (q - self._hs_springref)
        if limits and self.limits is not None:
            lp = self.limits
            lim = lp.ke * (torch.clamp(q, self._hs_lo, self._hs_hi) - q)
            qd = qvel[:, self._hs_v]
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

    def factorize(self, qpos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mass matrix ``M (B, nv, nv)`` (differentiable) and its inverse (no grad), for reuse over several
        substeps (dflex's mass-matrix caching). qpos: (B, nq)."""
        M = self.mass_matrix(qpos)
        return M, spd_inverse(M, method=self.linalg)

    def acceleration(
        self,
        qpos: torch.Tensor,
        qvel: torch.Tensor,
        tau: torch.Tensor,
        *,
        contact: bool = True,
        limits: bool = True,
        mass: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Joint accelerations with generalized applied force ``tau (B, nv)``, including ground contact and
        joint limits when enabled here and configured on the simulator. ``mass``: a cached (M, M^-1) from
        :meth:`factorize` (default: the mass matrix at ``qpos``). -> qacc (B, nv)."""
        fr = self.frames(qpos)
        inertia = self._inertia_parts(fr.X)
        if mass is None:
            M = self._mass_matrix(fr.S, self._spatial_inertia(*inertia))
            Minv = spd_inverse(M, method=self.linalg)
        else:
            M, Minv = mass
        Sq = fr.S * qvel.unsqueeze(-1)  # (B, nv, 6)
        vb = contract(self._body_dof_anc, Sq)  # body spatial velocities
        f_ext = self._contact_forces(fr, vb) if (contact and self.contact is not None) else None
        rhs = tau + self.passive_force(qpos, qvel, limits=limits) - self._bias(fr.S, inertia, Sq, vb, f_ext)
        return spd_solve(M, rhs, Minv)

    def integrate(self, qpos: torch.Tensor, qvel: torch.Tensor, dt: float) -> torch.Tensor:
        """Positions after ``dt`` [s] at constant velocity ``qvel`` (the second half of semi-implicit Euler).

        Hinge/slide: ``q + dt qd``. Free joints: position ``+ dt v`` (world frame), quaternion
        ``q + dt/2 q (0, w_body)`` renormalised. qpos: (B, nq), qvel: (B, nv) -> (B, nq).
        """
        q_hs = qpos[:, self._hs_q] + dt * qvel[:, self._hs_v]
        if self._nf:
            B = qpos.shape[0]
            pos = self._free_take(qpos, self._free_pos) + dt * self._free_take(qvel, self._free_lin)  # (B, nf, 3)
            quat = self._free_take(qpos, self._free_quat)
            w = self._free_take(qvel, self._free_ang)
            quat = quat + (0.5 * dt) * quat_mul(quat, torch.nn.functional.pad(w, (1, 0)))
            quat = quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True)
            q_hs = torch.cat((torch.cat((pos, quat), dim=-1).reshape(B, 7 * self._nf), q_hs), dim=1)
        return q_hs if self._qpos_src is None else q_hs[:, self._qpos_src]

    def substep(
        self,
        qpos: torch.Tensor,
        qvel: torch.Tensor,
        tau: torch.Tensor,
        dt: float,
        mass: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One semi-implicit Euler step: ``qvel += dt qacc`` then ``qpos`` from the new ``qvel``.

        qpos: (B, nq), qvel: (B, nv), tau: (B, nv) generalized applied force, dt [s], mass: optional cached
        (M, M^-1) from :meth:`factorize` -> (qpos, qvel).
        """
        qvel = qvel + dt * self.acceleration(qpos, qvel, tau, mass=mass)
        return self.integrate(qpos, qvel, dt), qvel

    def actuator_force(self, ctrl: torch.Tensor) -> torch.Tensor:
        """Motor controls (B, nu) times gears -> generalized force (B, nv)."""
        return ctrl @ self._act_map
