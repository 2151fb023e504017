"""The Warp kernels of :class:`tasks.warp_sim.WarpSimulator`: the model of :mod:`tasks.dynamics`, one thread an
environment, a launch a substep.

Kernels (one module per precision, so a float32 run compiles no float64 code):

* ``mass``: forward kinematics, composite inertias and the dense ``M (nv, nv)`` of every environment (one launch at
  the start of each caching window);
* ``invert``: its Cholesky inverse, forward only (the gradient reaches ``M`` as ``gM = -M^-1 gMinv M^-1``, the
  same expression as :class:`tasks.dynamics._InverseSolve`'s, applied in torch between the adjoint launches);
* ``substep``: kinematics, body velocities and bias accelerations, contacts, Newton-Euler, passive forces,
  ``qacc = M^-1 rhs`` and the integrator.

The loops over bodies, joints, dofs and contacts are dynamic (compile time does not grow with the model). Warp's
adjoint of a dynamic loop does not restore values a loop carries in registers (a register sum gets a zero
gradient), so every loop-carried value lives in an array slot: written once, or accumulated with ``+=`` (an atomic
add, which Warp skips when it replays the forward inside the adjoint) and read only once complete. Each substep has
its own slots (index ``k`` of every buffer), so the adjoint of substep ``k`` replays exactly its own forward.
"""

# Annotations are evaluated (no ``from __future__ import annotations``): Warp reads the kernels' closure types.
# Literals in kernels are typed (``S(0.0)``) so that one source serves float32 and float64.

import functools
from typing import Any

__all__ = ["MODEL_ARRAYS", "kernels", "load_warp"]

#: The model struct's arrays, name -> element type: "int" (int32) or the precision's "S" (scalar), "vec3", "mat33".
#: One entry an element of the articulated model (b_ a body, h_ a hinge/slide joint, f_ a free joint, d_ a dof,
#: c_ a contact point); :class:`tasks.warp_sim.WarpSimulator` fills each by name.
MODEL_ARRAYS = {
    "b_parent": "int",  # parent body, nb for the world
    "b_off_R": "mat33", "b_off_t": "vec3",
    "b_free": "int",  # free joint index or -1
    "b_j0": "int", "b_j1": "int",  # hinge/slide joints [j0, j1) of the body
    "b_d0": "int", "b_d1": "int",  # dofs [d0, d1) of the body
    "b_mass": "S", "b_ipos": "vec3", "b_inertia": "mat33",
    "h_hinge": "S",  # 1 hinge, 0 slide
    "h_axis": "vec3", "h_anchor": "vec3", "h_qadr": "int", "h_dof": "int", "h_qpos0": "S", "h_stiff": "S",
    "h_springref": "S", "h_lo": "S", "h_hi": "S",
    "f_body": "int", "f_qadr": "int", "f_dof": "int",
    "d_body": "int",
    "d_vsrc": "int",  # the dof whose running velocity moves this dof's axis (dS/dt)
    "d_damping": "S", "d_armature": "S",
    "d_anc": "int",  # (nv * nv) [i * nv + j] = 1: i ancestor-or-self of j
    "c_body": "int", "c_pos": "vec3", "c_dist": "S",
}


@functools.cache
def load_warp():
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    else:
        wp.config.quiet = True
    wp.init()
    return wp


@functools.cache
def kernels(precision: str) -> dict[str, Any]:
    """The three kernels and the model struct for ``precision`` ("float32" or "float64"), in one Warp module."""
    wp = load_warp()
    S = wp.float32 if precision == "float32" else wp.float64
    vec3 = wp.types.vector(3, S)
    vec4 = wp.types.vector(4, S)
    vec6 = wp.types.vector(6, S)
    mat33 = wp.types.matrix((3, 3), S)
    module = wp.get_module(f"{__name__}.{precision}")

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
        a0: vec3  # -gravity: the base's upward acceleration
        ground: S
        ke: S
        kd: S
        kf: S
        mu: S
        lim_ke: S
        lim_kd: S
        lim_violated: int  # 0: limit damping on every hinge/slide dof (dflex), 1: only outside the range

    element = {"int": int, "S": S, "vec3": vec3, "mat33": mat33}
    Model.__annotations__.update({name: wp.array(dtype=element[kind]) for name, kind in MODEL_ARRAYS.items()})
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
    def joint_motion(m: Model, q: wp.array3d(dtype=S), kq: int, e: int, h: int):
        """(rotation, translation) of hinge/slide joint h at the state in slot ``kq`` of ``q``."""
        th = q[kq, e, m.h_qadr[h]] - m.h_qpos0[h]
        R = joint_R(m.h_hinge[h], m.h_axis[h], th)
        return R, joint_t(m.h_hinge[h], m.h_axis[h], m.h_anchor[h], th, R)

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
                        Rg, tg = joint_motion(m, q, kq, e, g)
                        Wr[k, e, h] = Wr[k, e, g] * Rg
                        Wt[k, e, h] = Wr[k, e, g] * tg + Wt[k, e, g]
                hl = j1 - 1
                Rl, tl = joint_motion(m, q, kq, e, hl)
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
