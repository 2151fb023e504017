"""The simulator of :mod:`tasks.dynamics` as NVIDIA Warp kernels: one thread an environment, a launch a substep.

:class:`WarpSimulator` evaluates the same model as :class:`tasks.dynamics.Simulator` (forward kinematics with the
floating-base reference point, the joint-space inertia with armature, its inverse cached every
``mass_matrix_every`` substeps, Newton-Euler bias forces, damping and springs, the joint-limit penalty, dflex's
ground contact and the semi-implicit Euler update) and exposes dflex's boundary,
:meth:`WarpSimulator.step` ``(qpos, qvel, tau, h, substeps, mass_matrix_every) -> (qpos, qvel)``, as a
``torch.autograd.Function``.

Kernels (one module per precision, so a float32 run compiles no float64 code):

* ``mass``: forward kinematics, composite inertias and the dense ``M (nv, nv)`` of every environment (one launch at
  the start of each caching window);
* ``invert``: its Cholesky inverse, forward only (the gradient reaches ``M`` as ``gM = -M^-1 gMinv M^-1``, the
  same expression as :class:`tasks.dynamics._InverseSolve`'s, applied in torch between the adjoint launches);
* ``substep``: kinematics, body velocities and bias accelerations, contacts, Newton-Euler, passive forces,
  ``qacc = M^-1 rhs`` and the integrator.

A control step of ``K`` substeps and ``W`` windows is ``K + 2 W`` launches forward and ``K + W`` adjoint launches
(plus ``W`` torch products) backward. The loops over bodies, joints, dofs and contacts are dynamic (compile time
does not grow with the model). Warp's adjoint of a dynamic loop does not restore values a loop carries in
registers (a register sum gets a zero gradient), so every loop-carried value lives in an array slot: written
once, or accumulated with ``+=`` (an atomic add, which Warp skips when it replays the forward inside the adjoint)
and read only once complete. Each substep has its own slots (index ``k`` of every buffer), so the adjoint of
substep ``k`` replays exactly its own forward. The buffers come from torch's allocator, the adjoint buffers are
fresh zeros in every backward (a repeated backward gives the same gradient), and the launches go on torch's
current stream, taken at call time, inside ``ScopedCapture(external=True)`` while torch captures a CUDA graph.

Gradients flow into ``qpos``, ``qvel`` and ``tau``. :meth:`WarpSimulator.frames`,
:meth:`~WarpSimulator.mass_matrix` and :meth:`~WarpSimulator.forward_dynamics` give the torch simulator's values
with its conventions, without gradient.
"""

# Annotations are evaluated (no ``from __future__ import annotations``): Warp reads the kernels' closure types.
# Literals in kernels are typed (``S(0.0)``) so that one source serves float32 and float64.

import functools
from typing import Any, ClassVar

import numpy as np
import torch

from diffrender.raytrace import warp_on_torch_stream

from .dynamics import ContactParams, Frames, LimitParams
from .model import ArticulatedModel

__all__ = ["WarpSimulator"]

_BIG = 1.0e10  # "unlimited" joint range, as tasks.dynamics: clamp(q, -big, big) == q


@functools.cache
def _warp():
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    else:
        wp.config.quiet = True
    wp.init()
    return wp


@functools.cache
def _kernels(precision: str) -> dict[str, Any]:
    """The three kernels and the model struct for ``precision`` ("float32" or "float64"), in one Warp module."""
    wp = _warp()
    S = wp.float32 if precision == "float32" else wp.float64
    vec3 = wp.types.vector(3, S)
    vec4 = wp.types.vector(4, S)
    vec6 = wp.types.vector(6, S)
    mat33 = wp.types.matrix((3, 3), S)
    module = wp.get_module(f"tasks.warp_sim.{precision}")

    def func(f):
        return wp.func(f, module=module)

    def kernel(f, backward=True):
        return wp.kernel(f, enable_backward=backward, module=module)

    class Model:
        nb: int
        nh: int
        nf: int
        nv: int
        nc: int
        root_free: int  # 1: body 0 carries a free joint whose position is the reference point
        b_parent: wp.array(dtype=int)  # parent body, nb for the world
        b_off_R: wp.array(dtype=mat33)
        b_off_t: wp.array(dtype=vec3)
        b_free: wp.array(dtype=int)  # free joint index or -1
        b_j0: wp.array(dtype=int)  # hinge/slide joints [j0, j1) of the body
        b_j1: wp.array(dtype=int)
        b_d0: wp.array(dtype=int)  # dofs [d0, d1) of the body
        b_d1: wp.array(dtype=int)
        b_mass: wp.array(dtype=S)
        b_ipos: wp.array(dtype=vec3)
        b_inertia: wp.array(dtype=mat33)
        h_hinge: wp.array(dtype=S)  # 1 hinge, 0 slide
        h_axis: wp.array(dtype=vec3)
        h_anchor: wp.array(dtype=vec3)
        h_qadr: wp.array(dtype=int)
        h_dof: wp.array(dtype=int)
        h_qpos0: wp.array(dtype=S)
        h_stiff: wp.array(dtype=S)
        h_springref: wp.array(dtype=S)
        h_lo: wp.array(dtype=S)
        h_hi: wp.array(dtype=S)
        f_body: wp.array(dtype=int)
        f_qadr: wp.array(dtype=int)
        f_dof: wp.array(dtype=int)
        d_body: wp.array(dtype=int)
        d_vsrc: wp.array(dtype=int)  # the dof whose running velocity moves this dof's axis (dS/dt)
        d_damping: wp.array(dtype=S)
        d_armature: wp.array(dtype=S)
        d_anc: wp.array(dtype=int)  # (nv * nv) [i * nv + j] = 1: i ancestor-or-self of j
        c_body: wp.array(dtype=int)
        c_pos: wp.array(dtype=vec3)
        c_dist: wp.array(dtype=S)
        a0: vec3  # -gravity: the base's upward acceleration
        ground: S
        ke: S
        kd: S
        kf: S
        mu: S
        lim_ke: S
        lim_kd: S
        lim_violated: int  # 0: limit damping on every hinge/slide dof (dflex), 1: only outside the range

    Model.__module__ = __name__
    Model = wp.struct(Model, module=module)

    @func
    def top(s: vec6):
        return vec3(s[0], s[1], s[2])

    @func
    def bot(s: vec6):
        return vec3(s[3], s[4], s[5])

    @func
    def sv(w: vec3, v: vec3):
        return vec6(w[0], w[1], w[2], v[0], v[1], v[2])

    @func
    def cross_motion(a: vec6, b: vec6):
        return sv(wp.cross(top(a), top(b)), wp.cross(top(a), bot(b)) + wp.cross(bot(a), top(b)))

    @func
    def cross_force(a: vec6, f: vec6):
        return sv(wp.cross(top(a), top(f)) + wp.cross(bot(a), bot(f)), wp.cross(top(a), bot(f)))

    @func
    def inertia_times(J: mat33, c: vec3, m: S, v: vec6):
        """``I6 v`` for the spatial inertia [[J, [c]x], [-[c]x, m 1]] (J about the reference point, c the first
        moment m x com): ``(J w + c x u, m u - c x w)`` for ``v = (w, u)``."""
        w = top(v)
        u = bot(v)
        return sv(J * w + wp.cross(c, u), m * u - wp.cross(c, w))

    @func
    def joint_R(hinge: S, u: vec3, th: S):
        K = wp.skew(u)
        return wp.identity(3, S) + hinge * (wp.sin(th) * K + (S(1.0) - wp.cos(th)) * (K * K))

    @func
    def joint_t(hinge: S, u: vec3, a: vec3, th: S, R: mat33):
        return hinge * (a - R * a) + (S(1.0) - hinge) * th * u

    @func
    def free_origin(m: Model, q: wp.array3d(dtype=S), k: int, e: int):
        o = vec3(S(0.0), S(0.0), S(0.0))
        if m.root_free != 0:
            a = m.f_qadr[m.b_free[0]]
            o = vec3(q[k, e, a], q[k, e, a + 1], q[k, e, a + 2])
        return o

    @func
    def kinematics(m: Model, q: wp.array3d(dtype=S), kq: int, k: int, e: int, o: vec3,
                   Xr: wp.array3d(dtype=mat33), Xt: wp.array3d(dtype=vec3),
                   Wr: wp.array3d(dtype=mat33), Wt: wp.array3d(dtype=vec3)):
        """Body frames X (rotation, translation relative to ``o``) and the world frames W just before each
        hinge/slide joint of the state in slot ``kq`` of ``q``, into slots ``[k, e, .]``; slot ``nb`` of X is
        the world, (1, -o)."""
        nb = m.nb
        Xr[k, e, nb] = wp.identity(3, S)
        Xt[k, e, nb] = -o
        for b in range(nb):
            p = m.b_parent[b]
            f = m.b_free[b]
            j0 = m.b_j0[b]
            j1 = m.b_j1[b]
            if f >= 0:
                a = m.f_qadr[f]
                qw = vec4(q[kq, e, a + 3], q[kq, e, a + 4], q[kq, e, a + 5], q[kq, e, a + 6])
                qn = qw / wp.length(qw)
                w = qn[0]
                x = qn[1]
                y = qn[2]
                z = qn[3]
                Rf = mat33(
                    S(1.0) - S(2.0) * (y * y + z * z), S(2.0) * (x * y - w * z), S(2.0) * (x * z + w * y),
                    S(2.0) * (x * y + w * z), S(1.0) - S(2.0) * (x * x + z * z), S(2.0) * (y * z - w * x),
                    S(2.0) * (x * z - w * y), S(2.0) * (y * z + w * x), S(1.0) - S(2.0) * (x * x + y * y),
                )
                pf = vec3(q[kq, e, a], q[kq, e, a + 1], q[kq, e, a + 2])
                Xr[k, e, b] = Xr[k, e, p] * Rf
                Xt[k, e, b] = Xr[k, e, p] * pf + Xt[k, e, p]
            elif j1 == j0:
                Xr[k, e, b] = Xr[k, e, p] * m.b_off_R[b]
                Xt[k, e, b] = Xr[k, e, p] * m.b_off_t[b] + Xt[k, e, p]
            else:
                for h in range(j0, j1):
                    if h == j0:
                        Wr[k, e, h] = Xr[k, e, p] * m.b_off_R[b]
                        Wt[k, e, h] = Xr[k, e, p] * m.b_off_t[b] + Xt[k, e, p]
                    else:
                        g = h - 1
                        thg = q[kq, e, m.h_qadr[g]] - m.h_qpos0[g]
                        Rg = joint_R(m.h_hinge[g], m.h_axis[g], thg)
                        tg = joint_t(m.h_hinge[g], m.h_axis[g], m.h_anchor[g], thg, Rg)
                        Wr[k, e, h] = Wr[k, e, g] * Rg
                        Wt[k, e, h] = Wr[k, e, g] * tg + Wt[k, e, g]
                hl = j1 - 1
                thl = q[kq, e, m.h_qadr[hl]] - m.h_qpos0[hl]
                Rl = joint_R(m.h_hinge[hl], m.h_axis[hl], thl)
                tl = joint_t(m.h_hinge[hl], m.h_axis[hl], m.h_anchor[hl], thl, Rl)
                Xr[k, e, b] = Wr[k, e, hl] * Rl
                Xt[k, e, b] = Wr[k, e, hl] * tl + Wt[k, e, hl]

    @func
    def subspaces(m: Model, k: int, e: int, ox: vec3, Xr: wp.array3d(dtype=mat33), Xt: wp.array3d(dtype=vec3),
                  Wr: wp.array3d(dtype=mat33), Wt: wp.array3d(dtype=vec3), Sv: wp.array3d(dtype=vec6)):
        """Motion subspace of every dof, world-aligned, about the reference point (translations minus ``ox``)."""
        for h in range(m.nh):
            R = Wr[k, e, h]
            axis = R * m.h_axis[h]
            anchor = R * m.h_anchor[h] + Wt[k, e, h] - ox
            hg = m.h_hinge[h]
            Sv[k, e, m.h_dof[h]] = sv(hg * axis, hg * wp.cross(anchor, axis) + (S(1.0) - hg) * axis)
        for f in range(m.nf):
            b = m.f_body[f]
            d = m.f_dof[f]
            R = Xr[k, e, b]
            t = Xt[k, e, b] - ox
            for i in range(3):
                one, zero = S(1.0), S(0.0)
                unit = vec3(wp.where(i == 0, one, zero), wp.where(i == 1, one, zero), wp.where(i == 2, one, zero))
                col = vec3(R[0, i], R[1, i], R[2, i])
                Sv[k, e, d + i] = sv(vec3(S(0.0), S(0.0), S(0.0)), unit)
                Sv[k, e, d + 3 + i] = sv(col, wp.cross(t, col))

    @func
    def body_inertia(m: Model, b: int, R: mat33, t: vec3):
        """(J about the reference point, first moment m c) of body b at rotation R, translation t."""
        mb = m.b_mass[b]
        c = R * m.b_ipos[b] + t
        cx = wp.skew(c)
        J = R * m.b_inertia[b] * wp.transpose(R) - mb * (cx * cx)
        return J, mb * c

    def mass(m: Model, q: wp.array3d(dtype=S), k: int, w: int,
             Xr: wp.array3d(dtype=mat33), Xt: wp.array3d(dtype=vec3), Wr: wp.array3d(dtype=mat33),
             Wt: wp.array3d(dtype=vec3), Sv: wp.array3d(dtype=vec6), IJ: wp.array3d(dtype=mat33),
             Ih: wp.array3d(dtype=vec3), Im: wp.array3d(dtype=S), F: wp.array3d(dtype=vec6),
             org: wp.array2d(dtype=vec3), M: wp.array3d(dtype=S)):
        """Mass matrix of window ``w`` from the state in slot ``k`` of ``q``: ``M[w, e] (nv * nv)``; the scratch
        and ``org`` (the reference point [m]) in slots ``w``."""
        e = wp.tid()
        o = free_origin(m, q, k, e)
        kinematics(m, q, k, w, e, o, Xr, Xt, Wr, Wt)
        ox = Xt[w, e, 0] * S(1 - m.root_free)
        org[w, e] = o + ox
        subspaces(m, w, e, ox, Xr, Xt, Wr, Wt, Sv)
        nb = m.nb
        for i in range(nb):
            b = nb - 1 - i  # children first: each body's composite inertia is complete when it is read
            J, c = body_inertia(m, b, Xr[w, e, b], Xt[w, e, b] - ox)
            IJ[w, e, b] += J
            Ih[w, e, b] += c
            Im[w, e, b] += m.b_mass[b]
            p = m.b_parent[b]
            IJ[w, e, p] += IJ[w, e, b]
            Ih[w, e, p] += Ih[w, e, b]
            Im[w, e, p] += Im[w, e, b]
        nv = m.nv
        for j in range(nv):
            bj = m.d_body[j]
            F[w, e, j] = inertia_times(IJ[w, e, bj], Ih[w, e, bj], Im[w, e, bj], Sv[w, e, j])
        for i in range(nv):
            for j in range(nv):
                if i == j:
                    M[w, e, i * nv + j] = wp.dot(Sv[w, e, i], F[w, e, j]) + m.d_armature[i]
                elif m.d_anc[i * nv + j] != 0:
                    M[w, e, i * nv + j] = wp.dot(Sv[w, e, i], F[w, e, j])
                elif m.d_anc[j * nv + i] != 0:
                    M[w, e, i * nv + j] = wp.dot(Sv[w, e, j], F[w, e, i])
                else:
                    M[w, e, i * nv + j] = S(0.0)

    def invert(nv: int, w: int, M: wp.array3d(dtype=S), L: wp.array2d(dtype=S), Li: wp.array2d(dtype=S),
               Minv: wp.array3d(dtype=S)):
        """``Minv[w, e] = M[w, e]^-1`` by Cholesky (forward only)."""
        e = wp.tid()
        for j in range(nv):
            for i in range(j, nv):
                s = M[w, e, i * nv + j]
                for r in range(j):
                    s = s - L[e, i * nv + r] * L[e, j * nv + r]
                if i == j:
                    L[e, i * nv + j] = wp.sqrt(s)
                else:
                    L[e, i * nv + j] = s / L[e, j * nv + j]
        for i in range(nv):  # Li = L^-1, row by row
            for c in range(nv):
                s = S(0.0)
                if i == c:
                    s = S(1.0)
                for r in range(i):
                    s = s - L[e, i * nv + r] * Li[e, r * nv + c]
                Li[e, i * nv + c] = s / L[e, i * nv + i]
        for i in range(nv):
            for j in range(nv):
                s = S(0.0)
                for r in range(nv):
                    s = s + Li[e, r * nv + i] * Li[e, r * nv + j]
                Minv[w, e, i * nv + j] = s

    def substep(m: Model, Q: wp.array3d(dtype=S), V: wp.array3d(dtype=S), tau: wp.array2d(dtype=S),
                Minv: wp.array3d(dtype=S), k: int, w: int, dt: S, contact_on: int, limits_on: int,
                Xr: wp.array3d(dtype=mat33), Xt: wp.array3d(dtype=vec3), Wr: wp.array3d(dtype=mat33),
                Wt: wp.array3d(dtype=vec3), Sv: wp.array3d(dtype=vec6), Vb: wp.array3d(dtype=vec6),
                Ab: wp.array3d(dtype=vec6), Vd: wp.array3d(dtype=vec6), Fb: wp.array3d(dtype=vec6),
                rhs: wp.array3d(dtype=S), acc: wp.array3d(dtype=S)):
        """Semi-implicit Euler from slot ``k`` of (Q, V) into slot ``k + 1``, with the inverse of window ``w``."""
        e = wp.tid()
        o = free_origin(m, Q, k, e)
        kinematics(m, Q, k, k, e, o, Xr, Xt, Wr, Wt)
        ox = Xt[k, e, 0] * S(1 - m.root_free)
        origin = o + ox
        subspaces(m, k, e, ox, Xr, Xt, Wr, Wt, Sv)
        nb = m.nb
        nv = m.nv
        z3 = vec3(S(0.0), S(0.0), S(0.0))
        Vb[k, e, nb] = sv(z3, z3)
        Ab[k, e, nb] = sv(z3, m.a0)
        # body velocities v_b and bias accelerations a_b (qdd = 0), parents first
        for b in range(nb):
            p = m.b_parent[b]
            d0 = m.b_d0[b]
            d1 = m.b_d1[b]
            Ab[k, e, b] += Ab[k, e, p]
            if d1 == d0:
                Vb[k, e, b] = Vb[k, e, p]
            else:
                for d in range(d0, d1):
                    sq = Sv[k, e, d] * V[k, e, d]
                    if d == d0:
                        Vd[k, e, d] = Vb[k, e, p] + sq
                    else:
                        Vd[k, e, d] = Vd[k, e, d - 1] + sq
                    Ab[k, e, b] += cross_motion(Vd[k, e, m.d_vsrc[d]], sq)
                Vb[k, e, b] = Vd[k, e, d1 - 1]
        # ground contact: minus the contact force of each point on its body's force
        for c in range(m.nc * contact_on):
            b = m.c_body[c]
            pc = Xr[k, e, b] * m.c_pos[c] + Xt[k, e, b] - ox - vec3(S(0.0), S(0.0), m.c_dist[c])
            height = pc[2] + origin[2] - m.ground
            v6 = Vb[k, e, b]
            vel = bot(v6) + wp.cross(top(v6), pc)
            depth = wp.max(-height, S(0.0))
            fn = (m.ke - m.kd * wp.min(vel[2], S(0.0))) * depth
            vt = vec3(vel[0], vel[1], S(0.0))
            vt2 = wp.dot(vt, vt)
            moving = vt2 > S(1.0e-12)
            inv_norm = S(1.0) / wp.sqrt(wp.where(moving, vt2, S(1.0)))
            coef_m = wp.where(moving, wp.min(m.mu * m.ke * depth * inv_norm, m.kf), m.kf)
            coef = wp.where(depth > S(0.0), coef_m, S(0.0))
            force = vec3(S(0.0), S(0.0), fn) - coef * vt
            Fb[k, e, b] += -sv(wp.cross(pc, force), force)
        # Newton-Euler, children first: subtree force of each body, complete when read
        for i in range(nb):
            b = nb - 1 - i
            J, cm = body_inertia(m, b, Xr[k, e, b], Xt[k, e, b] - ox)
            mb = m.b_mass[b]
            vb = Vb[k, e, b]
            fb = inertia_times(J, cm, mb, Ab[k, e, b]) + cross_force(vb, inertia_times(J, cm, mb, vb))
            Fb[k, e, b] += fb
            Fb[k, e, m.b_parent[b]] += Fb[k, e, b]
        # generalized force: tau + passive - bias
        for d in range(nv):
            rhs[k, e, d] += tau[e, d] - m.d_damping[d] * V[k, e, d] - wp.dot(Sv[k, e, d], Fb[k, e, m.d_body[d]])
        for h in range(m.nh):
            qh = Q[k, e, m.h_qadr[h]]
            dh = m.h_dof[h]
            qdh = V[k, e, dh]
            lim = m.lim_ke * (wp.clamp(qh, m.h_lo[h], m.h_hi[h]) - qh)
            outside = (qh < m.h_lo[h]) or (qh > m.h_hi[h])
            damp = wp.where(m.lim_violated == 0 or outside, m.lim_kd * qdh, S(0.0))
            rhs[k, e, dh] += -m.h_stiff[h] * (qh - m.h_springref[h]) + S(limits_on) * (lim - damp)
        for i in range(nv):
            for j in range(nv):
                acc[k, e, i] += Minv[w, e, i * nv + j] * rhs[k, e, j]
        # semi-implicit Euler: velocities first, positions from the new velocities
        for d in range(nv):
            V[k + 1, e, d] = V[k, e, d] + dt * acc[k, e, d]
        for h in range(m.nh):
            a = m.h_qadr[h]
            Q[k + 1, e, a] = Q[k, e, a] + dt * V[k + 1, e, m.h_dof[h]]
        for f in range(m.nf):
            a = m.f_qadr[f]
            d = m.f_dof[f]
            for i in range(3):
                Q[k + 1, e, a + i] = Q[k, e, a + i] + dt * V[k + 1, e, d + i]
            qw = vec4(Q[k, e, a + 3], Q[k, e, a + 4], Q[k, e, a + 5], Q[k, e, a + 6])
            om = vec3(V[k + 1, e, d + 3], V[k + 1, e, d + 4], V[k + 1, e, d + 5])
            # q (0, w): Hamilton product with a pure quaternion
            dq = vec4(
                -qw[1] * om[0] - qw[2] * om[1] - qw[3] * om[2],
                qw[0] * om[0] + qw[2] * om[2] - qw[3] * om[1],
                qw[0] * om[1] - qw[1] * om[2] + qw[3] * om[0],
                qw[0] * om[2] + qw[1] * om[1] - qw[2] * om[0],
            )
            qs = qw + (S(0.5) * dt) * dq
            qn = qs / wp.length(qs)
            for i in range(4):
                Q[k + 1, e, a + 3 + i] = qn[i]

    return {
        "S": S, "vec3": vec3, "vec6": vec6, "mat33": mat33, "Model": Model, "module": module,
        "mass": kernel(mass), "invert": kernel(invert, backward=False), "substep": kernel(substep),
    }


def _contiguous_ranges(owner: np.ndarray, n: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """[start, end) of each owner's items (``owner (m,)`` nondecreasing): (n,), (n,)."""
    owner = np.asarray(owner, dtype=np.int64)
    if len(owner) and np.any(np.diff(owner) < 0):
        raise ValueError(f"the Warp simulator needs each body's {what} consecutive")
    start = np.searchsorted(owner, np.arange(n), side="left")
    end = np.searchsorted(owner, np.arange(n), side="right")
    return start, end


class _Run:
    """The buffers of one :meth:`WarpSimulator.step` call: every substep's state and scratch in its own slot
    (leading index k), the mass-matrix windows' in theirs (w). Torch tensors (torch's allocator) and the Warp
    arrays that view them."""

    def __init__(self, sim: "WarpSimulator", B: int, K: int, W: int) -> None:
        m = sim.model
        nb1, nh1, nv = m.nb + 1, max(m.nh, 1), m.nv
        dt = dict(dtype=sim.dtype, device=sim.device)
        self.B, self.K, self.W = B, K, W
        self.shapes = {
            "Q": (K + 1, B, m.nq), "V": (K + 1, B, nv), "tau": (B, nv),
            "Xr": (K, B, nb1, 3, 3), "Xt": (K, B, nb1, 3), "Wr": (K, B, nh1, 3, 3), "Wt": (K, B, nh1, 3),
            "Sv": (K, B, nv, 6), "Vb": (K, B, nb1, 6), "Ab": (K, B, nb1, 6), "Vd": (K, B, nv, 6),
            "Fb": (K, B, nb1, 6), "rhs": (K, B, nv), "acc": (K, B, nv),
            "mXr": (W, B, nb1, 3, 3), "mXt": (W, B, nb1, 3), "mWr": (W, B, nh1, 3, 3), "mWt": (W, B, nh1, 3),
            "mSv": (W, B, nv, 6), "IJ": (W, B, nb1, 3, 3), "Ih": (W, B, nb1, 3), "Im": (W, B, nb1),
            "F": (W, B, nv, 6), "org": (W, B, 3), "M": (W, B, nv * nv), "Minv": (W, B, nv * nv),
        }
        self.t = {name: torch.zeros(shape, **dt) for name, shape in self.shapes.items()}
        self.L = torch.zeros(B, nv * nv, **dt)  # the inverse's factor and its inverse: forward-only scratch
        self.Li = torch.zeros(B, nv * nv, **dt)
        self.w = sim._views(self.t)

    def zeros_like(self) -> dict[str, torch.Tensor]:
        return {name: torch.zeros_like(x) for name, x in self.t.items()}


class _Step(torch.autograd.Function):
    """``(qpos, qvel, tau) -> (qpos, qvel)`` after ``substeps`` substeps; the backward runs Warp's adjoint
    kernels in reverse order over fresh zeroed adjoint buffers (the forward's buffers are kept in ``ctx``, so a
    second backward of the same graph gives the same gradient)."""

    @staticmethod
    def forward(ctx, qpos, qvel, tau, sim, h, substeps, every):  # type: ignore[override]
        run = sim._forward(qpos.detach(), qvel.detach(), tau.detach(), float(h), int(substeps), int(every))
        ctx.sim, ctx.run, ctx.h, ctx.every = sim, run, float(h), int(every)
        return run.t["Q"][substeps].clone(), run.t["V"][substeps].clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gq, gv):  # type: ignore[override]
        gqpos, gqvel, gtau = ctx.sim._backward(ctx.run, gq, gv, ctx.h, ctx.every)
        return gqpos, gqvel, gtau, None, None, None, None


class WarpSimulator:
    """The model of :class:`tasks.dynamics.Simulator` in Warp kernels (module docstring), for batches of states.

    Args:
        model: the articulated model (:func:`tasks.model.load_model`).
        device: CPU or CUDA; dtype: float32 or float64 (one Warp module per precision).
        contact, limits: as :class:`tasks.dynamics.Simulator`'s (None: no ground contact / no joint limits).

    Raises ImportError when Warp is not installed, ValueError for a model layout the kernels do not take (each
    body's joints, dofs consecutive; parents before children, as MuJoCo orders them).
    """

    def __init__(self, model: ArticulatedModel, *, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, contact: ContactParams | None = None,
                 limits: LimitParams | None = None) -> None:
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        device = torch.device(device)
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        if device.type not in ("cpu", "cuda"):
            raise ValueError(f"device must be a CPU or CUDA device, got {device}")
        nb, nh, nf, nv, nc = model.nb, model.nh, model.nf, model.nv, model.nc
        if np.any(model.body_parent >= np.arange(nb)):
            raise ValueError("the Warp simulator needs every body's parent numbered before it")
        self.model, self.device, self.dtype = model, device, dtype
        self.contact = contact if (contact is not None and nc > 0) else None
        self.limits = limits
        self.nq, self.nv, self.nb = model.nq, nv, nb
        wp = _warp()
        self._wp = wp
        self._k = _kernels("float32" if dtype == torch.float32 else "float64")
        self._wp_device = wp.device_from_torch(device)
        self._streams: dict[int, Any] = {}
        k = self._k
        keep: list[torch.Tensor] = []

        def arr(x, wdtype=None, *, integer=False, width=None):
            x = np.asarray(x, dtype=np.int32 if integer else np.float64)
            if x.shape[0] == 0:  # Warp arrays of zero length: pad (the loops' counts stay 0)
                x = np.zeros((1, *x.shape[1:]), dtype=x.dtype)
            t = torch.as_tensor(x, dtype=torch.int32 if integer else dtype, device=device).contiguous()
            keep.append(t)
            return wp.from_torch(t, dtype=wdtype if wdtype is not None else (wp.int32 if integer else k["S"]))

        j0, j1 = _contiguous_ranges(model.hs_body, nb, "hinge/slide joints")
        d0, d1 = _contiguous_ranges(model.dof_body, nb, "dofs")
        vsrc = np.arange(nv)
        for d in model.free_dof:
            vsrc[d + 3 : d + 6] = d + 2  # a free joint's rotation axes move with its translation only
        st = k["Model"]()
        st.nb, st.nh, st.nf, st.nv, st.nc = nb, nh, nf, nv, nc
        st.root_free = int(nb > 0 and model.body_free[0] >= 0)
        st.b_parent = arr(np.where(model.body_parent < 0, nb, model.body_parent), integer=True)
        st.b_off_R = arr(model.body_rot, k["mat33"])
        st.b_off_t = arr(model.body_pos, k["vec3"])
        st.b_free = arr(model.body_free, integer=True)
        st.b_j0, st.b_j1 = arr(j0, integer=True), arr(j1, integer=True)
        st.b_d0, st.b_d1 = arr(d0, integer=True), arr(d1, integer=True)
        st.b_mass = arr(model.body_mass)
        st.b_ipos = arr(model.body_ipos, k["vec3"])
        st.b_inertia = arr(model.body_inertia, k["mat33"])
        st.h_hinge = arr(model.hs_hinge.astype(np.float64))
        st.h_axis = arr(model.hs_axis.reshape(nh, 3), k["vec3"])
        st.h_anchor = arr(model.hs_anchor.reshape(nh, 3), k["vec3"])
        st.h_qadr, st.h_dof = arr(model.hs_qadr, integer=True), arr(model.hs_dof, integer=True)
        st.h_qpos0 = arr(model.hs_qpos0)
        st.h_stiff, st.h_springref = arr(model.hs_stiffness), arr(model.hs_springref)
        st.h_lo = arr(np.where(model.hs_limited, model.hs_range[:, 0], -_BIG) if nh else np.zeros(0))
        st.h_hi = arr(np.where(model.hs_limited, model.hs_range[:, 1], _BIG) if nh else np.zeros(0))
        st.f_body, st.f_qadr = arr(model.free_body, integer=True), arr(model.free_qadr, integer=True)
        st.f_dof = arr(model.free_dof, integer=True)
        st.d_body, st.d_vsrc = arr(model.dof_body, integer=True), arr(vsrc, integer=True)
        st.d_damping, st.d_armature = arr(model.dof_damping), arr(model.dof_armature)
        st.d_anc = arr(model.dof_anc.reshape(-1) != 0, integer=True)
        st.c_body = arr(model.contact_body, integer=True)
        st.c_pos = arr(model.contact_pos.reshape(nc, 3), k["vec3"])
        st.c_dist = arr(model.contact_dist)
        S = k["S"]
        st.a0 = k["vec3"](*(-model.gravity).tolist())
        cp = self.contact
        st.ground = S(float(model.ground_height or 0.0))
        st.ke, st.kd, st.kf, st.mu = (S(float(getattr(cp, n) if cp else 0.0)) for n in ("ke", "kd", "kf", "mu"))
        lp = limits
        st.lim_ke = S(float(lp.ke if lp else 0.0))
        st.lim_kd = S(float(lp.kd if lp else 0.0))
        st.lim_violated = int(lp is not None and lp.damping == "violated")
        self._model_struct, self._keep = st, keep
        self._null_struct = k["Model"]()
        wp.load_module(k["module"], device=self._wp_device)

    # ------------------------------------------------------------------------------------------------------
    _WDTYPES: ClassVar[dict[str, str]] = {
        "Xr": "mat33", "Xt": "vec3", "Wr": "mat33", "Wt": "vec3", "Sv": "vec6", "Vb": "vec6", "Ab": "vec6",
        "Vd": "vec6", "Fb": "vec6", "mXr": "mat33", "mXt": "vec3", "mWr": "mat33", "mWt": "vec3", "mSv": "vec6",
        "IJ": "mat33", "Ih": "vec3", "F": "vec6", "org": "vec3"}

    def _views(self, tensors: dict[str, torch.Tensor]) -> dict[str, Any]:
        k = self._k
        return {n: self._wp.from_torch(t, dtype=k[self._WDTYPES[n]] if n in self._WDTYPES else k["S"])
                for n, t in tensors.items()}

    def _stream_scope(self):
        """Warp's work on torch's current stream, inside ``ScopedCapture(external=True)`` while torch captures a
        CUDA graph (:func:`diffrender.raytrace.warp_on_torch_stream`)."""
        return warp_on_torch_stream(self._wp, self.device, self._wp_device, self._streams)

    def _mass_inputs(self, w: dict, k: int, win: int) -> list:
        return [self._model_struct, w["Q"], k, win, w["mXr"], w["mXt"], w["mWr"], w["mWt"], w["mSv"], w["IJ"],
                w["Ih"], w["Im"], w["F"], w["org"], w["M"]]

    def _substep_inputs(self, w: dict, k: int, win: int, h: float, contact: bool, limits: bool) -> list:
        return [self._model_struct, w["Q"], w["V"], w["tau"], w["Minv"], k, win, h,
                int(contact and self.contact is not None), int(limits and self.limits is not None),
                w["Xr"], w["Xt"], w["Wr"], w["Wt"], w["Sv"], w["Vb"], w["Ab"], w["Vd"], w["Fb"], w["rhs"], w["acc"]]

    def _factor(self, run: _Run, k: int, win: int) -> None:
        wp, w = self._wp, run.w
        wp.launch(self._k["mass"], dim=run.B, inputs=self._mass_inputs(w, k, win), device=self._wp_device)
        wp.launch(self._k["invert"], dim=run.B, device=self._wp_device, inputs=[
            self.nv, win, w["M"], wp.from_torch(run.L), wp.from_torch(run.Li), w["Minv"]])

    def _check(self, qpos: torch.Tensor, qvel: torch.Tensor, tau: torch.Tensor) -> int:
        B = qpos.shape[0]
        for name, x, n in (("qpos", qpos, self.nq), ("qvel", qvel, self.nv), ("tau", tau, self.nv)):
            if x.ndim != 2 or tuple(x.shape) != (B, n):
                raise ValueError(f"{name} must have shape ({B}, {n}), got {tuple(x.shape)}")
            if x.dtype != self.dtype or x.device != self.device:
                raise ValueError(f"{name} is {x.dtype} on {x.device}; the Warp simulator runs {self.dtype} on "
                                 f"{self.device}")
        return B

    def _forward(self, qpos, qvel, tau, h: float, K: int, every: int, *, contact: bool = True,
                 limits: bool = True) -> _Run:
        B = self._check(qpos, qvel, tau)
        run = _Run(self, B, K, -(-K // every))
        run.t["Q"][0].copy_(qpos)
        run.t["V"][0].copy_(qvel)
        run.t["tau"].copy_(tau)
        wp = self._wp
        with self._stream_scope():
            for k in range(K):
                if k % every == 0:
                    self._factor(run, k, k // every)
                wp.launch(self._k["substep"], dim=B, device=self._wp_device,
                          inputs=self._substep_inputs(run.w, k, k // every, h, contact, limits))
        return run

    def _backward(self, run: _Run, gq, gv, h: float, every: int):
        K, wp = run.K, self._wp
        adj_t = run.zeros_like()
        if gq is not None:
            adj_t["Q"][K].copy_(gq)
        if gv is not None:
            adj_t["V"][K].copy_(gv)
        adj = self._views(adj_t)
        null = self._null_struct
        with self._stream_scope():
            for k in range(K - 1, -1, -1):
                win = k // every
                adj_in = self._substep_inputs(adj, k, win, 0.0, False, False)
                adj_in[0] = null
                wp.launch(self._k["substep"], dim=run.B, device=self._wp_device, adjoint=True,
                          inputs=self._substep_inputs(run.w, k, win, h, True, True), adj_inputs=adj_in)
                if k % every == 0:
                    # Minv = M^-1 was computed outside the adjoint: d(M^-1) = -M^-1 dM M^-1 (M^-1 symmetric)
                    n = self.nv
                    Minv = run.t["Minv"][win].view(run.B, n, n)
                    gMinv = adj_t["Minv"][win].view(run.B, n, n)
                    adj_t["M"][win].copy_((-(Minv @ gMinv @ Minv)).reshape(run.B, n * n))
                    adj_in = self._mass_inputs(adj, k, win)
                    adj_in[0] = null
                    wp.launch(self._k["mass"], dim=run.B, device=self._wp_device, adjoint=True,
                              inputs=self._mass_inputs(run.w, k, win), adj_inputs=adj_in)
        return adj_t["Q"][0], adj_t["V"][0], adj_t["tau"]

    # ------------------------------------------------------------------------------------------------------
    @torch.compiler.disable
    def step(self, qpos: torch.Tensor, qvel: torch.Tensor, tau: torch.Tensor, h: float, substeps: int,
             mass_matrix_every: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``substeps`` semi-implicit Euler substeps of ``h`` [s] with the generalized force ``tau (B, nv)``
        held, the mass matrix and its inverse computed every ``mass_matrix_every`` substeps (from the first).
        qpos: (B, nq), qvel: (B, nv) -> (qpos, qvel), differentiable with respect to all three inputs (Warp's
        adjoint kernels). Kept out of torch.compile's graphs (a graph break at each call)."""
        if not (isinstance(substeps, int) and substeps >= 1):
            raise ValueError(f"substeps must be a positive int, got {substeps!r}")
        if not (isinstance(mass_matrix_every, int) and mass_matrix_every >= 1):
            raise ValueError(f"mass_matrix_every must be a positive int, got {mass_matrix_every!r}")
        return _Step.apply(qpos.contiguous(), qvel.contiguous(), tau.contiguous(), self, h, substeps,
                           mass_matrix_every)

    def _static(self, qpos: torch.Tensor, qvel: torch.Tensor | None = None, tau: torch.Tensor | None = None,
                *, substep: bool = False) -> _Run:
        qvel = qpos.new_zeros(qpos.shape[0], self.nv) if qvel is None else qvel
        tau = qpos.new_zeros(qpos.shape[0], self.nv) if tau is None else tau
        with torch.no_grad():
            if substep:
                return self._forward(qpos.detach(), qvel.detach(), tau.detach(), 0.0, 1, 1, contact=False,
                                     limits=False)
            B = self._check(qpos.detach(), qvel, tau)
            run = _Run(self, B, 0, 1)
            run.t["Q"][0].copy_(qpos)
            with self._stream_scope():
                self._factor(run, 0, 0)
            return run

    def mass_matrix(self, qpos: torch.Tensor) -> torch.Tensor:
        """Joint-space inertia with armature (MuJoCo's ``qM``, dense), no gradient. (B, nq) -> (B, nv, nv)."""
        return self._static(qpos).t["M"][0].view(-1, self.nv, self.nv).clone()

    def frames(self, qpos: torch.Tensor) -> Frames:
        """Forward kinematics as :meth:`tasks.dynamics.Simulator.frames` (no gradient). qpos: (B, nq)."""
        run = self._static(qpos)
        B, nb = run.B, self.nb
        ox = run.t["mXt"][0, :, 0] * (0.0 if self.model.body_free[0] >= 0 else 1.0)
        X = torch.zeros(B, nb, 4, 4, dtype=self.dtype, device=self.device)
        X[..., :3, :3] = run.t["mXr"][0, :, :nb]
        X[..., :3, 3] = run.t["mXt"][0, :, :nb] - ox[:, None]
        X[..., 3, 3] = 1.0
        return Frames(X, run.t["org"][0].clone(), run.t["mSv"][0].clone())

    def forward_dynamics(self, qpos: torch.Tensor, qvel: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """Joint accelerations with contacts and limits off, as :meth:`tasks.dynamics.Simulator.forward_dynamics`
        (no gradient). qpos: (B, nq), qvel, tau: (B, nv) -> qacc (B, nv)."""
        return self._static(qpos, qvel, tau, substep=True).t["acc"][0].clone()
