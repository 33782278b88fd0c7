"""Textures rendered per pixel: a checkerboard's checks land where the camera model puts
them, minified textures average in linear light, normal maps bend the shading normal."""

from __future__ import annotations

import numpy as np
import pytest

from geometry.camera import CameraModel
from geometry.transforms import make_T
from renderer.assets.user_mesh import load_user_mesh
from renderer.lighting import Lighting, srgb_to_linear
from renderer.mesh import Material, ObjectMesh
from renderer.object_render import ObjectRenderer, material_defines
from tests.renderer.gltf_build import checkerboard, textured_box

FLAT = Lighting(sun_intensity=0.0, ambient_rgb=(1.0, 1.0, 1.0), sky_rgb=(1.0, 1.0, 1.0))


@pytest.fixture(scope="module")
def cam() -> CameraModel:
    K = np.array([[800.0, 0, 320.0], [0, 800.0, 240.0], [0, 0, 1]])
    return CameraModel("test", 640, 480, K, np.zeros(5), make_T(np.eye(3), [0.0, 0.0, 1.0]))


@pytest.fixture(scope="module")
def rr(cam: CameraModel) -> ObjectRenderer:
    return ObjectRenderer(cam, antialias="ssaa2")


def yaw_T(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return make_T(R, xyz)


def expected_checks(cam: CameraModel, roi, mesh: ObjectMesh, T_world_obj: np.ndarray):
    """Analytic check parity (+1 bright, -1 dark, 0 off the face) of each ROI pixel:
    the pixel's ray meets the box's front face (object +x) at a point whose UV follows
    from the face's corners."""
    u0, v0, u1, v1 = roi
    uu, vv = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
    rays, _ = cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1).astype(float))
    T_obj_opt = np.linalg.inv(T_world_obj) @ cam.T_base_opt  # vehicle at the origin
    d = rays @ T_obj_opt[:3, :3].T
    o = T_obj_opt[:3, 3]
    xf = mesh.vertices[:, 0].max()
    t = (xf - o[0]) / d[:, 0]
    p = o + t[:, None] * d
    # the front face's vertices (normal +x): uv is affine in (y, z) on it
    front = mesh.normals[:, 0] > 0.99
    A = np.c_[mesh.vertices[front][:, 1:], np.ones(front.sum())]
    coef, *_ = np.linalg.lstsq(A, mesh.uv[front].astype(float), rcond=None)
    uv = np.c_[p[:, 1:], np.ones(len(p))] @ coef
    inside = np.all((uv > 0) & (uv < 1), axis=1)
    ij = np.floor(uv * 8).astype(int)
    parity = np.where((ij[:, 0] + ij[:, 1]) % 2 == 0, -1, 1)
    # pixels within ~1 px of a check edge are mixed: left out
    g = uv * 8
    px = np.abs(t) / cam.fx / (np.ptp(mesh.vertices[:, 1]) / 8)  # checks per pixel across
    mixed = np.min(np.abs(g - np.round(g)), axis=1) < 1.0 * px
    out = np.where(inside & ~mixed, parity, 0)
    return out.reshape(uu.shape)


def test_checkerboard_box_shows_its_checks_where_the_camera_puts_them(cam, rr) -> None:
    mesh = load_user_mesh(textured_box(), "glb")
    assert mesh.meta["up"] == "y" and abs(mesh.size[2] - 1.8) < 1e-6  # stands, +Y up
    T = yaw_T(180.0, (6.0, 0.0, 0.0))  # its front (+x) faces the camera
    r = rr.render(mesh, T, np.eye(4), light=FLAT)
    lum = r.color @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    dark, bright = srgb_to_linear(20 / 255), srgb_to_linear(235 / 255)
    want = expected_checks(cam, r.roi, mesh, T)
    full = r.alpha > 0.999
    sel = (want != 0) & full
    assert sel.sum() > 2000
    got = np.where(lum > 0.5 * (dark + bright), 1, -1)
    agree = float(np.mean(got[sel] == want[sel]))
    assert agree > 0.99, agree
    # checks, not gradients: the two populations sit at the texture's two values, seen
    # facing the camera under a uniform white sky: (1 - F0) albedo + F0, F0 = 0.04
    for sign, value in ((1, bright), (-1, dark)):
        np.testing.assert_allclose(np.median(lum[sel & (want == sign)]), 0.96 * value + 0.04,
                                   atol=0.01)  # fmt: skip
    # eight checks across the face along the row through the middle of a check row
    mid = int(np.argmax((want != 0).sum(axis=1)))
    line = got[mid][full[mid]]
    assert int(np.sum(line[1:] != line[:-1])) == 7


def test_minified_texture_averages_in_linear_light(cam, rr) -> None:
    """A 1-texel checkerboard far away: the mipmaps average black and white in linear
    light (0.5), not in sRGB (0.5 sRGB = 0.21 linear)."""
    tex = checkerboard(n=256, px=1, lo=0, hi=255)
    v = np.array([[0, -1, 0], [0, 1, 0], [0, 1, 2], [0, -1, 2]], float)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    mesh = ObjectMesh(v, [[0, 1, 2], [0, 2, 3]], np.ones((4, 3)), np.ones(4), uv=uv,
                      materials=[Material(base_color_texture=np.dstack([tex, tex[..., :1]]),
                                          specular=False)])  # fmt: skip
    r = rr.render(mesh, yaw_T(180.0, (40.0, 0.0, 0.0)), np.eye(4), light=FLAT)
    inner = r.alpha > 0.999
    assert inner.sum() > 100
    np.testing.assert_allclose(float(np.median(r.color[inner][:, 1])), 0.5, atol=0.04)


def test_normal_map_tilts_the_shading_normal(cam, rr) -> None:
    """A flat quad facing the camera with a normal map of constant tilt a towards +u:
    the Lambertian sun term follows the tilted normal, dot(n', sun)."""
    a = np.radians(40.0)
    nt = np.array([np.sin(a), 0.0, np.cos(a)])
    nmap = np.tile(np.round((nt * 0.5 + 0.5) * 255).astype(np.uint8), (16, 16, 1))
    v = np.array([[0, -1, 0], [0, 1, 0], [0, 1, 2], [0, -1, 2]], float)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    tan = np.tile([0.0, 1.0, 0.0, 1.0], (4, 1))  # +u along object +y; bitangent +v = down
    mat = Material(normal_texture=nmap, specular=False)
    mesh = ObjectMesh(
        v,
        [[0, 1, 2], [0, 2, 3]],
        np.full((4, 3), 0.5),
        np.ones(4),
        uv=uv,
        normals=np.tile([1.0, 0, 0], (4, 1)),
        tangents=tan,
        materials=[mat],
    )
    # a low sun (no shadow map: the single-sided quad's self-shadowing is not under test)
    light = Lighting(sun_dir_world=[-0.5, -1.0, 0.01], sun_intensity=1.0, ambient_rgb=(0, 0, 0),
                     sky_rgb=(0, 0, 0))  # fmt: skip
    T = yaw_T(180.0, (8.0, 0.0, 0.0))
    r = rr.render(mesh, T, np.eye(4), light=light)
    inner = r.alpha > 0.999
    # object frame: +x = -world x, +y = -world y; n' = cos a * x_obj + sin a * y_obj
    R = T[:3, :3]
    n_world = R @ (np.cos(a) * np.array([1.0, 0, 0]) + np.sin(a) * np.array([0, 1.0, 0]))
    want = 0.5 * max(float(n_world @ light.sun_dir_world), 0.0)
    flat = 0.5 * max(float((R @ np.array([1.0, 0, 0])) @ light.sun_dir_world), 0.0)
    got = float(np.median(r.color[inner][:, 0]))
    assert abs(got - want) < 0.02 and abs(want - flat) > 0.1, (got, want, flat)


def test_shader_variant_compiles_only_what_the_material_uses() -> None:
    """The object shader's defines follow the material and the bound textures."""
    tex = checkerboard(n=8, px=1, lo=0, hi=255)
    plain = Material(specular=False)
    assert material_defines(plain, base=False, normal=False, mr=False, shadow=False) == ()
    bark = Material(base_color_texture=tex, triplanar_m=0.4, specular=False)
    assert material_defines(bark, base=True, normal=True, mr=False, shadow=True) == (
        "HAS_BASE", "TRIPLANAR", "SHADOW",
    )  # fmt: skip
    pbr = Material(alpha_cutoff=0.5, specular=True)
    assert material_defines(pbr, base=True, normal=True, mr=True, shadow=False) == (
        "HAS_BASE", "NORMAL_MAP", "ALPHA_CUTOFF", "SPECULAR", "HAS_MR",
    )  # fmt: skip
    assert "HAS_MR" not in material_defines(plain, base=False, normal=False, mr=True, shadow=False)


def test_two_materials_in_one_mesh_each_shade_with_their_own(cam, rr) -> None:
    """A textured quad (a 1-texel checkerboard averaging to 0.5 in linear light) beside a
    plain one of base colour (0.2, 0.4, 0.6): each keeps its own material although they
    are drawn with two shader variants in one render."""
    tex = checkerboard(n=256, px=1, lo=0, hi=255)
    v = np.array([[0, -1, 0], [0, 0, 0], [0, 0, 2], [0, -1, 2],
                  [0, 0.05, 0], [0, 1, 0], [0, 1, 2], [0, 0.05, 2]], float)  # fmt: skip
    uv = np.tile(np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32), (2, 1))
    faces = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]
    mats = [
        Material(base_color_texture=np.dstack([tex, tex[..., :1]]), specular=False),
        Material(base_color=(0.2, 0.4, 0.6, 1.0), specular=False),
    ]
    mesh = ObjectMesh(v, faces, np.ones((8, 3)), np.ones(8), uv=uv, materials=mats,
                      face_material=np.array([0, 0, 1, 1]))  # fmt: skip
    r = rr.render(mesh, yaw_T(180.0, (40.0, 0.0, 0.0)), np.eye(4), light=FLAT)
    inner = r.alpha > 0.999
    u0 = r.roi[0]
    cols = np.arange(r.alpha.shape[1]) + u0
    # object +y = world -y = image right of the centre column (camera looks along +x)
    right = inner & (cols[None, :] > cam.K[0, 2] + 3)
    left = inner & (cols[None, :] < cam.K[0, 2] - 3)
    assert right.sum() > 50 and left.sum() > 50
    np.testing.assert_allclose(np.median(r.color[right], axis=0), [0.2, 0.4, 0.6], atol=0.01)
    np.testing.assert_allclose(np.median(r.color[left], axis=0), [0.5, 0.5, 0.5], atol=0.04)
