"""The simulator of :mod:`tasks.dynamics` as NVIDIA Warp kernels (:mod:`tasks.warp_kernels`): one thread an
environment, a launch a substep.

:class:`WarpSimulator` evaluates the same model as :class:`tasks.dynamics.Simulator` (forward kinematics with the
floating-base reference point, the joint-space inertia with armature, its inverse cached every
``mass_matrix_every`` substeps, Newton-Euler bias forces, damping and springs, the joint-limit penalty, dflex's
ground contact and the semi-implicit Euler update) and exposes dflex's boundary,
:meth:`WarpSimulator.step` ``(qpos, qvel, tau, h, substeps, mass_matrix_every) -> (qpos, qvel)``, as a
``torch.autograd.Function``.

A control step of ``K`` substeps and ``W`` windows is ``K + 2 W`` launches forward (``mass`` and ``invert`` once a
window, ``substep`` once a substep) and ``K + W`` adjoint launches (plus ``W`` torch products) backward. The
buffers come from torch's allocator, one slot a substep (:class:`_Run`), the adjoint buffers are fresh zeros in
every backward (a repeated backward gives the same gradient), and the launches go on torch's current stream, taken
at call time, inside ``ScopedCapture(external=True)`` while torch captures a CUDA graph.

Gradients flow into ``qpos``, ``qvel`` and ``tau``. :meth:`WarpSimulator.frames`,
:meth:`~WarpSimulator.mass_matrix` and :meth:`~WarpSimulator.forward_dynamics` give the torch simulator's values
with its conventions, without gradient.
"""

from typing import Any, ClassVar

import numpy as np
import torch

from diffrender.raytrace import warp_on_torch_stream

from .dynamics import ContactParams, Frames, LimitParams
from .model import ArticulatedModel
from .warp_kernels import MODEL_ARRAYS, kernels, load_warp

__all__ = ["WarpSimulator"]

_BIG = 1.0e10  # "unlimited" joint range, as tasks.dynamics: clamp(q, -big, big) == q


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
        wp = load_warp()
        self._wp = wp
        self._k = kernels("float32" if dtype == torch.float32 else "float64")
        self._wp_device = wp.device_from_torch(device)
        self._streams: dict[int, Any] = {}
        k = self._k
        keep: list[torch.Tensor] = []

        def arr(x, kind: str):
            integer = kind == "int"
            x = np.asarray(x, dtype=np.int32 if integer else np.float64)
            if x.shape[0] == 0:  # Warp arrays of zero length: pad (the loops' counts stay 0)
                x = np.zeros((1, *x.shape[1:]), dtype=x.dtype)
            t = torch.as_tensor(x, dtype=torch.int32 if integer else dtype, device=device).contiguous()
            keep.append(t)
            return wp.from_torch(t, dtype=wp.int32 if integer else k[kind])

        j0, j1 = _contiguous_ranges(model.hs_body, nb, "hinge/slide joints")
        d0, d1 = _contiguous_ranges(model.dof_body, nb, "dofs")
        vsrc = np.arange(nv)
        for d in model.free_dof:
            vsrc[d + 3 : d + 6] = d + 2  # a free joint's rotation axes move with its translation only
        arrays = {
            "b_parent": np.where(model.body_parent < 0, nb, model.body_parent), "b_off_R": model.body_rot,
            "b_off_t": model.body_pos, "b_free": model.body_free, "b_j0": j0, "b_j1": j1, "b_d0": d0, "b_d1": d1,
            "b_mass": model.body_mass, "b_ipos": model.body_ipos, "b_inertia": model.body_inertia,
            "h_hinge": model.hs_hinge.astype(np.float64), "h_axis": model.hs_axis.reshape(nh, 3),
            "h_anchor": model.hs_anchor.reshape(nh, 3), "h_qadr": model.hs_qadr, "h_dof": model.hs_dof,
            "h_qpos0": model.hs_qpos0, "h_stiff": model.hs_stiffness, "h_springref": model.hs_springref,
            "h_lo": np.where(model.hs_limited, model.hs_range[:, 0], -_BIG) if nh else np.zeros(0),
            "h_hi": np.where(model.hs_limited, model.hs_range[:, 1], _BIG) if nh else np.zeros(0),
            "f_body": model.free_body, "f_qadr": model.free_qadr, "f_dof": model.free_dof,
            "d_body": model.dof_body, "d_vsrc": vsrc, "d_damping": model.dof_damping,
            "d_armature": model.dof_armature, "d_anc": model.dof_anc.reshape(-1) != 0,
            "c_body": model.contact_body, "c_pos": model.contact_pos.reshape(nc, 3), "c_dist": model.contact_dist,
        }
        assert arrays.keys() == MODEL_ARRAYS.keys(), "every array of the model struct is filled"
        st = k["Model"]()
        st.nb, st.nh, st.nf, st.nv, st.nc = nb, nh, nf, nv, nc
        st.root_free = int(nb > 0 and model.body_free[0] >= 0)
        for name, x in arrays.items():
            setattr(st, name, arr(x, MODEL_ARRAYS[name]))
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
