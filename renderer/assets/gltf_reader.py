"""glTF 2.0 / GLB scenes posed and flattened: meshes, materials, skins, morph targets.

trimesh reads glTF geometry but neither skins nor morph targets nor animations, so this
module reads the document itself (``pygltflib`` for the JSON model, accessors decoded
here with numpy) and returns every primitive of the default scene in the glTF scene
frame (+Y up, metres, front +Z by convention), posed:

- **node transforms**: ``matrix`` or translation / rotation / scale, composed down the
  hierarchy;
- **animation** (optional ``animation_time_s``): the chosen animation's channels
  (translation, rotation, scale, morph weights) sampled at that time, looping over the
  animation's duration; STEP, LINEAR (quaternions: normalised slerp) and CUBICSPLINE
  interpolation. Without a time, nodes stay at their rest values (the file's TRS);
- **morph targets**: POSITION / NORMAL / TANGENT deltas weighted by the node's (or the
  mesh's, or the animated) weights;
- **skins**: linear blend skinning, ``sum_k w_k (G(joint_k) @ inverseBindMatrix_k)``,
  JOINTS_n / WEIGHTS_n sets; the skinned node's own transform is ignored (glTF spec).

Materials: baseColorFactor / baseColorTexture (sRGB), normalTexture (+ scale),
metallic / roughness factors and texture, alphaMode MASK cutoff. Images are decoded with
Pillow from buffer views or ``data:`` URIs, capped at :data:`MAX_TEXTURE_PIXELS`;
external URIs are resolved only through ``resolve`` (an archive's extracted folder),
never from the filesystem at large.

Everything malformed raises :class:`GltfError` (a ``ValueError``) saying where.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pygltflib
from numpy.typing import NDArray
from PIL import Image
from scipy.spatial.transform import Rotation

from renderer.mesh import Material

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
MAX_TEXTURE_PIXELS = 4096 * 4096
MAX_NODES = 10_000

_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORM_DIV = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}


class GltfError(ValueError):
    """A glTF document that cannot be read; the message says where."""


@dataclass
class Primitive:
    """One triangle primitive posed in the glTF scene frame.

    positions, normals : (n, 3) float64 (normals None when the file has none);
    uv : (n, 2) float64 or None; tangents : (n, 4) float64 or None; colors : (n, 4)
    float64 linear RGBA (COLOR_0) or None; faces : (m, 3) int64; material : its surface.
    """

    positions: F64
    faces: NDArray[np.int64]
    material: Material
    normals: F64 | None = None
    uv: F64 | None = None
    tangents: F64 | None = None
    colors: F64 | None = None
    skin_sets: list[tuple[F64, F64]] = field(default_factory=list, repr=False)
    morphed: bool = False


@dataclass
class GltfScene:
    """The posed primitives and what was done to get them (for the asset's meta)."""

    primitives: list[Primitive]
    info: dict[str, Any] = field(default_factory=dict)


Resolver = Callable[[str], bytes]


def read_gltf(
    data: bytes,
    file_type: str,
    *,
    animation_time_s: float | None = None,
    animation: int | str | None = None,
    resolve: Resolver | None = None,
) -> GltfScene:
    """Read a GLB or glTF JSON document and pose its default scene.

    Parameters
    ----------
    data : the file's bytes; file_type : ``glb`` or ``gltf``.
    animation_time_s : sample the animation at this time (s, looped); None = rest pose.
    animation : which animation (index or name; default the first).
    resolve : bytes of an external ``uri`` (relative to the document), for glTF files
        uploaded in an archive; None = external URIs are an error.
    """
    try:
        if file_type == "glb":
            doc = pygltflib.GLTF2.load_from_bytes(data)
        else:
            doc = pygltflib.GLTF2.from_json(data.decode("utf-8"))
    except Exception as e:  # pygltflib raises many types on bad input
        raise GltfError(f"could not read the {file_type} document: {type(e).__name__}: {e}") from e
    reader = _Reader(doc, resolve)
    reader.node_weights = _node_weights(data, file_type)
    return reader.scene(animation_time_s, animation)


def _node_weights(data: bytes, file_type: str) -> dict[int, F64]:
    """Nodes' morph ``weights`` (pygltflib's Node drops them), from the raw JSON."""
    try:
        if file_type == "glb":
            (clen,) = struct.unpack_from("<I", data, 12)
            raw = json.loads(data[20 : 20 + clen].decode("utf-8"))
        else:
            raw = json.loads(data.decode("utf-8"))
        nodes = raw.get("nodes") or []
        return {i: np.asarray(n["weights"], np.float64) for i, n in enumerate(nodes)
                if isinstance(n, dict) and isinstance(n.get("weights"), list)}  # fmt: skip
    except (ValueError, TypeError, struct.error, AttributeError):
        return {}


class _Reader:
    def __init__(self, doc: pygltflib.GLTF2, resolve: Resolver | None) -> None:
        self.doc = doc
        self.resolve = resolve
        self._buffers: dict[int, bytes] = {}
        self._images: dict[int, NDArray[np.uint8]] = {}
        self._materials: dict[int, Material] = {}
        self.node_weights: dict[int, F64] = {}

    # ------------------------------------------------------------------ raw data
    def _uri_bytes(self, uri: str, what: str) -> bytes:
        if uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise GltfError(f"{what}: only base64 data: URIs are supported")
            try:
                return base64.b64decode(payload, validate=False)
            except ValueError as e:
                raise GltfError(f"{what}: bad base64 data: {e}") from e
        if self.resolve is None:
            raise GltfError(f"{what} references an external file {uri[:80]!r}")
        return self.resolve(uri)

    def buffer(self, i: int) -> bytes:
        if i not in self._buffers:
            bufs = self.doc.buffers or []
            if not 0 <= i < len(bufs):
                raise GltfError(f"buffer {i} does not exist")
            b = bufs[i]
            if b.uri is None:  # the GLB binary chunk
                blob = self.doc.binary_blob()
                if blob is None:
                    raise GltfError(f"buffer {i} has no uri and the file has no binary chunk")
                raw = bytes(blob)
            else:
                raw = self._uri_bytes(b.uri, f"buffers[{i}]")
            if len(raw) < (b.byteLength or 0):
                raise GltfError(f"buffer {i}: {len(raw)} bytes, byteLength says {b.byteLength}")
            self._buffers[i] = raw
        return self._buffers[i]

    def view_bytes(self, i: int) -> tuple[bytes, int, int, int | None]:
        """(buffer, start, end, byteStride) of buffer view ``i``, bounds-checked."""
        views = self.doc.bufferViews or []
        if not 0 <= i < len(views):
            raise GltfError(f"bufferView {i} does not exist")
        bv = views[i]
        buf = self.buffer(bv.buffer)
        start = bv.byteOffset or 0
        end = start + bv.byteLength
        if start < 0 or end > len(buf):
            raise GltfError(f"bufferView {i} lies outside its buffer")
        return buf, start, end, bv.byteStride

    def accessor(self, i: int) -> F64:
        """Accessor ``i`` as float64 (count, components), normalised and sparse applied."""
        accs = self.doc.accessors or []
        if not isinstance(i, int) or not 0 <= i < len(accs):
            raise GltfError(f"accessor {i} does not exist")
        a = accs[i]
        if a.componentType not in _DTYPES or a.type not in _NCOMP:
            raise GltfError(f"accessor {i}: unsupported type {a.componentType}/{a.type}")
        dt = np.dtype(_DTYPES[a.componentType])
        nc = _NCOMP[a.type]
        count = int(a.count)
        if a.bufferView is None:
            out = np.zeros((count, nc))
        else:
            out = self._strided(a.bufferView, a.byteOffset or 0, dt, nc, count, f"accessor {i}")
        if a.sparse is not None and a.sparse.count:
            sp = a.sparse
            k = int(sp.count)
            idt = np.dtype(_DTYPES.get(sp.indices.componentType, "<u4"))
            idx = self._strided(sp.indices.bufferView, sp.indices.byteOffset or 0, idt, 1, k,
                                f"accessor {i} sparse indices")[:, 0].astype(np.int64)  # fmt: skip
            val = self._strided(sp.values.bufferView, sp.values.byteOffset or 0, dt, nc, k,
                                f"accessor {i} sparse values")  # fmt: skip
            if len(idx) and (idx.min() < 0 or idx.max() >= count):
                raise GltfError(f"accessor {i}: sparse index out of range")
            out[idx] = val
        if a.normalized and a.componentType in _NORM_DIV:
            out = np.maximum(out / _NORM_DIV[a.componentType], -1.0)
        return out

    def _strided(self, view: int, offset: int, dt: np.dtype, nc: int, count: int,
                 what: str) -> F64:  # fmt: skip
        buf, start, end, stride = self.view_bytes(view)
        item = dt.itemsize * nc
        stride = stride or item
        first = start + offset
        if count and (first + stride * (count - 1) + item > end or first < start):
            raise GltfError(f"{what}: data runs past its bufferView")
        if count == 0:
            return np.zeros((0, nc))
        arr = np.ndarray((count, nc), dt, buffer=buf, offset=first, strides=(stride, dt.itemsize))
        return arr.astype(np.float64)

    def image(self, i: int) -> NDArray[np.uint8]:
        """Image ``i`` as (h, w, 4) uint8 (as stored: sRGB for colour, linear for data)."""
        if i not in self._images:
            imgs = self.doc.images or []
            if not 0 <= i < len(imgs):
                raise GltfError(f"image {i} does not exist")
            im = imgs[i]
            if im.bufferView is not None:
                buf, start, end, _ = self.view_bytes(im.bufferView)
                raw = buf[start:end]
            elif im.uri is not None:
                raw = self._uri_bytes(im.uri, f"images[{i}]")
            else:
                raise GltfError(f"image {i} has neither bufferView nor uri")
            self._images[i] = decode_image(raw, f"image {i}")
        return self._images[i]

    def texture(self, info: Any) -> NDArray[np.uint8] | None:
        if info is None:
            return None
        texs = self.doc.textures or []
        t = info.index
        if not isinstance(t, int) or not 0 <= t < len(texs) or texs[t].source is None:
            return None
        if getattr(info, "texCoord", 0):
            logger.warning("texture %d uses TEXCOORD_%d; TEXCOORD_0 is used", t, info.texCoord)
        return self.image(texs[t].source)

    def material(self, i: int | None) -> Material:
        if i is None:
            return Material(name="gltf-default")
        if i not in self._materials:
            mats = self.doc.materials or []
            if not 0 <= i < len(mats):
                raise GltfError(f"material {i} does not exist")
            m = mats[i]
            pbr = m.pbrMetallicRoughness or pygltflib.PbrMetallicRoughness()
            base = np.asarray(pbr.baseColorFactor or [1.0, 1.0, 1.0, 1.0], np.float64)
            tex = self.texture(pbr.baseColorTexture)
            ntex = self.texture(m.normalTexture)
            mr = self.texture(pbr.metallicRoughnessTexture)
            self._materials[i] = Material(
                name=m.name or f"material{i}",
                base_color=base,
                base_color_texture=tex,
                normal_texture=None if ntex is None else ntex[..., :3],
                normal_scale=float(getattr(m.normalTexture, "scale", 1.0) or 1.0),
                roughness=1.0 if pbr.roughnessFactor is None else float(pbr.roughnessFactor),
                metallic=1.0 if pbr.metallicFactor is None else float(pbr.metallicFactor),
                metallic_roughness_texture=None if mr is None else mr[..., :3],
                alpha_cutoff=float(m.alphaCutoff if m.alphaCutoff is not None else 0.5)
                if m.alphaMode == "MASK"
                else None,
            )
        return self._materials[i]

    # ------------------------------------------------------------------ scene graph
    def scene(self, t: float | None, animation: int | str | None) -> GltfScene:
        doc = self.doc
        nodes = doc.nodes or []
        if len(nodes) > MAX_NODES:
            raise GltfError(f"{len(nodes)} nodes, more than {MAX_NODES}")
        trs = [_rest_trs(n) for n in nodes]
        weights: dict[int, F64] = {}
        info: dict[str, Any] = {"animation_time_s": t}
        if t is not None and doc.animations:
            k = self._animation_index(animation)
            info["animation"] = doc.animations[k].name or k
            self._animate(k, float(t), trs, weights, info)
        elif t is not None:
            info["animation"] = None
            logger.warning("animation_time_s given but the file has no animation: rest pose")
        local = [_compose(*x) if x is not None else np.asarray(_matrix(n)) for x, n in
                 zip(trs, nodes, strict=True)]  # fmt: skip
        roots = self._roots()
        G: dict[int, F64] = {}
        stack = [(r, np.eye(4)) for r in roots]
        seen: set[int] = set()
        while stack:
            i, parent = stack.pop()
            if i in seen or not 0 <= i < len(nodes):
                raise GltfError(f"node {i} is repeated in the hierarchy or does not exist")
            seen.add(i)
            G[i] = parent @ local[i]
            stack.extend((c, G[i]) for c in nodes[i].children or [])
        prims: list[Primitive] = []
        skinned = morphed = 0
        for i in sorted(G):
            n = nodes[i]
            if n.mesh is None:
                continue
            w = weights.get(i)
            if w is None:
                w = self.node_weights.get(i)
            for p in self._mesh_primitives(n.mesh, w):
                if n.skin is not None:
                    self._skin(p, n.skin, G)
                    skinned += 1
                else:
                    _transform(p, G[i])
                morphed += int(p.morphed)
                prims.append(p)
        info.update({"skinned_primitives": skinned, "morphed_primitives": morphed})
        return GltfScene(prims, info)

    def _roots(self) -> list[int]:
        doc = self.doc
        scenes = doc.scenes or []
        if scenes:
            k = doc.scene if isinstance(doc.scene, int) and 0 <= doc.scene < len(scenes) else 0
            return list(scenes[k].nodes or [])
        children = {c for n in doc.nodes or [] for c in n.children or []}
        return [i for i in range(len(doc.nodes or [])) if i not in children]

    def _animation_index(self, animation: int | str | None) -> int:
        anims = self.doc.animations or []
        if animation is None:
            return 0
        if isinstance(animation, int):
            if not 0 <= animation < len(anims):
                raise GltfError(f"animation {animation} does not exist ({len(anims)} in file)")
            return animation
        names = [a.name for a in anims]
        if animation not in names:
            raise GltfError(f"no animation named {animation!r}; the file has {names}")
        return names.index(animation)

    def _animate(self, k: int, t: float, trs: list, weights: dict[int, F64], info: dict) -> None:
        anim = self.doc.animations[k]
        samplers = anim.samplers or []
        inputs = [self.accessor(s.input)[:, 0] for s in samplers]
        end = max((float(x[-1]) for x in inputs if len(x)), default=0.0)
        start = min((float(x[0]) for x in inputs if len(x)), default=0.0)
        dur = end - start
        ts = start + ((t - start) % dur if dur > 0 else 0.0)
        info.update({"animation_duration_s": dur, "animation_sampled_at_s": ts})
        for ch in anim.channels or []:
            node, path = ch.target.node, ch.target.path
            if node is None or not 0 <= node < len(trs) or not 0 <= ch.sampler < len(samplers):
                continue
            s = samplers[ch.sampler]
            x = inputs[ch.sampler]
            y = self.accessor(s.output)
            if path == "weights":
                y = y.reshape(len(x) * (3 if s.interpolation == "CUBICSPLINE" else 1), -1)
            v = _sample(x, y, ts, s.interpolation or "LINEAR", path == "rotation")
            if path == "weights":
                weights[node] = v
            elif trs[node] is not None:
                T, R, S = trs[node]
                trs[node] = (v if path == "translation" else T, v if path == "rotation" else R,
                             v if path == "scale" else S)  # fmt: skip

    # ------------------------------------------------------------------ geometry
    def _mesh_primitives(self, mi: int, node_weights: F64 | None) -> list[Primitive]:
        meshes = self.doc.meshes or []
        if not 0 <= mi < len(meshes):
            raise GltfError(f"mesh {mi} does not exist")
        mesh = meshes[mi]
        w = node_weights
        if w is None and mesh.weights:
            w = np.asarray(mesh.weights, np.float64)
        out = []
        for pi, p in enumerate(mesh.primitives or []):
            mode = 4 if p.mode is None else p.mode
            if mode not in (4, 5, 6):
                logger.info("mesh %d primitive %d: mode %d (not triangles) skipped", mi, pi, mode)
                continue
            att = p.attributes
            if att.POSITION is None:
                raise GltfError(f"mesh {mi} primitive {pi} has no POSITION")
            pos = self.accessor(att.POSITION)[:, :3]
            n = len(pos)
            idx = (self.accessor(p.indices)[:, 0].astype(np.int64) if p.indices is not None
                   else np.arange(n, dtype=np.int64))  # fmt: skip
            faces = _triangles(idx, mode)
            if len(faces) and (faces.min() < 0 or faces.max() >= n):
                raise GltfError(f"mesh {mi} primitive {pi}: index out of range")
            prim = Primitive(pos, faces, self.material(p.material))
            prim.normals = self.accessor(att.NORMAL)[:, :3] if att.NORMAL is not None else None
            prim.uv = self.accessor(att.TEXCOORD_0)[:, :2] if att.TEXCOORD_0 is not None else None
            prim.tangents = self.accessor(att.TANGENT)[:, :4] if att.TANGENT is not None else None
            if att.COLOR_0 is not None:
                c = self.accessor(att.COLOR_0)
                prim.colors = np.concatenate([c[:, :3], c[:, 3:4] if c.shape[1] > 3 else
                                              np.ones((n, 1))], axis=1)  # fmt: skip
            for k, arr in (("uv", prim.uv), ("normals", prim.normals), ("tangents", prim.tangents),
                           ("colors", prim.colors)):  # fmt: skip
                if arr is not None and len(arr) != n:
                    raise GltfError(f"mesh {mi} primitive {pi}: {k} count differs from POSITION")
            if p.targets and w is not None and np.any(w != 0):
                self._morph(prim, p.targets, w, f"mesh {mi} primitive {pi}")
            skin_sets = []
            for s in range(4):
                j, wt = getattr(att, f"JOINTS_{s}", None), getattr(att, f"WEIGHTS_{s}", None)
                if j is None or wt is None:
                    break
                skin_sets.append((self.accessor(j), self.accessor(wt)))
            prim.skin_sets = skin_sets
            out.append(prim)
        return out

    def _morph(self, prim: Primitive, targets: list, w: F64, where: str) -> None:
        n = len(prim.positions)
        for k, tgt in enumerate(targets[: len(w)]):
            wk = float(w[k])
            if wk == 0.0:
                continue
            get = tgt.get if isinstance(tgt, dict) else (lambda a, t=tgt: getattr(t, a, None))
            for attr, arr in (("POSITION", prim.positions), ("NORMAL", prim.normals),
                              ("TANGENT", prim.tangents)):  # fmt: skip
                ai = get(attr)
                if ai is None or arr is None:
                    continue
                d = self.accessor(ai)
                if len(d) != n:
                    raise GltfError(f"{where}: morph target {k} {attr} count differs")
                arr[:, :3] += wk * d[:, :3]
        prim.morphed = True

    def _skin(self, prim: Primitive, si: int, G: dict[int, F64]) -> None:
        skins = self.doc.skins or []
        if not 0 <= si < len(skins):
            raise GltfError(f"skin {si} does not exist")
        skin = skins[si]
        joints = list(skin.joints or [])
        if any(j not in G for j in joints):
            raise GltfError(f"skin {si}: a joint is not in the scene")
        nj = len(joints)
        if skin.inverseBindMatrices is not None:
            ibm = self.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        else:
            ibm = np.tile(np.eye(4), (nj, 1, 1))
        if len(ibm) < nj:
            raise GltfError(f"skin {si}: fewer inverseBindMatrices than joints")
        J = np.stack([G[j] for j in joints]) @ ibm[:nj]  # (nj, 4, 4)
        sets = prim.skin_sets
        if not sets:
            logger.warning("skin %d on a primitive without JOINTS_0/WEIGHTS_0: not skinned", si)
            return
        n = len(prim.positions)
        M = np.zeros((n, 4, 4))
        wsum = np.zeros(n)
        for jj, ww in sets:
            ji = jj.astype(np.int64)
            if ji.min() < 0 or ji.max() >= nj:
                raise GltfError(f"skin {si}: joint index out of range")
            for c in range(ji.shape[1]):
                M += ww[:, c, None, None] * J[ji[:, c]]
                wsum += ww[:, c]
        ok = wsum > 1e-8
        M[ok] /= wsum[ok, None, None]
        M[~ok] = np.eye(4)
        prim.positions = np.einsum("nij,nj->ni", M[:, :3, :3], prim.positions) + M[:, :3, 3]
        if prim.normals is not None:
            prim.normals = _unit(np.einsum("nij,nj->ni", M[:, :3, :3], prim.normals))
        if prim.tangents is not None:
            prim.tangents[:, :3] = _unit(np.einsum("nij,nj->ni", M[:, :3, :3],
                                                   prim.tangents[:, :3]))  # fmt: skip


# ---------------------------------------------------------------------------- helpers
def decode_image(raw: bytes, what: str) -> NDArray[np.uint8]:
    """PNG / JPEG / ... bytes -> (h, w, 4) uint8 RGBA; GltfError over the pixel cap."""
    try:
        with Image.open(io.BytesIO(raw)) as im:
            w, h = im.size
            if w * h > MAX_TEXTURE_PIXELS:
                raise GltfError(f"{what}: {w}x{h} pixels, more than {MAX_TEXTURE_PIXELS}")
            return np.asarray(im.convert("RGBA"), dtype=np.uint8).copy()
    except GltfError:
        raise
    except Exception as e:  # PIL raises many types on bad input
        raise GltfError(f"{what}: not a readable image: {type(e).__name__}: {e}") from e


def _unit(v: F64) -> F64:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def _rest_trs(n: Any) -> tuple[F64, F64, F64] | None:
    """(translation, rotation xyzw, scale) of a TRS node; None for a matrix node."""
    if n.matrix is not None and n.translation is None and n.rotation is None and n.scale is None:
        m = np.asarray(n.matrix, np.float64)
        if not np.allclose(m, np.eye(4).ravel()):
            return None
    return (
        np.asarray(n.translation or [0.0, 0.0, 0.0], np.float64),
        np.asarray(n.rotation or [0.0, 0.0, 0.0, 1.0], np.float64),
        np.asarray(n.scale or [1.0, 1.0, 1.0], np.float64),
    )


def _matrix(n: Any) -> F64:
    m = np.asarray(n.matrix, np.float64)
    if m.shape != (16,) or not np.all(np.isfinite(m)):
        raise GltfError(f"node {n.name!r}: matrix must be 16 finite numbers")
    return m.reshape(4, 4).T  # column-major


def _compose(T: F64, R: F64, S: F64) -> F64:
    q = np.asarray(R, np.float64)
    nq = np.linalg.norm(q)
    if not np.isfinite(nq) or nq < 1e-12:
        q, nq = np.array([0.0, 0.0, 0.0, 1.0]), 1.0
    M = np.eye(4)
    M[:3, :3] = Rotation.from_quat(q / nq).as_matrix() * np.asarray(S, np.float64)[None, :]
    M[:3, 3] = T
    return M


def _transform(p: Primitive, M: F64) -> None:
    p.positions = p.positions @ M[:3, :3].T + M[:3, 3]
    N = np.linalg.inv(M[:3, :3]).T
    if p.normals is not None:
        p.normals = _unit(p.normals @ N.T)
    if p.tangents is not None:
        p.tangents[:, :3] = _unit(p.tangents[:, :3] @ M[:3, :3].T)
    if np.linalg.det(M[:3, :3]) < 0:  # a mirroring node flips the winding
        p.faces = p.faces[:, ::-1].copy()


def _triangles(idx: NDArray[np.int64], mode: int) -> NDArray[np.int64]:
    if mode == 4:
        return idx[: len(idx) // 3 * 3].reshape(-1, 3)
    if len(idx) < 3:
        return np.zeros((0, 3), np.int64)
    k = np.arange(len(idx) - 2)
    if mode == 5:  # strip: alternate winding
        a, b = np.where(k % 2 == 0, idx[k], idx[k + 1]), np.where(k % 2 == 0, idx[k + 1], idx[k])
        return np.stack([a, b, idx[k + 2]], axis=1)
    return np.stack([np.full(len(k), idx[0]), idx[k + 1], idx[k + 2]], axis=1)  # fan


def _sample(x: F64, y: F64, t: float, interp: str, quat: bool) -> F64:
    """Sampler output at time ``t`` (clamped to the keys)."""
    n = len(x)
    if n == 0:
        raise GltfError("animation sampler without keyframes")
    cubic = interp == "CUBICSPLINE"
    vals = y.reshape(n, 3, -1)[:, 1] if cubic else y.reshape(n, -1)
    if n == 1 or t <= x[0]:
        return vals[0].copy()
    if t >= x[-1]:
        return vals[-1].copy()
    k = int(np.searchsorted(x, t, side="right") - 1)
    dt = float(x[k + 1] - x[k])
    u = (t - x[k]) / dt if dt > 0 else 0.0
    if interp == "STEP":
        return vals[k].copy()
    if cubic:
        yy = y.reshape(n, 3, -1)
        p0, m0 = yy[k, 1], dt * yy[k, 2]
        p1, m1 = yy[k + 1, 1], dt * yy[k + 1, 0]
        u2, u3 = u * u, u * u * u
        v = ((2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * m0 + (-2 * u3 + 3 * u2) * p1
             + (u3 - u2) * m1)  # fmt: skip
        return _unit(v) if quat else v
    a, b = vals[k], vals[k + 1]
    if quat:
        if a @ b < 0:
            b = -b
        om = np.arccos(np.clip(abs(float(a @ b)) / max(np.linalg.norm(a) * np.linalg.norm(b),
                                                       1e-12), -1.0, 1.0))  # fmt: skip
        if om < 1e-6:
            return _unit((1 - u) * a + u * b)
        return _unit((np.sin((1 - u) * om) * a + np.sin(u * om) * b) / np.sin(om))
    return (1 - u) * a + u * b
