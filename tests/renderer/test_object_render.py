"""ObjectRenderer: the object lands where the real camera model puts it, on the hard cases.

Ground truth for masks is analytic: each pixel's 4 x 4 sub-pixel rays (exact inverse
distortion, CameraModel.unproject) intersected with the sphere.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from geometry.camera import CameraModel, load_cameras
from geometry.transforms import invert_T, make_T, quat_to_matrix, transform_points
from osdar_platform.shared_data import real_labels_path
from renderer.lighting import Lighting
from renderer.mesh import ObjectMesh, ProxyMesh
from renderer.object_render import ObjectRender, ObjectRenderer

REAL_LABELS = real_labels_path()
SCALE = 0.25
FAR = np.array([5.9e6, 5.9e6, 120.0])  # UTM-like offset for the far-origin case


@pytest.fixture(scope="module")
def cams() -> dict[str, CameraModel]:
    if not REAL_LABELS.is_file():
        pytest.skip(f"{REAL_LABELS} not available")
    raw = json.loads(REAL_LABELS.read_text())
    return {n: c.scaled(SCALE) for n, c in load_cameras(raw).items()}


@pytest.fixture(scope="module")
def renderers(cams) -> dict[str, ObjectRenderer]:
    return {}


def renderer(renderers: dict, cams: dict, name: str, **kw) -> ObjectRenderer:
    key = (name, tuple(sorted(kw.items())))
    if key not in renderers:
        renderers[key] = ObjectRenderer(cams[name], **kw)
    return renderers[key]


def sphere(radius: float, color: float = 0.5) -> ObjectMesh:
    """Icosphere standing on the ground (centre at z = radius)."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    v = np.asarray(s.vertices) + np.array([0.0, 0.0, radius])
    n = len(v)
    return ObjectMesh(v, s.faces, np.full((n, 3), color, np.float32), np.ones(n, np.float32))


def box(size: tuple[float, float, float]) -> ObjectMesh:
    b = trimesh.creation.box(extents=size)
    v = np.asarray(b.vertices) + np.array([0.0, 0.0, size[2] / 2])
    n = len(v)
    return ObjectMesh(v, b.faces, np.full((n, 3), 0.4, np.float32), np.ones(n, np.float32))


def vehicle_pose(origin: np.ndarray | None = None) -> np.ndarray:
    """A non-trivial T_world_base (yawed, slightly pitched and rolled)."""
    R = quat_to_matrix([0.01, -0.02, np.sin(0.35), np.cos(0.35)])
    t = np.array([12.0, -7.0, 0.4]) + (0.0 if origin is None else origin)
    return make_T(R, t)


def place(T_world_base: np.ndarray, p_base: tuple[float, float, float]) -> np.ndarray:
    """T_world_obj at a base-frame position, yawed 0.3 rad relative to the vehicle."""
    T_base_obj = make_T(quat_to_matrix([0, 0, np.sin(0.15), np.cos(0.15)]), p_base)
    return T_world_base @ T_base_obj


def sphere_truth(
    cam: CameraModel, r: ObjectRender, T_world_base: np.ndarray, c_world: np.ndarray, radius: float
) -> np.ndarray:
    """Analytic coverage (h, w) of the ROI by the sphere (4 x 4 sub-pixel samples)."""
    u0, v0, u1, v1 = r.roi
    n = 4
    off = (np.arange(n) + 0.5) / n - 0.5
    vv, uu, dv, du = np.meshgrid(np.arange(v0, v1), np.arange(u0, u1), off, off, indexing="ij")
    uv = np.stack([(uu + du).ravel(), (vv + dv).ravel()], 1)
    rays, ok = cam.unproject(uv)
    T_opt_world = invert_T(T_world_base @ cam.T_base_opt)
    c = transform_points(T_opt_world, c_world[None])[0]
    b = rays @ c
    disc = b * b - (c @ c - radius * radius)
    hit = ok & (disc > 0) & (b > 0)
    return hit.reshape(v1 - v0, u1 - u0, n * n).mean(axis=2)


def centroid(r: ObjectRender, w: np.ndarray) -> np.ndarray:
    vs, us = np.mgrid[0 : w.shape[0], 0 : w.shape[1]]
    return np.array([(w * us).sum(), (w * vs).sum()]) / w.sum() + [r.roi[0], r.roi[1]]


def check_sphere(cams, renderers, name: str, p_base, radius: float, origin=None):
    cam = cams[name]
    T_wb = vehicle_pose(origin)
    T_wo = place(T_wb, p_base)
    obj = sphere(radius)
    r = renderer(renderers, cams, name).render(obj, T_wo, T_wb)
    c_world = T_wo[:3, 3] + T_wo[:3, 2] * radius
    truth = sphere_truth(cam, r, T_wb, c_world, radius)
    return cam, r, truth, T_wb, T_wo, c_world


def test_sphere_lands_where_the_camera_model_says(cams, renderers):
    cam, r, truth, T_wb, T_wo, c_world = check_sphere(
        cams, renderers, "rgb_center", (35.0, 1.5, 0.0), 0.8
    )
    assert r.roi is not None and r.alpha.shape == truth.shape
    uv_anchor, ok = cam.project_world(T_wo[:3, 3][None], T_wb)
    assert ok[0] and np.abs(r.anchor_uv - uv_anchor[0]).max() < 0.05
    uv_c, _ = cam.project_world(c_world[None], T_wb)
    # the mask's centroid vs the projected centre (symmetric object) and vs the analytic mask
    assert np.linalg.norm(centroid(r, r.alpha) - uv_c[0]) < 0.5
    assert np.linalg.norm(centroid(r, r.alpha) - centroid(r, truth)) < 0.1
    inter = np.minimum(r.alpha, truth).sum()
    union = np.maximum(r.alpha, truth).sum()
    assert inter / union > 0.97
    assert abs(r.alpha.sum() / truth.sum() - 1.0) < 0.02
    assert r.visible_fraction == pytest.approx(1.0, abs=1e-6)
    has = r.alpha > 0
    assert np.all(np.isfinite(r.depth[has])) and np.all(np.isnan(r.depth[~has]))
    assert np.nanmin(r.depth) > 0 and np.all(np.isfinite(r.color))
    p_opt = transform_points(invert_T(T_wb @ cam.T_base_opt), T_wo[:3, 3][None])
    assert r.distance_m == pytest.approx(np.linalg.norm(p_opt), rel=1e-9)


def test_far_origin_adds_no_error(cams, renderers):
    _, r0, *_ = check_sphere(cams, renderers, "rgb_highres_center", (30.0, -1.0, 0.0), 0.6)
    _, r1, *_ = check_sphere(cams, renderers, "rgb_highres_center", (30.0, -1.0, 0.0), 0.6, FAR)
    assert r0.roi == r1.roi
    assert np.linalg.norm(centroid(r0, r0.alpha) - centroid(r1, r1.alpha)) < 0.01
    assert np.abs(r0.alpha - r1.alpha).max() < 0.05
    assert np.abs(r0.anchor_uv - r1.anchor_uv).max() < 1e-4


def test_k3_2_48_image_corner(cams, renderers):
    """rgb_highres_right (k3 = 2.48): a sphere in the image corner lands exactly."""
    name = "rgb_highres_right"
    cam = cams[name]
    assert cam.dist[4] == pytest.approx(2.48, abs=0.01)
    T_wb = vehicle_pose()
    corner = np.array([[cam.width - 12.0, cam.height - 12.0]])
    ray, ok = cam.unproject(corner)
    assert ok[0]
    radius = 0.25
    c_opt = ray[0] * 25.0
    c_world = transform_points(T_wb @ cam.T_base_opt, c_opt[None])[0]
    T_wo = make_T(np.eye(3), c_world - [0.0, 0.0, radius])
    r = renderer(renderers, cams, name).render(sphere(radius), T_wo, T_wb)
    uv, ok = cam.project_world(T_wo[:3, 3][None], T_wb)
    assert ok[0] and np.abs(r.anchor_uv - uv[0]).max() < 0.05
    truth = sphere_truth(cam, r, T_wb, c_world, radius)
    assert r.roi[2] == cam.width and r.roi[3] == cam.height  # clipped at the corner
    assert np.linalg.norm(centroid(r, r.alpha) - centroid(r, truth)) < 0.1
    assert np.minimum(r.alpha, truth).sum() / np.maximum(r.alpha, truth).sum() > 0.95


def test_partly_outside_behind_and_near_plane(cams, renderers):
    name = "rgb_center"
    cam = cams[name]
    rr = renderer(renderers, cams, name)
    T_wb = vehicle_pose()
    # partly outside: the sphere's centre on the left image border
    ray, _ = cam.unproject(np.array([[0.0, cam.height / 2]]))
    c_world = transform_points(T_wb @ cam.T_base_opt, (ray[0] * 20.0)[None])[0]
    T_wo = make_T(np.eye(3), c_world - [0, 0, 1.0])
    r = rr.render(sphere(1.0), T_wo, T_wb)
    assert r.roi is not None and r.roi[0] == 0 and r.alpha[:, 0].max() > 0.99
    truth = sphere_truth(cam, r, T_wb, c_world, 1.0)
    assert np.minimum(r.alpha, truth).sum() / np.maximum(r.alpha, truth).sum() > 0.97
    # fully behind the camera
    r = rr.render(sphere(1.0), place(T_wb, (-15.0, 0.0, 0.0)), T_wb)
    assert r.roi is None and np.all(np.isnan(r.anchor_uv)) and r.alpha.size == 0
    # crossing the near plane: a long box from behind the vehicle to 6 m ahead
    T_wo = place(T_wb, (2.0, 0.0, 0.0)) @ make_T(np.eye(3), [0.0, 0.0, 0.0])
    r = rr.render(box((10.0, 1.0, 3.5)), T_wo, T_wb, near=0.05)
    assert r.roi is not None
    for a in (r.color, r.alpha, r.shadow):
        assert np.all(np.isfinite(a))
    has = r.alpha > 0
    assert has.sum() > 0.2 * has.size
    assert np.all(r.depth[has] >= 0.05 * 0.999)


def test_tiny_and_huge(cams, renderers):
    name = "rgb_center"
    cam = cams[name]
    rr = renderer(renderers, cams, name)
    T_wb = vehicle_pose()
    # tiny: 0.25 m ball at 250 m -> ~1.15 px across at scale 0.25
    radius = 0.125
    T_wo = place(T_wb, (250.0, 0.0, 0.0))
    r = rr.render(sphere(radius), T_wo, T_wb)
    assert r.roi is not None and r.alpha.sum() > 0
    c_world = T_wo[:3, 3] + T_wo[:3, 2] * radius
    truth = sphere_truth(cam, r, T_wb, c_world, radius)
    area = np.pi * (radius * cam.fx / np.linalg.norm(c_world - (T_wb @ cam.T_base_opt)[:3, 3])) ** 2
    assert r.alpha.sum() == pytest.approx(area, rel=0.25)
    assert np.linalg.norm(centroid(r, r.alpha) - centroid(r, truth)) < 0.15
    assert np.all(np.isfinite(r.bbox)) and r.bbox[2] - r.bbox[0] <= 4
    # huge: an elephant-sized box (3.5 x 2.5 x 3.2 m) at 3 m fills the image
    size = np.array([3.5, 2.5, 3.2])
    T_wo = place(T_wb, (4.75, 0.0, 0.0))
    r = rr.render(box(tuple(size)), T_wo, T_wb)
    assert r.roi == (0, 0, cam.width, cam.height)
    assert r.alpha.min() > 0.999 and r.visible_fraction == pytest.approx(1.0)
    # the depth puts every pixel on the box's surface
    vs, us = np.mgrid[0 : cam.height : 7, 0 : cam.width : 7]
    xy, ok = cam.undistort(cam.pixel_to_normalized(np.stack([us.ravel(), vs.ravel()], 1)))
    z = r.depth[vs.ravel(), us.ravel()].astype(float)
    p_opt = np.concatenate([xy * z[:, None], z[:, None]], 1)
    p_obj = transform_points(invert_T(T_wo) @ T_wb @ cam.T_base_opt, p_opt[ok])
    off = np.abs(p_obj - [0.0, 0.0, size[2] / 2]) - size / 2
    assert np.percentile(np.abs(off.max(axis=1)), 95) < 0.005


def test_roi_equals_full_frame_render(cams, renderers):
    name = "rgb_center"
    T_wb = vehicle_pose()
    T_wo = place(T_wb, (25.0, -2.0, 0.0))
    obj = sphere(0.7)
    a = renderer(renderers, cams, name, antialias="ssaa2").render(obj, T_wo, T_wb)
    b = renderer(renderers, cams, name, roi=False, antialias="ssaa2").render(obj, T_wo, T_wb)
    assert b.roi == (0, 0, cams[name].width, cams[name].height)
    u0, v0, u1, v1 = a.roi
    assert np.abs(b.alpha[v0:v1, u0:u1] - a.alpha).max() < 1e-4
    assert b.alpha.sum() == pytest.approx(a.alpha.sum(), rel=1e-5)


def _plane(corners: np.ndarray) -> ProxyMesh:
    return ProxyMesh(corners, np.array([[0, 1, 2], [0, 2, 3]]))


def test_proxy_occludes_and_receives_shadow(cams, renderers):
    name = "rgb_center"
    cam = cams[name]
    rr = renderer(renderers, cams, name)
    T_wb = vehicle_pose(FAR)  # far origin on purpose: proxies are world-frame too
    T_wo = place(T_wb, (30.0, 0.0, 0.0))
    obj = sphere(1.0)
    # A wall at 20 m covering base y > 0 (the object's left half, image left).
    wall_b = np.array([[20.0, 0.0, -2.0], [20.0, 8.0, -2.0], [20.0, 8.0, 6.0], [20.0, 0.0, 6.0]])
    wall = _plane(transform_points(T_wb, wall_b))
    no_sun = Lighting(sun_intensity=0.0)  # no shadow: the ROI is the object's alone
    r = rr.render(obj, T_wo, T_wb, proxies=wall, light=no_sun)
    full = rr.render(obj, T_wo, T_wb, light=no_sun)
    assert r.roi == full.roi
    uv_c, _ = cam.project_world((T_wo[:3, 3] + T_wo[:3, 2])[None], T_wb)
    col = round(float(uv_c[0, 0])) - r.roi[0]
    assert r.alpha[:, : col - 1].max() == 0.0  # hidden behind the wall
    assert np.allclose(r.alpha[:, col + 2 :], full.alpha[:, col + 2 :], atol=1e-6)
    assert 0.4 < r.visible_fraction < 0.6
    # Ground proxy under the object: shadow on the side away from the sun.
    sun = np.array([0.45, -0.55, 0.7])
    light = Lighting(sun_dir_world=sun, sun_intensity=0.8)
    g = T_wo[:3, 3]
    ground = _plane(g + np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]]))
    r = rr.render(obj, T_wo, T_wb, proxies=ground, light=light)
    assert r.shadow.max() > 0.9 and np.all((r.shadow >= 0) & (r.shadow <= 1))
    vs, us = np.nonzero(r.shadow > 0.5)
    uv = np.stack([us + r.roi[0], vs + r.roi[1]], 1).astype(float)
    rays, _ = cam.unproject(uv)
    T_world_opt = T_wb @ cam.T_base_opt
    d_world = rays @ T_world_opt[:3, :3].T
    t = (g[2] - T_world_opt[2, 3]) / d_world[:, 2]
    p = T_world_opt[:3, 3] + t[:, None] * d_world  # shadow points on the ground
    rel = (p - g)[:, :2]
    sun_h = sun[:2] / np.linalg.norm(sun[:2])
    assert np.median(rel @ sun_h) < -0.5  # behind the object as seen from the sun
    # where the object covers a pixel fully, no shadow is reported
    assert r.shadow[r.alpha > 0.999].max() == 0.0
    # no sun -> no shadow
    r = rr.render(
        obj, T_wo, T_wb, proxies=ground, light=Lighting(sun_dir_world=sun, sun_intensity=0)
    )
    assert r.shadow.max() == 0.0


def test_gathered_shadow_filter_equals_texel_fetches(cams, renderers):
    """The shadow filter from textureGather gives the same bits as sixteen texelFetch:
    the object's self-shadow and its shadow on a ground proxy, near the map's edges too
    (a low sun: the ground shadow reaches past the map, clamped at its edge)."""
    name = "rgb_center"
    T_wb = vehicle_pose()
    T_wo = place(T_wb, (14.0, 0.5, 0.0))
    g = T_wo[:3, 3]
    ground = _plane(g + np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]]))
    obj = box((0.6, 0.8, 1.8))
    for sun in ([0.45, -0.55, 0.7], [0.9, 0.3, 0.15]):
        light = Lighting(sun_dir_world=np.array(sun), sun_intensity=0.8)
        a = renderer(renderers, cams, name, gather_shadow=False)
        b = renderer(renderers, cams, name, gather_shadow=True)
        ra = a.render(obj, T_wo, T_wb, proxies=ground, light=light)
        rb = b.render(obj, T_wo, T_wb, proxies=ground, light=light)
        assert ra.roi == rb.roi and ra.shadow.max() > 0.5
        assert np.array_equal(ra.shadow, rb.shadow)
        assert np.array_equal(ra.color, rb.color)


def test_long_triangles_get_the_exact_depth_at_every_range(cams, renderers):
    """The depth (reversed Z, ``near / z`` in a float buffer) is interpolated from the
    vertices, exactly (1/z is affine on the screen): a 6 m x 2 m slab of two triangles
    1 cm above a ground proxy is wholly visible, 1 mm below it wholly hidden, near
    (12-18 m) and far (150-156 m, where 1 mm is 7e-6 of the distance)."""
    name = "rgb_highres_center"
    rr = renderer(renderers, cams, name)
    T_wb = vehicle_pose()
    no_sun = Lighting(sun_intensity=0.0)

    def slab(h: float) -> ObjectMesh:
        v = np.array([[0.0, -1, h], [6.0, -1, h], [6.0, 1.0, h], [0.0, 1.0, h]])
        return ObjectMesh(
            v, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.4, np.float32),
            np.ones(4, np.float32),
        )  # fmt: skip

    above, below = slab(0.01), slab(-0.001)
    for ahead in (12.0, 150.0):
        T_wo = T_wb @ make_T(np.eye(3), (ahead, -0.5, 0.0))
        quad = np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]])
        ground = _plane(transform_points(T_wo, quad))  # the object frame's z = 0
        alone = rr.render(above, T_wo, T_wb, light=no_sun).alpha.sum()
        assert alone > (10000 if ahead < 100 else 20)
        seen = rr.render(above, T_wo, T_wb, proxies=ground, light=no_sun).alpha.sum()
        assert seen > 0.999 * alone
        assert rr.render(below, T_wo, T_wb, proxies=ground, light=no_sun).alpha.sum() == 0.0


def test_the_proxy_bias_is_resolved_far_away(cams, renderers):
    """The float depth resolves the proxies' relative bias (``PROXY_DEPTH_BIAS``, 2e-4)
    at 150-450 m: a panel facing the camera 1e-4 of the distance behind a wall proxy
    stays visible, 3e-4 behind it is hidden (a 24-bit fixed-point ``near / z`` has steps
    of 1.8e-4 to 5.4e-4 of the distance there)."""
    import renderer.object_render as ormod

    name = "rgb_highres_center"
    rr = renderer(renderers, cams, name)
    cam = cams[name]
    T_wb = vehicle_pose()
    T_w_opt = T_wb @ cam.T_base_opt
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
    no_sun = Lighting(sun_intensity=0.0)
    assert ormod.PROXY_DEPTH_BIAS == pytest.approx(2e-4)
    for D in (150.0, 300.0, 450.0):
        half = D / 150.0
        panel = ObjectMesh(
            half * quad, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.4, np.float32),
            np.ones(4, np.float32),
        )  # fmt: skip
        at_D = T_w_opt @ make_T(np.eye(3), (0.0, 0.0, D))
        wall = _plane(transform_points(at_D, 10.0 * half * quad))
        for behind, seen in ((1e-4, True), (3e-4, False)):
            T_wo = T_w_opt @ make_T(np.eye(3), (0.0, 0.0, D * (1.0 + behind)))
            alone = rr.render(panel, T_wo, T_wb, light=no_sun).alpha.sum()
            got = rr.render(panel, T_wo, T_wb, proxies=wall, light=no_sun).alpha.sum()
            assert alone > 300
            assert (got > 0.999 * alone) if seen else (got == 0.0), (D, behind, got, alone)


def test_proxy_layers_hidden_behind_the_nearest_change_nothing(cams, renderers):
    """The proxies' shading runs where a proxy's depth is the one kept (depth pass, then
    GL_EQUAL): ground planes stacked 5-40 cm below the ground the object stands on, drawn
    before and after it, leave the render (colour, coverage, shadow) bit-equal to the
    ground alone."""
    name = "rgb_center"
    rr = renderer(renderers, cams, name)
    T_wb = vehicle_pose()
    T_wo = place(T_wb, (14.0, 0.5, 0.0))
    g = T_wo[:3, 3]
    quad = np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]])
    top = _plane(g + quad)
    layers = [_plane(g + quad - [0, 0, dz]) for dz in (0.05, 0.4)]
    stack = [layers[0], top, layers[1]]
    v = np.concatenate([m.vertices for m in stack])
    f = np.concatenate([m.faces + 4 * i for i, m in enumerate(stack)])
    stacked = ProxyMesh(v, f)
    light = Lighting(sun_dir_world=np.array([0.45, -0.55, 0.7]), sun_intensity=0.8)
    obj = box((0.6, 0.8, 1.8))
    ra = rr.render(obj, T_wo, T_wb, proxies=top, light=light)
    rb = rr.render(obj, T_wo, T_wb, proxies=stacked, light=light)
    assert ra.roi == rb.roi and ra.shadow.max() > 0.5
    for k in ("color", "alpha", "shadow"):
        assert np.array_equal(getattr(ra, k), getattr(rb, k)), k


def test_a_shadow_map_drawn_before_is_reused_only_for_the_same_object_and_sun(cams, renderers):
    """A renderer draws a shadow map once per object, sun and map size: the object seen
    again (here from a train 0.2 m nearer, the map's size unchanged) reuses it and
    renders what a fresh renderer does; another sun or another mesh is drawn anew."""
    name = "rgb_center"
    T_wb = vehicle_pose()
    T_wo = place(T_wb, (16.0, 0.5, 0.0))
    g = T_wo[:3, 3]
    ground = _plane(g + np.array([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0.0]]))
    obj = box((0.6, 0.8, 1.8))
    sun_a = Lighting(sun_dir_world=np.array([0.45, -0.55, 0.7]), sun_intensity=0.8)
    sun_b = Lighting(sun_dir_world=np.array([-0.5, 0.4, 0.6]), sun_intensity=0.8)
    nearer = T_wb @ make_T(np.eye(3), (0.2, 0.0, 0.0))
    cached = ObjectRenderer(cams[name])
    cached.render(obj, T_wo, T_wb, proxies=ground, light=sun_a)
    first = dict(cached._sm_drawn)  # size -> what its map holds (a new tuple when drawn)
    other_mesh = box((0.6, 0.8, 1.7))
    for T, light, mesh in ((nearer, sun_a, obj), (nearer, sun_b, obj), (T_wb, sun_a, other_mesh)):
        got = cached.render(mesh, T_wo, T, proxies=ground, light=light)
        fresh = ObjectRenderer(cams[name]).render(mesh, T_wo, T, proxies=ground, light=light)
        assert got.roi == fresh.roi and got.shadow.max() > 0.5
        assert np.array_equal(got.shadow, fresh.shadow) and np.array_equal(got.color, fresh.color)
        redrawn = [k for k, v in cached._sm_drawn.items() if first.get(k) is not v]
        assert (redrawn == []) == (light is sun_a and mesh is obj)
        first = dict(cached._sm_drawn)
    cached.close()
