"""glTF reading with known answers: skinned joints move exactly their vertices, morph
targets add their weighted deltas, animations are sampled (and looped) in time, and the
glTF frame (+Y up) stands up in the object frame."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from renderer.assets.gltf_reader import GltfError, read_gltf
from renderer.assets.user_mesh import MeshError, load_user_mesh
from tests.renderer.gltf_build import GlbBuilder, checkerboard


def rz(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_quat()  # xyzw


def bar_positions() -> np.ndarray:
    """A 0.2 x 2.0 x 0.2 bar along +Y (glTF up): 4 vertices per level y = 0, 0.5, ... 2."""
    ring = np.array([[0.1, 0.1], [-0.1, 0.1], [-0.1, -0.1], [0.1, -0.1]])
    return np.array([[x, y, z] for y in np.arange(0.0, 2.01, 0.5) for x, z in ring])


def bar_faces(levels: int = 5) -> np.ndarray:
    f = []
    for k in range(levels - 1):
        for i in range(4):
            a, b = 4 * k + i, 4 * k + (i + 1) % 4
            f += [[a, b, b + 4], [a, b + 4, a + 4]]
    return np.array(f)


def skinned_bar(rest_deg: float = 90.0, animate: bool = True) -> bytes:
    """Two joints: root at the origin (weights for y < 1) and an elbow at y = 1 rotated
    ``rest_deg`` about Z in the file (weights for y > 1; half and half at y = 1)."""
    p = bar_positions()
    y = p[:, 1]
    w1 = np.where(y > 1.0 + 1e-9, 1.0, np.where(np.isclose(y, 1.0), 0.5, 0.0))
    joints = np.zeros((len(p), 4), int)
    joints[:, 1] = 1
    weights = np.stack([1 - w1, w1, 0 * w1, 0 * w1], 1)
    g = GlbBuilder()
    m = g.mesh(p, bar_faces(), joints=joints, weights=weights)
    elbow = g.node(root=False, translation=[0.0, 1.0, 0.0], rotation=list(rz(rest_deg)))
    root = g.node(children=[elbow])
    ibm = np.stack([np.eye(4), np.linalg.inv(np.array([[1, 0, 0, 0], [0, 1, 0, 1], [0, 0, 1, 0],
                                                        [0, 0, 0, 1.0]]))])  # fmt: skip
    g.doc["skins"] = [{"joints": [root, elbow],
                       "inverseBindMatrices": g.accessor(ibm.transpose(0, 2, 1).reshape(2, 16),
                                                         kind="MAT4")}]  # fmt: skip
    g.node(mesh=m, skin=0, translation=[50.0, 0.0, 0.0])  # ignored for skinned meshes
    if animate:
        g.animation(elbow, "rotation", [0.0, 1.0], [rz(0.0), rz(90.0)])
    return g.glb()


def expected_bar(angle_deg: float) -> np.ndarray:
    p = bar_positions()
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    q = (p - [0, 1, 0]) @ R.T + [0, 1, 0]
    out = p.copy()
    top = p[:, 1] > 1.0 + 1e-9
    out[top] = q[top]
    mid = np.isclose(p[:, 1], 1.0)
    out[mid] = 0.5 * (p[mid] + q[mid])  # linear blend of the two joints
    return out


def positions(data: bytes, **kw) -> np.ndarray:
    (prim,) = read_gltf(data, "glb", **kw).primitives
    return prim.positions


def test_skinned_joint_moves_exactly_its_vertices() -> None:
    data = skinned_bar(rest_deg=90.0)
    np.testing.assert_allclose(positions(data), expected_bar(90.0), atol=1e-6)  # rest = file
    np.testing.assert_allclose(positions(data, animation_time_s=0.5), expected_bar(45.0),
                               atol=1e-6)  # slerp half way  # fmt: skip
    np.testing.assert_allclose(positions(data, animation_time_s=1.25), expected_bar(22.5),
                               atol=1e-6)  # looped over the 1 s animation  # fmt: skip
    lower = bar_positions()[:, 1] < 1.0 - 1e-9
    np.testing.assert_allclose(positions(data, animation_time_s=0.7)[lower],
                               bar_positions()[lower], atol=1e-7)  # fmt: skip


def test_morph_target_weights_from_mesh_node_and_animation() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    delta = np.zeros((4, 3))
    delta[2:, 1] = 0.5
    for node_weights, t, want in ((None, None, 0.2), ([0.8], None, 0.4), (None, 0.5, 0.125)):
        g = GlbBuilder()
        m = g.mesh(v, [[0, 1, 2], [0, 2, 3]], targets=[delta], default_weights=[0.4])
        node = g.node(mesh=m, weights=node_weights)
        if t is not None:
            g.animation(node, "weights", [0.0, 2.0], [0.0, 1.0])
        (prim,) = read_gltf(g.glb(), "glb", animation_time_s=t).primitives
        np.testing.assert_allclose(prim.positions, v + want / 0.5 * delta, atol=1e-6)
        assert prim.morphed


def test_load_user_mesh_poses_and_stands_gltf_up() -> None:
    data = skinned_bar(rest_deg=0.0)
    m = load_user_mesh(data, "glb")  # glTF +Y up -> object +z up
    np.testing.assert_allclose(m.size, [0.2, 0.2, 2.0], atol=1e-6)
    bent = load_user_mesh(data, "glb", animation_time_s=0.5)  # elbow at 45 deg
    np.testing.assert_allclose(bent.size[2], 1.0 + np.sqrt(0.5) + 0.1 * np.sqrt(0.5), atol=1e-6)
    assert bent.meta["pose"]["animation_time_s"] == 0.5
    assert bent.meta["pose"]["skinned_primitives"] == 1
    side = load_user_mesh(data, "glb", up="z")  # overridden: lies on its side
    assert side.size[2] < 0.21


def test_texture_materials_and_refusals() -> None:
    g = GlbBuilder()
    tex = g.image(checkerboard(n=2, px=4))
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)
    m = g.mesh(v, [[0, 1, 2], [0, 2, 3]], uv=uv, material=g.material(tex, metallic=0.3,
                                                                   roughness=0.6))  # fmt: skip
    g.node(mesh=m)
    mesh = load_user_mesh(g.glb(), "glb")
    mat = mesh.materials[0]
    assert mat.base_color_texture.shape == (8, 8, 4) and mesh.uv is not None
    assert (mat.metallic, mat.roughness) == (pytest.approx(0.3), pytest.approx(0.6))
    assert mesh.meta["color_source"] == "texture" and mesh.textured
    # bad documents: errors say where
    g.doc["accessors"][0]["count"] = 10**5
    with pytest.raises(GltfError, match="accessor 0: data runs past its bufferView"):
        read_gltf(g.glb(), "glb")
    g.doc["images"][0] = {"uri": "../../etc/passwd"}
    with pytest.raises(MeshError, match=r"images\[0\] references an external"):
        load_user_mesh(g.glb(), "glb")
    with pytest.raises(MeshError, match="animation"):
        load_user_mesh(skinned_bar(), "glb", animation_time_s=0.1, animation="walk")
