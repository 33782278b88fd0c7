"""The camera model: real OSDaR23 annotations, projection round trips, distortion folds, GL."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from geometry.camera import (
    T_CAM_OPT,
    CameraModel,
    gl_projection,
    gl_projection_reversed_z,
    load_cameras,
    undistort_normalized,
    valid_radius,
)
from geometry.transforms import invert_T, make_T, quat_to_matrix
from osdar_platform.shared_data import real_labels_path

log = logging.getLogger(__name__)

REAL_LABELS = real_labels_path()


@pytest.fixture(scope="module")
def real_raw() -> dict:
    return json.loads(REAL_LABELS.read_text())


@pytest.fixture(scope="module")
def real_cams(real_raw) -> dict[str, CameraModel]:
    return load_cameras(real_raw)


def _text_attr(entry: dict, name: str) -> str | None:
    for t in entry.get("attributes", {}).get("text", []):
        if t["name"] == name:
            return t["val"]
    return None


def _dist_to_polyline(q: np.ndarray, poly: np.ndarray) -> float:
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(((q - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * ab - q, axis=1).min())


def annotation_errors(raw: dict, cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Pixel errors of real 3D annotations projected into ``cam`` against the 2D ones.

    Returns (rail errors: distance of projected poly3d rail points to the poly2d rail of
    the same side, within its vertical extent; cuboid errors: projected cuboid centre to
    bbox centre).
    """
    ol = raw["openlabel"]
    rails, centres = [], []
    for frame in ol["frames"].values():
        for obj in frame.get("objects", {}).values():
            od = obj["object_data"]
            p2 = [e for e in od.get("poly2d", []) if e["coordinate_system"] == cam.name]
            for e3 in od.get("poly3d", []):
                if e3["coordinate_system"] != "lidar":
                    continue
                side = _text_attr(e3, "railSide")
                match = [e for e in p2 if _text_attr(e, "railSide") == side]
                if not match:
                    continue
                poly = np.asarray(match[0]["val"], dtype=float).reshape(-1, 2)
                uv, ok = cam.project(np.asarray(e3["val"], dtype=float).reshape(-1, 3))
                ok &= cam.in_image(uv)
                vmin, vmax = poly[:, 1].min(), poly[:, 1].max()
                for q in uv[ok]:
                    if vmin <= q[1] <= vmax:
                        rails.append(_dist_to_polyline(q, poly))
            cub = od.get("cuboid", [])
            bb = [e for e in od.get("bbox", []) if e["coordinate_system"] == cam.name]
            if cub and bb:
                uv, ok = cam.project(np.asarray(cub[0]["val"][:3], dtype=float)[None])
                if ok[0] and cam.in_image(uv)[0]:
                    centres.append(float(np.linalg.norm(uv[0] - np.asarray(bb[0]["val"][:2]))))
    return np.asarray(rails), np.asarray(centres)


# Bounds: the annotations' own noise (rails clicked on 2464 px images, cuboid centres vs
# visible-box centres of partly occluded objects 25-250 m away) is ~10 px on rgb_center
# and ~20 px on rgb_highres_center (1.6x the focal length). A wrong frame convention
# misses by hundreds of pixels.
BOUNDS = {
    "rgb_center": {"rail_median": 15.0, "rail_p90": 40.0, "box_median": 15.0, "box_p90": 40.0},
    "rgb_highres_center": {
        "rail_median": 30.0,
        "rail_p90": 75.0,
        "box_median": 30.0,
        "box_p90": 80.0,
    },
}


@pytest.mark.parametrize("name", ["rgb_center", "rgb_highres_center"])
def test_real_annotations_project_onto_their_2d_counterparts(real_raw, real_cams, name):
    rails, boxes = annotation_errors(real_raw, real_cams[name])
    assert len(rails) > 100 and len(boxes) > 100
    b = BOUNDS[name]
    log.info(
        "%s: rails median %.1f p90 %.1f px (n=%d); cuboid centres median %.1f p90 %.1f px (n=%d)",
        name,
        np.median(rails),
        np.percentile(rails, 90),
        len(rails),
        np.median(boxes),
        np.percentile(boxes, 90),
        len(boxes),
    )
    assert np.median(rails) < b["rail_median"]
    assert np.percentile(rails, 90) < b["rail_p90"]
    assert np.median(boxes) < b["box_median"]
    assert np.percentile(boxes, 90) < b["box_p90"]


OPTICAL_Q = [0.5, -0.5, 0.5, -0.5]  # OSDaR23's readme: the optical rotation (x, y, z, w)


def test_optical_rotation_is_the_readme_quaternion_applied_as_frame_rotation():
    """R_cam_opt = R(q): the quaternion's inverse maps vectors cam -> opt (OSDAR23.md)."""
    assert np.allclose(quat_to_matrix(OPTICAL_Q), T_CAM_OPT[:3, :3], atol=1e-12)


@pytest.mark.parametrize(
    ("optical_inverted", "extrinsic_inverted"), [(True, False), (False, True), (True, True)]
)
def test_the_other_three_conventions_miss_by_hundreds_of_pixels(
    real_raw, real_cams, optical_inverted, extrinsic_inverted
):
    """The optical quaternion or the extrinsic read the other way round (OSDAR23.md)."""
    for name in ("rgb_center", "rgb_highres_center"):
        cam = real_cams[name]
        T_base_cam = invert_T(cam.T_base_cam) if extrinsic_inverted else cam.T_base_cam
        R_cam_opt = quat_to_matrix(OPTICAL_Q)
        R_cam_opt = R_cam_opt.T if optical_inverted else R_cam_opt
        T_base_opt = T_base_cam @ make_T(R_cam_opt, np.zeros(3))
        wrong = CameraModel(
            name, cam.width, cam.height, cam.K, cam.dist, T_base_opt @ invert_T(T_CAM_OPT)
        )
        _, boxes = annotation_errors(real_raw, wrong)
        # rgb_center is mounted almost level, 2 m up: inverting its extrinsic mostly moves
        # it 4 m down (~90 px at 200 m); the highres camera is pitched 6.5 deg.
        bound = 60.0 if (name == "rgb_center" and not optical_inverted) else 200.0
        assert len(boxes) == 0 or np.median(boxes) > bound, (name, np.median(boxes))


# ---------------------------------------------------------------- projection round trips
@pytest.mark.parametrize(
    "name", ["rgb_center", "rgb_highres_center", "rgb_highres_right", "rgb_left"]
)
def test_pixel_round_trip_everywhere_including_corners(real_cams, name):
    cam = real_cams[name]
    u = np.linspace(-0.5, cam.width - 0.5, 41)
    v = np.linspace(-0.5, cam.height - 0.5, 29)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    rays, ok = cam.unproject(uv)
    assert ok.all(), "every pixel of the real image must have a ray"
    p_base = (cam.T_base_opt[:3, :3] @ (rays * 37.0).T).T + cam.T_base_opt[:3, 3]
    uv2, ok2 = cam.project(p_base)
    assert ok2.all()
    assert np.abs(uv2 - uv).max() < 1e-6


def test_distortion_round_trip_with_tangential_terms():
    dist = np.array([-0.0655375, -0.329857, 1e-3, -5e-4, 2.48002])
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.35, 0.35, (5000, 2))
    from geometry.camera import distort_normalized

    back, ok = undistort_normalized(distort_normalized(xy, dist), dist)
    assert ok.all()
    assert np.abs(back - xy).max() < 1e-10


def test_real_highres_right_has_no_fold_in_the_image(real_cams):
    cam = real_cams["rgb_highres_right"]  # k3 = 2.48
    corner = cam.pixel_to_normalized(np.array([[-0.5, -0.5]]))
    assert np.hypot(*corner[0]) < cam.r_valid


def test_folding_lens_flags_beyond_valid_radius():
    # r_d = r - 0.5 r^3 turns back at r = sqrt(2/3) = 0.8165 (r_d = 0.5443).
    dist = np.array([-0.5, 0.0, 0.0, 0.0, 0.0])
    assert valid_radius(dist) == pytest.approx(np.sqrt(2.0 / 3.0), rel=1e-12)
    rd = np.array([[0.3, 0.0], [0.54, 0.0], [0.56, 0.0], [0.0, 0.9]])
    xy, ok = undistort_normalized(rd, dist)
    assert ok.tolist() == [True, True, False, False]
    assert np.isnan(xy[~ok]).all()
    # and the forward direction refuses points beyond the fold instead of wrapping them
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cam = CameraModel("fold", 640, 480, K, dist, np.eye(4))
    p_opt = np.array([[0.5, 0.0, 1.0], [0.9, 0.0, 1.0]])
    uv, ok = cam.project_optical(p_opt)
    assert ok.tolist() == [True, False]
    assert np.isnan(uv[1]).all()


def test_folding_lens_render_map_has_no_folded_pixels():
    dist = np.array([-0.9, 0.0, 0.0, 0.0, 0.0])  # folds at r = 0.609, r_d = 0.406
    K = np.array([[300.0, 0, 320], [0, 300.0, 240], [0, 0, 1]])
    cam = CameraModel("fold", 640, 480, K, dist, np.eye(4))
    setup = cam.render_setup()
    invalid = setup.map_x < 0
    # the image corners (r_d = 1.33) are beyond the fold, the centre is not
    assert invalid[0, 0] and invalid[-1, -1] and not invalid[240, 320]
    # within each row the valid map increases strictly: no pixel maps back onto another
    for row in (0, 120, 240, 479):
        mx = setup.map_x[row][~invalid[row]]
        assert np.all(np.diff(mx) > 0)


def test_points_behind_or_at_the_camera_are_flagged(real_cams):
    cam = real_cams["rgb_center"]
    p_opt = np.array([[0.0, 0.0, -5.0], [0.1, 0.1, 0.0], [1.0, 1.0, 1e-12], [0.0, 0.0, 10.0]])
    with np.errstate(all="raise"):
        uv, ok = cam.project_optical(p_opt)
    assert ok.tolist() == [False, False, False, True]
    assert np.isnan(uv[:3]).all() and np.isfinite(uv[3]).all()


def test_scaled_camera_keeps_pixel_centres_exact(real_cams):
    cam = real_cams["rgb_highres_center"]
    small = cam.scaled(0.25)
    assert (small.width, small.height) == (1028, 626)
    rng = np.random.default_rng(0)
    p = np.column_stack(
        [rng.uniform(10, 80, 200), rng.uniform(-5, 5, 200), rng.uniform(-1, 4, 200)]
    )
    uv, ok = cam.project(p)
    uv_s, ok_s = small.project(p)
    sx, sy = small.width / cam.width, small.height / cam.height
    expect = np.column_stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5])
    assert (ok == ok_s).all()
    assert np.abs(uv_s[ok] - expect[ok]).max() < 1e-9


def test_openlabel_quaternion_is_normalised(real_raw):
    raw = json.loads(json.dumps(real_raw))
    cs = raw["openlabel"]["coordinate_systems"]["rgb_center"]["pose_wrt_parent"]
    cs["quaternion"] = [-3.0 * q for q in cs["quaternion"]]  # non-unit and sign-flipped
    a = load_cameras(real_raw)["rgb_center"]
    b = load_cameras(raw)["rgb_center"]
    assert np.allclose(a.T_base_cam, b.T_base_cam, atol=1e-12)


def test_camera_json_round_trip(real_cams):
    cam = real_cams["rgb_highres_center"].scaled(0.5)
    back = CameraModel.from_json(json.loads(json.dumps(cam.to_json())))
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.T_base_cam, cam.T_base_cam)
    assert back.scale == cam.scale


# ---------------------------------------------------------------- OpenGL projection
def test_gl_projection_maps_pixel_centres():
    K = np.array([[400.0, 0.0, 101.3], [0.0, 410.0, 77.8], [0.0, 0.0, 1.0]])
    W, H = 200, 150
    P = gl_projection(K, W, H, 0.5, 100.0)
    p = np.array([0.3, -0.2, 4.0, 1.0])
    clip = P @ p
    ndc = clip[:3] / clip[3]
    u = K[0, 0] * p[0] / p[2] + K[0, 2]
    v = K[1, 1] * p[1] / p[2] + K[1, 2]
    # framebuffer column/row (from the bottom) whose centre the point hits
    assert (ndc[0] + 1) * W / 2 - 0.5 == pytest.approx(u, abs=1e-9)
    assert (ndc[1] + 1) * H / 2 - 0.5 == pytest.approx(v, abs=1e-9)
    assert gl_projection(K, W, H, 0.5, 100.0) @ np.array([0, 0, 0.5, 1]) @ np.array(
        [0, 0, 1, 0]
    ) / 0.5 == pytest.approx(-1.0)


def test_reversed_z_projection_keeps_x_y_and_gives_near_over_z():
    """Reversed, infinite Z: the same x, y as gl_projection; window depth (clip z over w,
    with clip z in [0, w]) is near / z: 1 at the near plane, falling towards 0."""
    K = np.array([[400.0, 0.0, 101.3], [0.0, 410.0, 77.8], [0.0, 0.0, 1.0]])
    W, H, near = 200, 150, 0.05
    P = gl_projection_reversed_z(K, W, H, near)
    Q = gl_projection(K, W, H, near, 100.0)
    for z in (near, 4.0, 1234.5):
        p = np.array([0.3 * z, -0.2 * z, z, 1.0])
        clip, ref = P @ p, Q @ p
        np.testing.assert_allclose(clip[[0, 1, 3]], ref[[0, 1, 3]], rtol=1e-15)
        assert clip[2] / clip[3] == pytest.approx(near / z, rel=1e-15)
    with pytest.raises(ValueError):
        gl_projection_reversed_z(K, W, H, 0.0)


@pytest.mark.gl
def test_gl_render_lands_where_the_model_projects():
    """A small square rendered with gl_projection: its pixel centroid is the projection."""
    moderngl = pytest.importorskip("moderngl")
    try:
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # pragma: no cover - depends on the machine
        pytest.fail(f"EGL context unavailable: {exc}")
    W, H = 320, 240
    K = np.array([[300.0, 0.0, 170.25], [0.0, 300.0, 101.75], [0.0, 0.0, 1.0]])
    prog = ctx.program(
        vertex_shader="""#version 330
        uniform mat4 P; in vec3 p; void main(){ gl_Position = P * vec4(p, 1.0); }""",
        fragment_shader="""#version 330
        out vec4 c; void main(){ c = vec4(1.0); }""",
    )
    prog["P"].write(gl_projection(K, W, H, 0.1, 100.0).T.astype("f4").tobytes())
    centre = np.array([0.4, -0.3, 5.0])
    h = 0.05
    quad = (
        np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, -h, 0], [h, h, 0], [-h, h, 0]]) + centre
    )
    vbo = ctx.buffer(quad.astype("f4").tobytes())
    vao = ctx.vertex_array(prog, [(vbo, "3f", "p")])
    fbo = ctx.simple_framebuffer((W, H), components=1)
    fbo.use()
    fbo.clear(0.0)
    vao.render()
    img = np.frombuffer(fbo.read(components=1), dtype=np.uint8).reshape(H, W).astype(float)
    vv, uu = np.nonzero(img)
    w = img[vv, uu]
    centroid = np.array([(uu * w).sum() / w.sum(), (vv * w).sum() / w.sum()])
    expect = K[:2, :2] @ (centre[:2] / centre[2]) + K[:2, 2]
    # The square covers 6x6 px, rasterised at pixel centres: its centroid is exact to
    # the coverage quantisation (half a pixel at worst, much less on average).
    assert np.abs(centroid - expect).max() < 0.5
    ctx.release()
