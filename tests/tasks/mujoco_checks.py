"""MuJoCo as the simulators' reference: random states, MuJoCo's quantities of them, and the float64 comparison that
the torch simulator (tasks.dynamics) and the Warp one (tasks.warp_sim) both pass."""

from __future__ import annotations

import mujoco
import numpy as np
import torch


def random_states(m: mujoco.MjModel, model, n: int, seed: int):
    """Random (qpos, qvel, tau) with random root orientations; joint angles spread over +-1.5 rad."""
    rng = np.random.default_rng(seed)
    qs, vs, ts = [], [], []
    for _ in range(n):
        q = m.qpos0 + rng.uniform(-1.5, 1.5, m.nq)
        for a in model.free_qadr:
            q[a : a + 3] = rng.uniform(-3, 3, 3)
            quat = rng.normal(size=4)
            q[a + 3 : a + 7] = quat / np.linalg.norm(quat)
        qs.append(q)
        vs.append(rng.uniform(-3, 3, m.nv))
        ts.append(rng.uniform(-100, 100, m.nv))
    return np.array(qs), np.array(vs), np.array(ts)


def mujoco_reference(m: mujoco.MjModel, qs, vs, ts):
    """mj_forward with constraints disabled and qfrc_applied = tau: qacc, xpos, xmat, dense M."""
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    d = mujoco.MjData(m)
    out = {"qacc": [], "xpos": [], "xmat": [], "M": []}
    for q, v, t in zip(qs, vs, ts):
        d.qpos[:], d.qvel[:], d.qfrc_applied[:] = q, v, t
        mujoco.mj_forward(m, d)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        out["qacc"].append(d.qacc.copy())
        out["xpos"].append(d.xpos[1:].copy())
        out["xmat"].append(d.xmat[1:].reshape(-1, 3, 3).copy())
        out["M"].append(M)
    return {k: torch.tensor(np.array(v)) for k, v in out.items()}


def assert_float64_matches_mujoco(sim, m: mujoco.MjModel, model) -> None:
    """A float64 simulator of ``model`` (MuJoCo's ``m``) on 16 random states: forward_dynamics (constraints off) to
    1e-8 relative, mass_matrix to 1e-9 relative, the body frames to 1e-10 of MuJoCo's."""
    qs, vs, ts = random_states(m, model, 16, seed=1)
    ref = mujoco_reference(m, qs, vs, ts)
    q, v, t = (torch.tensor(x) for x in (qs, vs, ts))
    qacc = sim.forward_dynamics(q, v, t)
    rel = ((qacc - ref["qacc"]).norm(dim=-1) / ref["qacc"].norm(dim=-1)).max().item()
    assert rel < 1e-8, f"qacc relative error {rel:.3e}"
    M = sim.mass_matrix(q)
    assert torch.allclose(M, ref["M"], rtol=1e-9, atol=1e-10 * ref["M"].abs().max())
    fr = sim.frames(q)
    assert torch.allclose(fr.pos, ref["xpos"], atol=1e-10)
    assert torch.allclose(fr.rot, ref["xmat"], atol=1e-10)
