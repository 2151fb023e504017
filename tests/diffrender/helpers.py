"""Shared scenes and an independent hard z-buffer for the diffrender tests."""

from __future__ import annotations

import math
from pathlib import Path

import torch

import diffrender as dr
from diffrender.floor import floor_candidate

ASSETS = Path(__file__).resolve().parents[2] / "tasks" / "assets"
ROBOTS = ("cartpole", "hopper", "ant", "humanoid", "cheetah")
F64 = torch.float64


def asset(name: str) -> str:
    return str(ASSETS / f"{name}.xml")


def tiny_scene(batch: int = 2, *, dtype=F64, seed: int = 0):
    """Three overlapping triangles at different depths in front of the camera of :func:`tiny_camera`,
    wound so that they face the camera. Returns verts (B, 9, 3), faces (3, 3), colors (9, 3)."""
    g = torch.Generator().manual_seed(seed)
    base = torch.tensor([[-0.6, 0.0, 0.4], [0.5, 0.1, 0.5], [0.0, -0.1, 1.2]], dtype=dtype)
    tris = [base, base + torch.tensor([0.3, -0.4, 0.1], dtype=dtype),
            base * 0.7 + torch.tensor([-0.2, 0.5, 0.2], dtype=dtype)]
    verts = torch.cat(tris)[None].repeat(batch, 1, 1)
    verts = verts + 0.05 * torch.randn(batch, 9, 3, dtype=dtype, generator=g)
    faces = torch.arange(9).view(3, 3)
    colors = 0.1 + 0.8 * torch.rand(9, 3, dtype=dtype, generator=g)
    return verts, faces, colors


def degenerate_scene():
    """One good face among zero-area, collinear, edge-on, behind-camera and near-plane-straddling faces and
    one with a vertex at the eye, seen by a 16x16 camera. Returns verts (1, 21, 3), faces (7, 3), colors
    (21, 3), camera; vertices 12..17 belong to faces every backend must drop."""
    eye = torch.tensor([0.0, -3.0, 1.0], dtype=F64)
    good = [[-0.5, 0.0, 0.5], [0.5, 0.0, 0.5], [0.0, 0.0, 1.3]]
    tris = [
        good,
        [[0.1, 0.0, 0.8], [0.1, 0.0, 0.8], [0.3, 0.1, 0.9]],  # two identical vertices
        [[-0.2, 0.0, 0.7], [0.0, 0.0, 0.8], [0.2, 0.0, 0.9]],  # collinear
        [[0.0, -3.0 + 1.0, 1.0], [0.0, 0.5, 1.0], [0.0, 0.5, 0.5]],  # edge-on: its plane x = 0 holds the eye
        [[-0.5, -4.0, 1.0], [0.5, -4.0, 1.0], [0.0, -4.0, 1.5]],  # behind the camera
        [[-0.2, -3.5, 0.9], [0.2, -2.0, 0.9], [0.0, -2.5, 1.2]],  # straddles z = 0 and znear
        [eye.tolist(), [0.4, 0.5, 0.5], [-0.4, 0.5, 0.6]],  # a vertex exactly at the eye
    ]
    verts = torch.tensor(tris, dtype=F64).view(1, -1, 3)
    faces = torch.arange(verts.shape[1]).view(-1, 3)
    colors = torch.rand(verts.shape[1], 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    cam = dr.Camera.look_at(eye, torch.tensor([0.0, 0.0, 0.8]).double(), (0, 0, 1.0), 50.0, 16, 16)
    return verts, faces, colors, cam


def tiny_camera(batch: int = 2, *, height: int = 7, width: int = 6, dtype=F64):
    eye = torch.tensor([[0.0, -3.0, 1.0], [0.2, -3.0, 1.1]], dtype=dtype)[:batch]
    target = torch.tensor([0.0, 0.0, 0.7], dtype=dtype)
    return eye, target, dr.Camera.look_at(eye, target, (0.0, 0.0, 1.0), 40.0, height, width)


def tiny_settings(**kw) -> dr.RasterSettings:
    base = dict(sigma=1.0, gamma=0.05, znear=0.5, zfar=10.0)
    base.update(kw)
    return dr.RasterSettings(**base)


def hard_zbuffer(verts, faces, colors, camera: dr.Camera, settings: dr.RasterSettings, normals=None):
    """Independent hard rasterizer: for each pixel centre, the nearest face whose (closed) screen triangle
    contains it, perspective-correct depth and attributes, Lambert shading with normalised interpolated
    normals; else the floor where the pixel's ray hits it (nearer than any face), else the background.
    Evaluates every face at every pixel with its own edge functions, sharing no code with the soft
    rasterizer except the floor texture (:func:`diffrender.floor.floor_candidate`). Returns (B, 3, H, W)."""
    b, h, w = verts.shape[0], camera.height, camera.width
    dt = verts.dtype
    if normals is None:
        fv = verts[:, faces]
        fn = torch.linalg.cross(fv[:, :, 1] - fv[:, :, 0], fv[:, :, 2] - fv[:, :, 0])
        normals = torch.zeros_like(verts)
        for k in range(3):
            normals.index_add_(1, faces[:, k], fn)
        normals = normals / normals.norm(dim=-1, keepdim=True)
    light = torch.tensor(settings.light_dir, dtype=dt)
    light = light / light.norm()
    cam = torch.einsum("bij,bnj->bni", camera.rotation, verts - camera.eye[:, None])
    u = camera.focal * cam[..., 0] / cam[..., 2] + camera.cx
    v = camera.focal * cam[..., 1] / cam[..., 2] + camera.cy
    z = cam[..., 2]
    jj, ii = torch.meshgrid(torch.arange(w, dtype=dt) + 0.5, torch.arange(h, dtype=dt) + 0.5, indexing="xy")
    best = torch.full((b, h, w), math.inf, dtype=dt)
    img = torch.tensor(settings.background, dtype=dt).view(1, 3, 1, 1).repeat(b, 1, h, w)
    if settings.floor is not None:
        lf = settings.ambient + settings.diffuse * max(0.0, float(light[2]))
        zn, col, hit = floor_candidate(camera.rotation, camera.eye, jj, ii, focal=camera.focal, cx=camera.cx,
                                       cy=camera.cy, znear=settings.znear, zfar=settings.zfar,
                                       gamma=settings.gamma, floor=settings.floor, light_factor=lf)
        depth = settings.zfar - zn * (settings.zfar - settings.znear)
        best = torch.where(hit, depth, best)
        img = torch.where(hit[:, None], col.permute(0, 3, 1, 2), img)
    # all faces at once per environment: (F, H, W) edge functions, depth, nearest covering face
    f_idx = faces
    for bi in range(b):
        fz = z[bi, f_idx]  # (F, 3)
        fu, fv = u[bi, f_idx], v[bi, f_idx]
        (u0, u1, u2), (v0, v1, v2) = fu.unbind(1), fv.unbind(1)
        area = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
        ok = (fz > settings.znear).all(1) & (area != 0)
        if settings.cull_backfaces:
            ok &= area < 0
        area = torch.where(area == 0, torch.ones_like(area), area)[:, None, None]
        e = lambda a: a[:, None, None]  # noqa: E731
        l0 = ((e(u2) - e(u1)) * (ii - e(v1)) - (e(v2) - e(v1)) * (jj - e(u1))) / area
        l1 = ((e(u0) - e(u2)) * (ii - e(v2)) - (e(v0) - e(v2)) * (jj - e(u2))) / area
        l2 = 1.0 - l0 - l1
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & ok[:, None, None]
        iz = 1.0 / fz.clamp(min=settings.znear)
        q = torch.stack([l0 * e(iz[:, 0]), l1 * e(iz[:, 1]), l2 * e(iz[:, 2])])  # (3, F, H, W)
        depth = torch.where(inside, 1.0 / q.sum(0), torch.full_like(l0, math.inf))
        dmin, arg = depth.min(0)  # nearest face per pixel
        take = dmin < best[bi]
        best[bi] = torch.where(take, dmin, best[bi])
        bary = (q * depth).gather(1, arg[None, None].expand(3, 1, h, w))[:, 0]  # (3, H, W)
        fsel = f_idx[arg]  # (H, W, 3) vertex ids of the chosen face
        n = (bary.permute(1, 2, 0)[..., None] * normals[bi][fsel]).sum(2)
        n = n / n.norm(dim=-1, keepdim=True)
        shade = settings.ambient + settings.diffuse * (n @ light).clamp(min=0)
        cols = colors[fsel] if colors.ndim == 2 else colors[bi][fsel]
        albedo = (bary.permute(1, 2, 0)[..., None] * cols).sum(2).permute(2, 0, 1)
        img[bi] = torch.where(take, albedo * shade, img[bi])
    return img


def ant_pose(batch: int, *, dtype=F64, seed: int = 0):
    """Random plausible ant configurations (nq = 15)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.zeros(batch, 15, dtype=dtype)
    q[:, :2] = 0.3 * torch.randn(batch, 2, dtype=dtype, generator=g)
    q[:, 2] = 0.75
    axis = torch.randn(batch, 3, dtype=dtype, generator=g)
    angle = 0.2 * torch.rand(batch, 1, dtype=dtype, generator=g)
    q[:, 3] = torch.cos(angle[:, 0] / 2)
    q[:, 4:7] = torch.sin(angle / 2) * axis / axis.norm(dim=1, keepdim=True)
    q[:, 7:] = torch.tensor([0, 1, 0, -1, 0, -1, 0, 1.0], dtype=dtype) + 0.3 * torch.randn(batch, 8, dtype=dtype,
                                                                                            generator=g)
    return q


def ant_camera(qpos: torch.Tensor, *, size: int = 32, fov: float = 60.0, track: str = "xyz"):
    """The ant's tracking camera, looking at the torso from the front-left and above."""
    return dr.tracking_camera(qpos[:, :3], eye_offset=(0.6, -2.2, 0.9), target_offset=(0.0, 0.0, -0.2),
                              track=track, fov_deg=fov, height=size, width=size)
