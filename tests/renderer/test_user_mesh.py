"""Tests of renderer/assets/user_mesh.py: uploads from bytes, refusals, units, colours."""

from __future__ import annotations

import json
import logging
import os

import numpy as np
import pytest
import trimesh
from trimesh.exchange.gltf import export_gltf

from renderer.assets.user_mesh import MeshError, load_user_mesh, welded_normals
from tests.renderer.gltf_build import textured_box

EXTENTS = np.array([1.0, 2.0, 3.0])


def colored_box(offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=EXTENTS)
    b.apply_translation(offset)
    b.visual.vertex_colors = np.tile([255, 0, 0, 255], (len(b.vertices), 1)).astype(np.uint8)
    return b


def to_bytes(mesh: trimesh.Trimesh, ft: str) -> bytes:
    data = mesh.export(file_type=ft)
    return data.encode() if isinstance(data, str) else data


@pytest.mark.parametrize("ft", ["glb", "obj", "ply", "stl", "off"])
def test_round_trip_from_bytes(ft: str) -> None:
    m = load_user_mesh(to_bytes(colored_box(offset=(5.0, -3.0, 7.0)), ft), ft, name="crate")
    # glTF is +Y up with its front +Z (its z -> our x, x -> y, y -> z); OBJ/PLY +Z up
    want = EXTENTS[[2, 0, 1]] if ft == "glb" else EXTENTS
    np.testing.assert_allclose(m.size, want, atol=1e-6)
    assert m.meta["up"] == ("y" if ft == "glb" else "z")
    assert m.name == "crate" and m.meta["source"] == ft
    assert abs(m.vertices[:, 2].min()) < 1e-12  # standing on the ground
    lo, hi = m.bounds
    np.testing.assert_allclose(0.5 * (lo[:2] + hi[:2]), 0.0, atol=1e-12)  # footprint centre
    assert len(m.faces) == 12
    tm = trimesh.Trimesh(m.vertices, m.faces, process=True)
    assert tm.is_watertight and tm.volume > 0  # outward
    assert np.all((m.colors >= 0) & (m.colors <= 1)) and np.all(m.reflectivity > 0)
    if ft in ("glb", "ply"):  # vertex colours kept (sRGB red -> linear red)
        np.testing.assert_allclose(m.colors, np.tile([1.0, 0.0, 0.0], (len(m.colors), 1)))
        assert m.meta["color_source"] == "vertex"


def test_default_grey_and_up_axis() -> None:
    data = to_bytes(trimesh.creation.box(extents=EXTENTS), "ply")
    m = load_user_mesh(data, ".PLY", up="y")
    # y up: the file's z (front) becomes x, its x becomes y, its y becomes z
    np.testing.assert_allclose(m.size, [3.0, 1.0, 2.0], atol=1e-9)
    assert m.meta["color_source"] == "default" and np.ptp(m.colors) == 0.0
    for up in ("x", "-x", "-y", "-z"):
        assert load_user_mesh(data, "ply", up=up).meta["watertight"]


def test_gltf_data_uri_ok_external_uri_refused() -> None:
    scene = trimesh.Scene(colored_box())
    embedded = export_gltf(scene, embed_buffers=True)["model.gltf"]
    m = load_user_mesh(embedded, "gltf", up="z")
    np.testing.assert_allclose(m.size, EXTENTS, atol=1e-6)

    external = export_gltf(scene)["model.gltf"]  # buffers in side files
    with pytest.raises(MeshError, match="external resource"):
        load_user_mesh(external, "gltf")
    doc = json.loads(embedded)
    doc["images"] = [{"uri": "https://example.com/texture.png"}]
    with pytest.raises(MeshError, match=r"images\[0\].*external"):
        load_user_mesh(json.dumps(doc).encode(), "gltf")
    doc["images"] = [{"uri": "file:///etc/passwd"}]
    with pytest.raises(MeshError, match="external"):
        load_user_mesh(json.dumps(doc).encode(), "gltf")


@pytest.mark.parametrize("ft", ["glb", "obj", "ply"])
def test_caps(ft: str) -> None:
    data = to_bytes(trimesh.creation.icosphere(subdivisions=3), ft)  # 642 v, 1280 f
    assert len(load_user_mesh(data, ft).faces) == 1280
    with pytest.raises(MeshError, match="faces, more than the cap"):
        load_user_mesh(data, ft, max_faces=1000)
    with pytest.raises(MeshError, match="vertices, more than the cap"):
        load_user_mesh(data, ft, max_vertices=600)


@pytest.mark.parametrize("ft", ["glb", "gltf", "obj", "ply"])
def test_garbage_refused(ft: str) -> None:
    rng = np.random.default_rng(0)
    for junk in (b"hello world", rng.bytes(4096), b"glTF" + os.urandom(64), b"ply\n" + b"\0" * 50):
        with pytest.raises(MeshError):
            load_user_mesh(junk, ft)
    with pytest.raises(MeshError, match="empty"):
        load_user_mesh(b"", ft)


def test_bad_arguments_and_truncated_files() -> None:
    data = to_bytes(colored_box(), "glb")
    with pytest.raises(MeshError, match="unsupported"):
        load_user_mesh(data, "fbx")
    with pytest.raises(MeshError, match="up must be"):
        load_user_mesh(data, "glb", up="w")
    with pytest.raises(MeshError, match="scale"):
        load_user_mesh(data, "glb", scale=-1.0)
    for cut in (len(data) // 2, 30):
        with pytest.raises(MeshError):
            load_user_mesh(data[:cut], "glb")
    pts = trimesh.PointCloud(np.random.default_rng(1).normal(size=(20, 3)))
    with pytest.raises(MeshError, match="no"):
        load_user_mesh(to_bytes(pts, "ply"), "ply")


@pytest.mark.parametrize("ft", ["obj", "ply", "glb"])
def test_nan_vertices_refused(ft: str) -> None:
    b = trimesh.creation.box()
    v = b.vertices.copy()
    v[3] = np.nan
    bad = trimesh.Trimesh(v, b.faces, process=False)
    with pytest.raises(MeshError, match="NaN"):
        load_user_mesh(to_bytes(bad, ft), ft)


def test_units_scale_and_warning(caplog) -> None:
    mm = trimesh.creation.box(extents=EXTENTS * 1000.0)  # a model in millimetres
    data = to_bytes(mm, "ply")
    with caplog.at_level(logging.WARNING, logger="renderer.assets.user_mesh"):
        m = load_user_mesh(data, "ply")
    assert "implausible" in caplog.text
    np.testing.assert_allclose(m.size, EXTENTS * 1000.0)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="renderer.assets.user_mesh"):
        m = load_user_mesh(data, "ply", scale=0.001)
    assert "implausible" not in caplog.text
    np.testing.assert_allclose(m.size, EXTENTS, atol=1e-9)


def test_inward_faces_flipped() -> None:
    b = trimesh.creation.box(extents=EXTENTS)
    inv = trimesh.Trimesh(b.vertices, b.faces[:, ::-1], process=False)
    m = load_user_mesh(to_bytes(inv, "ply"), "ply")
    assert m.meta["flipped"]
    assert trimesh.Trimesh(m.vertices, m.faces).volume > 0


# ----------------------------------------------------------------- OBJ + MTL archives
def obj_quad_archive(kind: str, mtl_map: str = "tex/check.png", extra: dict | None = None) -> bytes:
    """An OBJ quad (2 x 2 m, facing +x, z up) with an MTL and a PNG checkerboard."""
    import io as _io
    import tarfile
    import zipfile

    from PIL import Image

    from tests.renderer.gltf_build import checkerboard

    obj = (
        "mtllib quad.mtl\nv 0 -1 0\nv 0 1 0\nv 0 1 2\nv 0 -1 2\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl checks\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    )
    mtl = f"newmtl checks\nKd 1 1 1\nmap_Kd {mtl_map}\n"
    png = _io.BytesIO()
    Image.fromarray(checkerboard(n=2, px=8, lo=0, hi=255)).save(png, format="PNG")
    files = {"model/quad.obj": obj.encode(), "model/quad.mtl": mtl.encode(),
             "model/tex/check.png": png.getvalue(), **(extra or {})}  # fmt: skip
    buf = _io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buf, "w") as z:
            for k, v in files.items():
                z.writestr(k, v)
    else:
        with tarfile.open(fileobj=buf, mode="w:gz") as t:
            for k, v in files.items():
                info = tarfile.TarInfo(k)
                info.size = len(v)
                t.addfile(info, _io.BytesIO(v))
    return buf.getvalue()


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_obj_mtl_texture_archive(kind: str) -> None:
    m = load_user_mesh(obj_quad_archive(kind), kind, name="sign")
    assert m.meta["source"] == "obj" and m.meta["color_source"] == "texture" and m.textured
    tex = m.materials[0].base_color_texture
    assert tex.shape == (16, 16, 4)
    # OBJ's v is up the image, ours (glTF) down: the vertex at the quad's top-left
    # (y = +1, z = 2 after re-centring: the file's vt 1 1) samples the image's top row
    top_right = np.argmax(m.vertices[:, 1] + m.vertices[:, 2])
    np.testing.assert_allclose(m.uv[top_right], [1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(m.size, [0.0, 2.0, 2.0], atol=1e-9)  # +Z up kept for OBJ


def test_archive_refusals() -> None:
    with pytest.raises(MeshError, match="not a file inside the upload"):
        load_user_mesh(obj_quad_archive("zip", mtl_map="../../../../etc/hostname"), "zip")
    two = obj_quad_archive("zip", extra={"model/other.ply": b"ply\n"})
    with pytest.raises(MeshError, match="exactly one mesh file"):
        load_user_mesh(two, "zip")
    with pytest.raises(MeshError, match="archive refused"):
        load_user_mesh(b"PK\x03\x04 not really a zip", "zip")


def test_normals_without_the_file_smooth_seams_not_creases() -> None:
    """A 24-vertex box without NORMAL: every face stays flat (no smoothing across its
    90 deg edges, which drew discs on the faces); a sphere whose every corner is its own
    vertex stays smooth across those seams."""
    m = load_user_mesh(textured_box(normals=False), "glb")
    tri = m.vertices[m.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    for k in range(3):
        np.testing.assert_allclose(m.normals[m.faces[:, k]], fn, atol=1e-6)
    s = trimesh.creation.uv_sphere(radius=1.0, count=[24, 24])
    v = np.asarray(s.vertices)[np.asarray(s.faces).reshape(-1)]
    f = np.arange(len(v)).reshape(-1, 3)
    n = welded_normals(v, f)
    assert np.min(np.einsum("ij,ij->i", n, v / np.linalg.norm(v, axis=1, keepdims=True))) > 0.99
