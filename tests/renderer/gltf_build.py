"""Small GLB files built by hand for the tests: geometry, textures, skins, morph targets.

The JSON and the binary chunk are written here directly (glTF 2.0 spec, section 4.4), so
the reader under test is checked against an independent writer.
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from PIL import Image

FLOAT, UINT, USHORT, UBYTE = 5126, 5125, 5123, 5121


@dataclass
class GlbBuilder:
    doc: dict[str, Any] = field(
        default_factory=lambda: {
            "asset": {"version": "2.0"},
            "buffers": [],
            "bufferViews": [],
            "accessors": [],
            "scenes": [{"nodes": []}],
            "scene": 0,
            "nodes": [],
            "meshes": [],
        }
    )
    blob: bytearray = field(default_factory=bytearray)

    def _view(self, raw: bytes) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.doc["bufferViews"].append(
            {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(raw)}
        )
        self.blob.extend(raw)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, arr: np.ndarray, ctype: int = FLOAT, kind: str | None = None,
                 normalized: bool = False) -> int:  # fmt: skip
        dt = {FLOAT: "<f4", UINT: "<u4", USHORT: "<u2", UBYTE: "<u1"}[ctype]
        a = np.ascontiguousarray(np.asarray(arr).astype(dt))
        nc = 1 if a.ndim == 1 else int(np.prod(a.shape[1:]))
        kind = kind or {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}[nc]
        acc: dict[str, Any] = {"bufferView": self._view(a.tobytes()), "componentType": ctype,
                               "count": int(a.shape[0]), "type": kind}  # fmt: skip
        if normalized:
            acc["normalized"] = True
        if ctype == FLOAT and kind == "VEC3":
            acc["min"] = a.reshape(-1, 3).min(0).tolist()
            acc["max"] = a.reshape(-1, 3).max(0).tolist()
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def image(self, rgb: np.ndarray) -> int:
        buf = io.BytesIO()
        Image.fromarray(np.asarray(rgb, np.uint8)).save(buf, format="PNG")
        self.doc.setdefault("images", []).append(
            {"bufferView": self._view(buf.getvalue()), "mimeType": "image/png"}
        )
        self.doc.setdefault("textures", []).append({"source": len(self.doc["images"]) - 1})
        return len(self.doc["textures"]) - 1

    def material(self, base_texture: int | None = None, base_color=(1, 1, 1, 1),
                 metallic: float = 0.0, roughness: float = 1.0,
                 normal_texture: int | None = None) -> int:  # fmt: skip
        pbr: dict[str, Any] = {"baseColorFactor": list(base_color), "metallicFactor": metallic,
                               "roughnessFactor": roughness}  # fmt: skip
        if base_texture is not None:
            pbr["baseColorTexture"] = {"index": base_texture}
        m: dict[str, Any] = {"pbrMetallicRoughness": pbr}
        if normal_texture is not None:
            m["normalTexture"] = {"index": normal_texture}
        self.doc.setdefault("materials", []).append(m)
        return len(self.doc["materials"]) - 1

    def mesh(self, positions, faces, *, uv=None, normals=None, material=None, joints=None,
             weights=None, targets=None, default_weights=None) -> int:  # fmt: skip
        att = {"POSITION": self.accessor(np.asarray(positions, np.float32))}
        if uv is not None:
            att["TEXCOORD_0"] = self.accessor(np.asarray(uv, np.float32))
        if normals is not None:
            att["NORMAL"] = self.accessor(np.asarray(normals, np.float32))
        if joints is not None:
            att["JOINTS_0"] = self.accessor(np.asarray(joints), USHORT, "VEC4")
            att["WEIGHTS_0"] = self.accessor(np.asarray(weights, np.float32))
        prim: dict[str, Any] = {
            "attributes": att,
            "mode": 4,
            "indices": self.accessor(np.asarray(faces).reshape(-1), UINT),
        }
        if material is not None:
            prim["material"] = material
        if targets:
            prim["targets"] = [{"POSITION": self.accessor(np.asarray(t, np.float32))}
                               for t in targets]  # fmt: skip
        mesh: dict[str, Any] = {"primitives": [prim]}
        if default_weights is not None:
            mesh["weights"] = list(default_weights)
        self.doc["meshes"].append(mesh)
        return len(self.doc["meshes"]) - 1

    def node(self, root: bool = True, **kw: Any) -> int:
        self.doc["nodes"].append({k: v for k, v in kw.items() if v is not None})
        i = len(self.doc["nodes"]) - 1
        if root:
            self.doc["scenes"][0]["nodes"].append(i)
        return i

    def animation(self, node: int, path: str, times, values, interp: str = "LINEAR") -> None:
        inp = self.accessor(np.asarray(times, np.float32))
        out = self.accessor(
            np.asarray(values, np.float32).reshape(len(times), -1)
            if path != "weights"
            else np.asarray(values, np.float32).reshape(-1)
        )
        anims = self.doc.setdefault("animations", [{"channels": [], "samplers": []}])
        a = anims[0]
        a["samplers"].append({"input": inp, "output": out, "interpolation": interp})
        a["channels"].append({"sampler": len(a["samplers"]) - 1,
                              "target": {"node": node, "path": path}})  # fmt: skip

    def glb(self) -> bytes:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.doc["buffers"] = [{"byteLength": len(self.blob)}]
        js = json.dumps(self.doc).encode()
        js += b" " * (-len(js) % 4)
        total = 12 + 8 + len(js) + 8 + len(self.blob)
        head = struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON")
        return head + js + struct.pack("<I4s", len(self.blob), b"BIN\0") + bytes(self.blob)


def checkerboard(n: int = 8, px: int = 32, lo: int = 20, hi: int = 235) -> np.ndarray:
    """(n px, n px, 3) uint8 sRGB checkerboard, top-left check dark."""
    ij = np.indices((n * px, n * px)) // px
    v = np.where((ij[0] + ij[1]) % 2 == 0, lo, hi).astype(np.uint8)
    return np.repeat(v[..., None], 3, axis=2)


def textured_box(
    size_xyz=(0.6, 1.8, 0.6), texture: np.ndarray | None = None, normals: bool = True
) -> bytes:
    """A GLB box (glTF frame: +Y up), 24 vertices with per-face UVs over the full
    texture, metallic 0; its size is given in the glTF frame."""
    hx, hy, hz = np.asarray(size_xyz) / 2
    pos, uv, nrm, faces = [], [], [], []
    for axis in range(3):
        for sgn in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sgn
            a, b = [(1, 2), (2, 0), (0, 1)][axis]
            ua, ub = np.zeros(3), np.zeros(3)
            ua[a], ub[b] = 1.0, 1.0
            if sgn < 0:
                ua = -ua
            c = n * np.array([hx, hy, hz])
            h = np.array([hx, hy, hz])
            k = len(pos)
            for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                pos.append(c + s * ua * h + t * ub * h)
                uv.append([(s + 1) / 2, (1 - t) / 2])
                nrm.append(n)
            faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    g = GlbBuilder()
    tex = g.image(checkerboard() if texture is None else texture)
    m = g.mesh(np.array(pos), np.array(faces), uv=np.array(uv),
               normals=np.array(nrm) if normals else None, material=g.material(tex))  # fmt: skip
    g.node(mesh=m)
    return g.glb()
