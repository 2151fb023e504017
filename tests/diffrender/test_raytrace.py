"""The Warp ray tracer (on Warp's CPU device): agreement with the rasterizer's sharp limit on the task robots
at their task cameras, the floor, environments kept apart, BVH refits, back-face culling, shadows, errors."""

import dataclasses
import re

import pytest
import torch

import diffrender as dr
import tasks

pytest.importorskip("warp")

from diffrender.raytrace import RayTracer, render_raytraced

from .helpers import F64, ROBOTS, ant_camera, ant_pose, asset, hard_zbuffer, tiny_camera, tiny_scene

# the soft model near its sharp limit: coverage edges of 1e-3 px, depth temperature of 2.5e-4 m
SHARP = dict(sigma=1e-3, gamma=1e-5)
# float32 ray casting against the float64 rasterizer
F32_TOL = 1e-4


def _task_scene(name: str, batch: int, *, seed: int = 0):
    """``batch`` random start states of task ``name`` seen by its task camera: (robot, verts, normals,
    camera) in float64."""
    task = tasks.make(name, batch, dtype=F64, seed=seed)
    task.reset()
    robot = dr.RobotModel.from_mjcf(task.mjcf_path, dtype=F64)
    spec = task.camera
    pose = robot.pose(task.qpos)
    verts, normals = pose.world_vertices_and_normals()
    root = pose.link_poses()[:, robot.body_names.index(spec.root_body), :3, 3]
    cam = dr.tracking_camera(root, eye_offset=spec.eye, target_offset=spec.target, track=spec.track,
                             fov_deg=spec.fov_deg, height=spec.height, width=spec.width)
    return robot, verts, normals, cam


def _item_colors(robot) -> torch.Tensor:
    """(V, 3) a distinct grey per meshed item (every item is a convex primitive, so a colour change between
    neighbouring pixels is a silhouette or depth edge)."""
    ids = torch.zeros(robot.num_vertices, 3, dtype=F64)
    n = len(robot.vertex_ranges)
    for k, (start, stop) in enumerate(robot.vertex_ranges):
        ids[start:stop] = (k + 1) / (n + 1)
    return ids


def _id_settings(base: dr.RasterSettings) -> dr.RasterSettings:
    """Unlit item ids over a black floor and sky: the image is the item id, 0 off the robot."""
    black = dr.FloorSettings(color_a=(0.0, 0.0, 0.0), color_b=(0.0, 0.0, 0.0))
    return dataclasses.replace(base, floor=black, background=(0.0, 0.0, 0.0), ambient=1.0, diffuse=0.0)


def _edges(ids: torch.Tensor) -> torch.Tensor:
    """(B, H, W) bool: pixels within one pixel (3 x 3 neighbourhood) of an id change; ids (B, 3, H, W)."""
    g = ids[:, :1]
    hi = torch.nn.functional.max_pool2d(g, 3, stride=1, padding=1)
    lo = -torch.nn.functional.max_pool2d(-g, 3, stride=1, padding=1)
    return (hi - lo)[:, 0] > 1e-6


def _iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / max(1, float((a | b).sum()))


# ------------------------------------------------------------------------------------------------ the robots
@pytest.mark.parametrize("name", ROBOTS)
def test_matches_sharp_rasterizer_at_task_camera(name):
    """At each robot's task camera: the same silhouettes (IoU >= 0.99) and, away from silhouette and depth
    edges, the same colours (mean |difference| <= 2/255) as the soft rasterizer at sigma 1e-3 px, gamma 1e-5;
    and the hard model's image to float32 rounding everywhere."""
    robot, verts, normals, cam = _task_scene(name, 2)
    soft = dr.RasterSettings(**SHARP)
    ids = _item_colors(robot)
    ref_ids = dr.render(verts, robot.faces, ids, cam, _id_settings(soft), normals=normals)
    ray_ids = render_raytraced(verts, robot.faces, ids, cam, _id_settings(soft), normals=normals)
    ref_mask, ray_mask = ref_ids[:, 0] > 0, ray_ids[:, 0] > 0
    assert (ref_mask.flatten(1).sum(1) > 30).all(), "the robot must be in view for the test to mean anything"
    assert _iou(ref_mask, ray_mask) >= 0.99

    ref = dr.render(verts, robot.faces, robot.colors, cam, soft, normals=normals)
    ray = render_raytraced(verts, robot.faces, robot.colors, cam, soft, normals=normals)
    assert ray.shape == ref.shape and ray.dtype == F64
    interior = ~(_edges(ref_ids) | _edges(ray_ids))
    assert (interior & ref_mask).sum() >= 20  # the colour comparison covers robot pixels
    diff = (ray - ref).abs().mean(1)
    assert diff[interior].mean() <= 2 / 255
    assert diff[interior & ref_mask].mean() <= 2 / 255

    hard = dr.RasterSettings(raster_model="hard")
    ref_hard = dr.render(verts, robot.faces, robot.colors, cam, hard, normals=normals)
    assert (render_raytraced(verts, robot.faces, robot.colors, cam, hard, normals=normals) - ref_hard).abs().max() \
        <= F32_TOL


@pytest.mark.slow
@pytest.mark.parametrize("name", ROBOTS)
def test_matches_hard_rasterizer_many_environments(name):
    """Eight environments per robot (seeded random starts), computed normals and float32 inputs."""
    robot, verts, _, cam = _task_scene(name, 8, seed=3)
    hard = dr.RasterSettings(raster_model="hard")
    ref = dr.render(verts, robot.faces, robot.colors, cam, hard)
    c32 = dr.Camera(rotation=cam.rotation.float(), eye=cam.eye.float(), focal=cam.focal, height=cam.height,
                    width=cam.width)
    ray = render_raytraced(verts.float(), robot.faces, robot.colors.float(), c32, hard)
    assert ray.dtype == torch.float32
    # float32 vertices move silhouettes by ~1e-7 m: a pixel centre on an edge may flip
    assert ((ray.double() - ref).abs().amax(1) > F32_TOL).double().mean() < 1e-3


# ------------------------------------------------------------------------------------------------ the scene
def test_tiny_scene_equals_independent_hard_zbuffer():
    """Three overlapping triangles over the floor: the independent z-buffer of the tests, pixel by pixel,
    with mesh normals (normals=None) and with given normals."""
    verts, faces, colors = tiny_scene(2)
    _, _, cam = tiny_camera(2, height=24, width=20)
    s = dr.RasterSettings(znear=0.5, zfar=10.0)
    assert (render_raytraced(verts, faces, colors, cam, s) - hard_zbuffer(verts, faces, colors, cam, s)).abs().max() \
        <= F32_TOL
    normals = torch.nn.functional.normalize(torch.randn(verts.shape, dtype=F64, generator=torch.Generator()
                                                        .manual_seed(1)), dim=-1)
    ray = render_raytraced(verts, faces, colors, cam, s, normals=normals)
    assert (ray - hard_zbuffer(verts, faces, colors, cam, s, normals=normals)).abs().max() <= F32_TOL


def test_floor_only_equals_rasterizer_floor():
    """Robot out of view (behind the camera), and a scene without faces: the floor and sky are the
    rasterizer's (default, soft settings), horizon included."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)
    q = ant_pose(2)
    verts = robot.world_vertices(q)
    eye = torch.tensor([[0.3, -2.0, 1.0], [0.0, -2.5, 0.4]], dtype=F64)
    cam = dr.Camera.look_at(eye, eye + torch.tensor([0.2, -1.0, -0.25], dtype=F64), (0.0, 0.0, 1.0), 70.0, 40, 48)
    s = dr.RasterSettings()
    ref = dr.render(verts, robot.faces, robot.colors, cam, s)
    assert (ref[:, :, 0] - torch.tensor(s.background, dtype=F64)[:, None]).abs().max() < 1e-6  # sky at the top
    assert (render_raytraced(verts, robot.faces, robot.colors, cam, s) - ref).abs().max() <= F32_TOL
    no_faces = torch.zeros(0, 3, dtype=torch.long)
    assert (render_raytraced(verts, no_faces, robot.colors, cam, s) - ref).abs().max() <= F32_TOL


def test_environments_see_only_their_own_robot():
    """Environment 1's camera looks at where environment 0's robot stands while its own robot is far away:
    it sees the floor only (one BVH holds both, but rays of environment b traverse only b's triangles)."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)
    q = ant_pose(2)
    q[1, :3] = q[0, :3]
    verts = robot.world_vertices(q)
    cam = ant_camera(q, size=32)
    s = dr.RasterSettings(raster_model="hard")
    both = render_raytraced(verts, robot.faces, robot.colors, cam, s)
    away = verts.clone()
    away[1, :, 0] += 100.0
    ray = render_raytraced(away, robot.faces, robot.colors, cam, s)
    floor = render_raytraced(verts, torch.zeros(0, 3, dtype=torch.long), robot.colors, cam, s)
    assert (ray[0] - both[0]).abs().max() == 0
    assert (both[1] - floor[1]).abs().amax(0).gt(0.05).sum() > 30  # its own robot was in view
    assert (ray[1] - floor[1]).abs().max() == 0


def test_refit_follows_the_vertices():
    """One tracer over several frames (BVH built at the first, refitted after) renders what a tracer built at
    the later frame renders; float32 and float64 inputs give the same image in their own dtype."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)
    s = dr.RasterSettings(raster_model="hard")
    tracer = RayTracer(robot.faces, num_envs=2, num_verts=robot.num_vertices, settings=s)
    for seed in (0, 1, 2):
        q = ant_pose(2, seed=seed)
        verts, normals = robot.world_vertices_and_normals(q)
        cam = ant_camera(q, size=32)
        img = tracer(verts, robot.colors, cam, normals=normals)
        fresh = RayTracer(robot.faces, num_envs=2, num_verts=robot.num_vertices, settings=s)
        assert (img - fresh(verts, robot.colors, cam, normals=normals)).abs().max() == 0
        assert (img - dr.render(verts, robot.faces, robot.colors, cam, s, normals=normals)).abs().max() <= F32_TOL
    c32 = dr.Camera(rotation=cam.rotation.float(), eye=cam.eye.float(), focal=cam.focal, height=32, width=32)
    img32 = tracer(verts.float(), robot.colors.float(), c32, normals=normals.float())
    assert img32.dtype == torch.float32 and (img32.double() - img).abs().max() <= F32_TOL
    per_env = tracer(verts, robot.colors.expand(2, -1, -1), cam, normals=normals)  # (B, V, 3) colours
    assert (per_env - img).abs().max() == 0


@pytest.mark.parametrize("cull", [True, False])
def test_back_faces_follow_the_rasterizer(cull):
    """A triangle wound clockwise as seen from the camera is culled with cull_backfaces, drawn without."""
    verts, faces, colors = tiny_scene(2)
    _, _, cam = tiny_camera(2, height=20, width=20)
    flipped = faces[:, [0, 2, 1]]
    s = dr.RasterSettings(znear=0.5, zfar=10.0, cull_backfaces=cull, raster_model="hard")
    ref = dr.render(verts, flipped, colors, cam, s)
    floor = dr.render(verts, flipped[:0], colors, cam, s)
    assert ((ref - floor).abs().max() > 0.05) == (not cull)
    assert (render_raytraced(verts, flipped, colors, cam, s) - ref).abs().max() <= F32_TOL


def test_alpha_model_keeps_faces_below_the_floor():
    """A triangle that dips below z = 0: hidden there by the floor in the hard/softmax models, drawn over it
    in the alpha model, as the rasterizer does."""
    verts = torch.tensor([[[-0.6, 0.0, -0.4], [0.6, 0.0, -0.4], [0.0, 0.0, 0.6]]], dtype=F64)
    faces = torch.tensor([[0, 2, 1]])
    colors = torch.tensor([[0.9, 0.1, 0.1]] * 3, dtype=F64)
    cam = dr.Camera.look_at(torch.tensor([0.0, -2.0, 0.8], dtype=F64), torch.tensor([0.0, 0.0, 0.0], dtype=F64),
                            (0.0, 0.0, 1.0), 60.0, 24, 24)
    images = {}
    for model in ("hard", "alpha"):
        s = dr.RasterSettings(znear=0.1, zfar=10.0, cull_backfaces=False, raster_model=model, **SHARP)
        ref = dr.render(verts, faces, colors, cam, s)
        ray = render_raytraced(verts, faces, colors, cam, s)
        ids = render_raytraced(verts, faces, colors, cam, _id_settings(s))
        keep = ~_edges(ids)
        assert (ray - ref).abs().amax(1)[keep].max() <= F32_TOL
        images[model] = ray
    red = lambda img: (img[:, 0] - img[:, 1] > 0.3).sum()  # noqa: E731
    assert red(images["alpha"]) > red(images["hard"]) + 10


# ------------------------------------------------------------------------------------------------ options
def _ant_frames(seeds=(0, 1), size=(30, 34)):
    """The ant (detail 0) in two environments at poses of ``seeds``: (robot, [(verts, normals, camera)])
    float32, at an image size that tiles of 4 x 8 and 3 x 5 do not divide."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)
    frames = []
    for seed in seeds:
        q = ant_pose(2, seed=seed)
        verts, normals = robot.world_vertices_and_normals(q)
        cam = ant_camera(q, size=32)
        cam = dr.Camera(rotation=cam.rotation.float(), eye=cam.eye.float(), focal=cam.focal, height=size[0],
                        width=size[1])
        frames.append((verts.float(), normals.float(), cam))
    return robot, frames


@pytest.mark.parametrize("options", [
    dict(tile=None), dict(tile=(3, 5)), dict(tile=(1, 1)), dict(tile=(2, 16), rays_per_thread=3),
    dict(rays_per_thread=2), dict(block_dim=64), dict(bvh_leaf_size=1), dict(bvh_leaf_size=8),
    dict(bvh_constructor="median"), dict(bvh_constructor="lbvh", bvh_leaf_size=2)])
def test_options_render_the_default_image(options):
    """Pixel tiles, rays per thread and block size change only which thread shades a pixel: the default's
    image exactly. Another tree (constructor, leaf size) can only change which of two triangles at the same
    distance a ray meets (a shared edge, where both interpolate the same normals and colours): float32
    rounding. Over two frames, so the refitted tree is compared too."""
    robot, frames = _ant_frames()
    s = dr.RasterSettings(raster_model="hard")
    default = RayTracer(robot.faces, num_envs=2, num_verts=robot.num_vertices, settings=s)
    other = RayTracer(robot.faces, num_envs=2, num_verts=robot.num_vertices, settings=s, **options)
    same_tree = not ({"bvh_constructor", "bvh_leaf_size"} & set(options))
    for verts, normals, cam in frames:
        ref = default(verts, robot.colors.float(), cam, normals=normals)
        img = other(verts, robot.colors.float(), cam, normals=normals)
        assert ref.shape == img.shape == (2, 3, 30, 34)
        assert (ref[:, 0] != ref[:, 0, :1, :1]).any()  # not a blank image
        if same_tree:
            assert torch.equal(img, ref)
        else:
            assert (img - ref).abs().max() <= 1e-5


def test_refit_and_trace_are_the_call():
    """refit + trace (the halves a benchmark times) render what one call renders; rebuild (a new tree from
    the current points) renders the same; trace before any refit is an error."""
    robot, frames = _ant_frames(seeds=(0, 1, 2))
    s = dr.RasterSettings(raster_model="hard")
    colors = robot.colors.float()
    whole = RayTracer(robot.faces, num_envs=2, num_verts=robot.num_vertices, settings=s)
    halves = RayTracer(robot.faces, num_envs=2, num_verts=robot.num_vertices, settings=s, bvh_constructor="median")
    with pytest.raises(RuntimeError, match="before the first refit"):
        halves.trace(colors, frames[0][2], normals=frames[0][1])
    for k, (verts, normals, cam) in enumerate(frames):
        halves.refit(verts)
        if k == 2:
            halves.rebuild()
        img = halves.trace(colors, cam, normals=normals)
        assert (img - whole(verts, colors, cam, normals=normals)).abs().max() <= 1e-5
    with pytest.raises(ValueError, match=r"verts must have shape \(2, "):
        halves.refit(frames[0][0][:1])


def test_bad_options_are_named():
    faces = torch.tensor([[0, 1, 2]])
    cases = [
        (dict(bvh_constructor="bvh"), "bvh_constructor must be one of sah, median, lbvh"),
        (dict(bvh_constructor="cubql"), "bvh_constructor must be one of"),
        (dict(bvh_leaf_size=0), "bvh_leaf_size must be None or a positive int"),
        (dict(tile=(4,)), r"tile must be None or \(rows, columns\)"),
        (dict(tile=(0, 8)), "tile must be"),
        (dict(rays_per_thread=0), "rays_per_thread must be a positive int"),
        (dict(block_dim=100), "block_dim must be a multiple of 32"),
    ]
    for options, message in cases:
        with pytest.raises(ValueError, match=message):
            RayTracer(faces, num_envs=1, num_verts=3, **options)


# ------------------------------------------------------------------------------------------------ shadows
def test_shadow_of_a_plate_on_the_floor():
    """A horizontal square 0.5 m above the floor, light straight down, seen from the side so that its whole
    shadow is in view: with shadows the floor under the square (and only there, up to a pixel at the
    shadow's edge) keeps only the ambient term; the square itself (lit from above) and the rest of the floor
    do not change."""
    a = 0.3
    verts = torch.tensor([[[-a, -a, 0.5], [a, -a, 0.5], [a, a, 0.5], [-a, a, 0.5]]], dtype=F64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])  # counter-clockwise seen from above
    colors = torch.full((4, 3), 0.8, dtype=F64)
    eye = torch.tensor([[1.5, 0.0, 1.0]], dtype=F64)
    cam = dr.Camera.look_at(eye, torch.zeros(1, 3, dtype=F64), (0.0, 0.0, 1.0), 60.0, 64, 64)
    s = dr.RasterSettings(light_dir=(0.0, 0.0, 1.0), ambient=0.3, diffuse=0.7, znear=0.1, zfar=10.0)
    off = render_raytraced(verts, faces, colors, cam, s)
    on = render_raytraced(verts, faces, colors, cam, s, shadows=True)
    # where each pixel's ray meets the plane of the plate and the floor
    j, i = torch.meshgrid(torch.arange(64, dtype=F64) + 0.5, torch.arange(64, dtype=F64) + 0.5, indexing="xy")
    d = torch.stack([(j - cam.cx) / cam.focal, (i - cam.cy) / cam.focal, torch.ones_like(j)], -1) @ cam.rotation[0]
    t_floor, t_plate = -eye[0, 2] / d[..., 2], (0.5 - eye[0, 2]) / d[..., 2]
    fx, fy = eye[0, 0] + t_floor * d[..., 0], eye[0, 1] + t_floor * d[..., 1]
    px, py = eye[0, 0] + t_plate * d[..., 0], eye[0, 1] + t_plate * d[..., 1]
    margin = 0.04  # [m] more than a pixel on the plate and on the floor
    on_plate = (t_plate > 0) & (px.abs() < a - margin) & (py.abs() < a - margin)
    off_plate = (t_plate < 0) | (px.abs() > a + margin) | (py.abs() > a + margin)
    shadowed = off_plate & (t_floor > 0) & (fx.abs() < a - margin) & (fy.abs() < a - margin)
    lit = off_plate & ((t_floor < 0) | (fx.abs() > a + margin) | (fy.abs() > a + margin))
    assert shadowed.sum() > 100 and on_plate.sum() > 50 and lit.sum() > 1000
    assert torch.allclose(on[0][:, shadowed], off[0][:, shadowed] * 0.3, atol=1e-6)
    assert (on[0][:, lit] - off[0][:, lit]).abs().max() == 0
    assert (on[0][:, on_plate] - off[0][:, on_plate]).abs().max() == 0


def test_robot_shadows_only_darken():
    """The ant with shadows: the image changes only by darkening; a changed floor pixel keeps exactly the
    ambient share of its light; off by default, so the default image is the rasterizer's."""
    robot = dr.RobotModel.from_mjcf(asset("ant"), dtype=F64, detail=0)
    q = ant_pose(2)
    verts, normals = robot.world_vertices_and_normals(q)
    target = q[:, :3] * torch.tensor([1.0, 1.0, 0.0], dtype=F64)
    # from the side away from the light, where the shadow falls
    cam = dr.Camera.look_at(target + torch.tensor([0.8, 1.5, 2.5], dtype=F64), target, (0.0, 0.0, 1.0), 60.0, 48, 48)
    s = dr.RasterSettings(raster_model="hard")
    off = render_raytraced(verts, robot.faces, robot.colors, cam, s, normals=normals)
    on = render_raytraced(verts, robot.faces, robot.colors, cam, s, normals=normals, shadows=True)
    assert (off - dr.render(verts, robot.faces, robot.colors, cam, s, normals=normals)).abs().max() <= F32_TOL
    changed = (on - off).abs().amax(1) > 0
    assert changed.sum() > 20
    assert (on <= off + 1e-7).all()
    floor = dr.render(verts, robot.faces[:0], robot.colors, cam, s)
    on_floor = changed & ((off - floor).abs().amax(1) <= F32_TOL)
    assert on_floor.sum() > 100
    light_z = dr.shading.unit_light(s.light_dir)[2]
    ratio = s.ambient / (s.ambient + s.diffuse * light_z)
    assert torch.allclose(on.permute(0, 2, 3, 1)[on_floor], off.permute(0, 2, 3, 1)[on_floor] * ratio, atol=1e-5)


# ------------------------------------------------------------------------------------------------ errors
def test_asking_for_a_gradient_is_an_error():
    verts, faces, colors = tiny_scene(2)
    eye, target, cam = tiny_camera(2)
    s = dr.RasterSettings(znear=0.5, zfar=10.0)
    with pytest.raises(RuntimeError, match=r"no gradient.*verts"):
        render_raytraced(verts.clone().requires_grad_(), faces, colors, cam, s)
    with pytest.raises(RuntimeError, match=r"no gradient.*camera\.eye"):
        moving = dr.Camera.look_at(eye.clone().requires_grad_(), target, (0.0, 0.0, 1.0), 40.0, 7, 6)
        render_raytraced(verts, faces, colors, moving, s)
    with torch.no_grad():
        img = render_raytraced(verts.clone().requires_grad_(), faces, colors, cam, s)
    assert not img.requires_grad
    assert (img - render_raytraced(verts, faces, colors, cam, s)).abs().max() == 0


def test_bad_input_is_named():
    verts, faces, colors = tiny_scene(2)
    _, _, cam = tiny_camera(2)
    s = dr.RasterSettings(znear=0.5, zfar=10.0)
    tracer = RayTracer(faces, num_envs=2, num_verts=9, settings=s)
    cases = [
        (lambda: tracer(verts[:1], colors, cam), r"verts must have shape \(2, 9, 3\)"),
        (lambda: tracer(verts[:, :8], colors, cam), r"verts must have shape \(2, 9, 3\)"),
        (lambda: tracer(verts.long(), colors, cam), "verts must be float32 or float64"),
        (lambda: tracer(verts, colors[:8], cam), "colors must have shape"),
        (lambda: tracer(verts, colors.float(), cam), "colors is torch.float32 but verts is torch.float64"),
        (lambda: tracer(verts, colors, cam, normals=verts[:, :8]), "normals must have the shape of verts"),
        (lambda: tracer(verts, colors, "camera"), "camera must be a diffrender.Camera"),
        (lambda: tracer(verts, colors, tiny_camera(2, dtype=torch.float32)[2]), "camera is torch.float32"),
        (lambda: tracer(torch.cat([verts, verts]), colors, cam), r"verts must have shape \(2, 9, 3\)"),
        (lambda: tracer(verts.clone().index_fill_(1, torch.tensor([3]), float("nan")), colors, cam),
         "verts contain"),
        (lambda: RayTracer(faces, num_envs=2, num_verts=8), r"faces index vertices 0..8 but num_verts is 8"),
        (lambda: RayTracer(faces.float(), num_envs=2, num_verts=9), "faces must be an int64/int32 tensor"),
        (lambda: RayTracer(faces[:, :2], num_envs=2, num_verts=9), r"faces must have shape \(F, 3\)"),
        (lambda: RayTracer(faces, num_envs=0, num_verts=9), "num_envs must be a positive int"),
        (lambda: RayTracer(faces, num_envs=2, num_verts=9, settings={"sigma": 1.0}), "settings must be a"),
        (lambda: RayTracer(faces, num_envs=2, num_verts=9, shadows=1), "shadows must be a bool"),
        (lambda: render_raytraced(verts[0], faces, colors, cam), r"verts must have shape \(B, V, 3\)"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message):
            call()
    four = dr.Camera.look_at(torch.zeros(4, 3, dtype=F64) + torch.tensor([0.0, -3.0, 1.0], dtype=F64),
                             torch.tensor([0.0, 0.0, 0.7], dtype=F64), (0.0, 0.0, 1.0), 40.0, 7, 6)
    with pytest.raises(ValueError, match="camera has 4 views but the ray tracer renders 2 environments"):
        tracer(verts, colors, four)


def test_render_raytraced_refuses_what_render_refuses_with_the_same_message():
    """Both take the same arguments through one check (diffrender.render.check_inputs): a bad argument is named
    the same way by either."""
    verts, faces, colors = tiny_scene(2)
    _, _, cam = tiny_camera(2)
    s = dr.RasterSettings(znear=0.5, zfar=10.0)
    bad = [(verts, faces.float(), colors, cam, s), (verts, faces, colors.float(), cam, s),
           (verts, faces, colors, tiny_camera(2, dtype=torch.float32)[2], s), (verts, faces, colors, cam, {"a": 1}),
           (verts, faces[:, :2], colors, cam, s), (verts, faces, colors[:8], cam, s)]
    for args in bad:
        with pytest.raises(ValueError) as rendered:
            dr.render(*args)
        with pytest.raises(ValueError, match=re.escape(str(rendered.value))):
            render_raytraced(*args)


# ------------------------------------------------------------------------------------------------ benchmark
def test_benchmark_runs_on_the_cpu(tmp_path, capsys, benchmark_script):
    """benchmarks/raytrace.py --tiny on Warp's CPU device: every variant timed, its image the default's, the
    JSON with its provenance and the table printed last."""
    import json
    bench = benchmark_script("raytrace")
    out = tmp_path / "rt.json"
    assert bench.main(["--device", "cpu", "--tiny", "--repeats", "2", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert {"device", "date", "command", "commit", "warp"} <= set(doc["meta"])
    rows = doc["rows"]
    assert [r["variant"] for r in rows] == list(bench.TINY_VARIANTS)
    for r in rows:
        assert r["status"] == "ok", r
        assert r["refit_ms"] > 0 and r["trace_ms"] > 0 and r["frame_ms"] > 0 and r["images_per_s"] > 0
        assert r["max_abs_diff_vs_first"] <= 1e-5
    assert 0 < rows[0]["robot_ray_share"] < 1
    assert capsys.readouterr().out.rstrip().splitlines()[-1].split()[1] == bench.TINY_VARIANTS[-1]
