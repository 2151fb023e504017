"""What a visual policy sees: task-camera renders of the robot and the 3-frame stack.

``tasks -> diffrender``: the task knows its camera (``Task.camera``; docs/design.md, "Image model") and its
MJCF; the renderer knows nothing of tasks.
"""

from __future__ import annotations

import dataclasses

import torch

import diffrender
from vocabulary import RENDERERS  # the differentiable soft rasterizer and the forward-only ray tracer

__all__ = ["RENDERERS", "FrameStack", "TaskRenderer"]



class TaskRenderer:
    """qpos -> what the policy sees: RGB images of the robot from the task's camera.

    The camera follows the task's root body (``Task.camera``: eye/target offsets, tracked axes); its pose is
    computed from ``qpos`` through forward kinematics, so in full mode the image is differentiable in the
    state both through the robot's pixels and through the camera (the textured floor moves under it).

    Args:
        task: a :class:`tasks.Task` (its ``mjcf_path``, ``camera``, ``dtype`` and ``device`` are used).
        height, width: image size [px] (the task camera's 84 x 84 by default).
        detail: tessellation level of the robot's primitives.
        extra_meshes, extra_mesh_verts: extra meshes attached to moving links (scene complexity sweeps).
        sigma, gamma: soft-rasterizer softness [px] and depth temperature; None keeps the renderer defaults
            (sigma is given at 84 px and scaled with the image height so that edges stay equally soft).
        renderer: ``"soft"``, the differentiable rasterizer, or ``"warp"``, the forward-only ray tracer
            (:class:`diffrender.RayTracer`: the rasterizer's sharp limit, cost nearly flat in faces) for images
            that need no gradient. :meth:`soft` renders with the rasterizer whichever is chosen.
        settings: further :class:`diffrender.RasterSettings` fields.
    """

    def __init__(
        self,
        task,
        *,
        height: int | None = None,
        width: int | None = None,
        detail: int = 1,
        extra_meshes: int = 0,
        extra_mesh_verts: int = 64,
        sigma: float | None = None,
        gamma: float | None = None,
        renderer: str = "soft",
        **settings,
    ):
        if renderer not in RENDERERS:
            raise ValueError(f"unknown renderer {renderer!r}; valid renderers: {', '.join(RENDERERS)}")
        self.renderer = renderer
        self._tracers: dict[int, diffrender.RayTracer] = {}  # one per batch size (a tracer renders exactly B)
        spec = task.camera
        self.spec = spec
        self.height = height or spec.height
        self.width = width or spec.width
        robot = diffrender.RobotModel.from_mjcf(task.mjcf_path, detail=detail, dtype=task.dtype, device=task.device)
        if extra_meshes:
            robot = robot.with_extra_meshes(extra_meshes, extra_mesh_verts, seed=0)
        self.robot = robot
        if spec.root_body not in robot.body_names:
            raise ValueError(f"camera root body {spec.root_body!r} is not a body of {task.mjcf_path}")
        self.root_index = robot.body_names.index(spec.root_body)
        defaults = diffrender.RasterSettings()
        base_sigma = defaults.sigma if sigma is None else sigma
        fields = {"sigma": base_sigma * self.height / 84.0}
        if gamma is not None:
            fields["gamma"] = gamma
        fields.update(settings)
        self.settings = dataclasses.replace(defaults, **fields)
        self._scene = self.scene
        self.focal = diffrender.focal_length(spec.fov_deg, self.height)  # [px], as the tracking camera computes it

    @property
    def num_faces(self) -> int:
        return self.robot.num_faces

    @property
    def num_vertices(self) -> int:
        return self.robot.num_vertices

    def freeze_capacity(self, qpos: torch.Tensor, *, headroom: float = 2.0) -> int:
        """Fix the tiled backend's bin capacity at ``headroom`` x what the frames of ``qpos (B, nq)`` need.

        A render inside a captured CUDA graph cannot measure or grow its bins (no host synchronisation) and
        an overflowing environment would render as NaN; a fixed, generous capacity keeps that from happening
        as the robot moves. Returns the capacity (pairs per environment). The ray tracer has no bins; this
        sizes the rasterizer, which probes and :meth:`soft` use with either renderer.
        """
        self.robot.check_qpos(qpos)
        with torch.no_grad():
            pose = self.robot.pose(qpos)
            verts, _ = pose.world_vertices_and_normals()
            capacity = diffrender.measure_bin_capacity(verts, self.robot.faces, self._camera_at(pose), self.settings)
        capacity = int(capacity * headroom) + 64
        self.settings = dataclasses.replace(self.settings, bin_capacity=capacity)
        return capacity

    def camera(self, qpos: torch.Tensor) -> diffrender.Camera:
        """The task camera for each environment of ``qpos: (B, nq)``."""
        return self._camera_at(self.robot.pose(qpos))

    def _camera_at(self, pose: diffrender.RobotPose) -> diffrender.Camera:
        """The task camera of each environment of an already computed ``pose`` (B environments)."""
        spec = self.spec
        root = pose.link_poses()[:, self.root_index, :3, 3]  # (B, 3) [m]
        return diffrender.tracking_camera(
            root,
            eye_offset=spec.eye,
            target_offset=spec.target,
            track=spec.track,
            fov_deg=spec.fov_deg,
            height=self.height,
            width=self.width,
        )

    def scene(self, qpos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """What the rasterizer takes, from ``qpos: (B, nq)``: world vertices (B, V, 3) [m], unit normals
        (B, V, 3), camera rotation (B, 3, 3) and eye (B, 3) [m]. The meshes and the camera's anchor are read
        off one forward-kinematics pass."""
        pose = self.robot.pose(qpos)
        verts, normals = pose.world_vertices_and_normals()
        cam = self._camera_at(pose)
        return verts, normals, cam.rotation, cam.eye

    def compile(self, **compile_kwargs) -> TaskRenderer:
        """Run the renderer's PyTorch work through ``torch.compile`` (static shapes): :meth:`scene` (forward
        kinematics, posed vertices and normals, the tracking camera) on CUDA and, where the fused rasterizer is
        used, its per-face setup (``RasterSettings.compile``). Same images and gradients up to float rounding
        (tested on CUDA). Keyword arguments go to ``torch.compile``. Returns self.

        The tiled backend's own kernels and, on the CPU, :meth:`scene` stay eager: the tests that pin this say why
        (tests/tasks/test_tasks.py, tests/test_cuda.py); the CPU is not where kernel launches cost anything."""
        kw = {"dynamic": False, **compile_kwargs}
        if self.robot.device.type == "cuda":
            self._scene = torch.compile(self.scene, **kw)
        if diffrender.backend_for(self.settings, self.robot.device) == "fused":
            self.settings = dataclasses.replace(self.settings, compile=True)
        return self

    def __call__(self, qpos: torch.Tensor) -> torch.Tensor:
        """qpos: (B, nq) -> images (B, 3, H, W) in [0, 1] from the chosen renderer. With ``"warp"`` the image
        has no gradient: calling it with grad enabled and a ``qpos`` that requires grad is an error."""
        if self.renderer == "soft":
            return self.soft(qpos)
        self.robot.check_qpos(qpos)
        if torch.is_grad_enabled() and qpos.requires_grad:
            raise RuntimeError("TaskRenderer(renderer='warp') renders without gradient, but qpos requires grad: "
                               "call it under torch.no_grad() or use .soft(qpos) for a differentiable image")
        with torch.no_grad():
            verts, normals, camera = self._posed(qpos)
            tracer = self._tracers.get(qpos.shape[0])
            if tracer is None:
                tracer = self._tracers[qpos.shape[0]] = diffrender.RayTracer(
                    self.robot.faces, num_envs=qpos.shape[0], num_verts=self.robot.num_vertices,
                    device=self.robot.device, settings=self.settings)
            return tracer(verts, self.robot.colors, camera, normals=normals)

    def soft(self, qpos: torch.Tensor) -> torch.Tensor:
        """qpos: (B, nq) -> images (B, 3, H, W) in [0, 1] from the soft rasterizer, differentiable in qpos."""
        self.robot.check_qpos(qpos)  # a clear error before any (compiled) work
        verts, normals, camera = self._posed(qpos)
        return diffrender.render(verts, self.robot.faces, self.robot.colors, camera, self.settings,
                                 normals=normals)

    def _posed(self, qpos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, diffrender.Camera]:
        if not torch.is_grad_enabled():
            # compiled, the scene guards on requires_grad even where no gradient is taken: one no-grad graph
            # for states with grad (a stepped state, through its action) and without (a reset state)
            qpos = qpos.detach()
        verts, normals, rotation, eye = self._scene(qpos)
        camera = diffrender.Camera(rotation=rotation, eye=eye, focal=self.focal, height=self.height,
                                   width=self.width)
        return verts, normals, camera


class FrameStack:
    """The last ``k`` RGB frames stacked on channels, oldest first: (B, 3k, H, W).

    At reset the first frame is tiled k times; environments that reset mid-window get their new first frame
    tiled while the others shift by one. ``detach`` cuts the buffer from the graph (SHAC window start).
    """

    def __init__(self, k: int = 3):
        if k < 1:
            raise ValueError(f"FrameStack needs k >= 1, got {k}")
        self.k = k
        self.frames: list[torch.Tensor] = []

    def reset(self, frame: torch.Tensor) -> None:
        """frame: (B, 3, H, W)."""
        self.frames = [frame] * self.k

    def push(self, frame: torch.Tensor, *, reset: torch.Tensor) -> None:
        """frame: (B, 3, H, W) of the state after the step; reset: (B,) bool, envs that were just reset."""
        if not self.frames:
            raise RuntimeError("FrameStack.push before reset")
        m = reset.view(-1, 1, 1, 1)
        older = [torch.where(m, frame, f) for f in self.frames[1:]]
        self.frames = [*older, frame]

    def stacked(self) -> torch.Tensor:
        if not self.frames:
            raise RuntimeError("FrameStack.stacked before reset")
        return torch.cat(self.frames, dim=1)

    def detach(self) -> None:
        self.frames = [f.detach() for f in self.frames]

    def state_dict(self) -> dict:
        return {"k": self.k, "frames": [f.detach().clone() for f in self.frames]}

    def load_state_dict(self, state: dict, *, device: torch.device | str | None = None) -> None:
        self.k = state["k"]
        self.frames = [f.to(device) if device is not None else f for f in state["frames"]]
