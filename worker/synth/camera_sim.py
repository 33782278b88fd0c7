"""Camera simulation of the synthetic railway scene (moderngl, EGL).

Per frame and camera: the undistorted pinhole of :meth:`CameraModel.render_setup` is
rendered with 4x MSAA (procedural per-material textures, sun + sky light, haze, sky with
clouds), remapped with OpenCV into the real distorted image, then vignetting and sensor
noise are applied (deterministic per frame).

Precision: vertices are uploaded once relative to ``origin`` (a point of the scene near
the ego track), the view matrix ``T_opt_origin = inv(T_world_base @ T_base_opt) @
T_world_origin`` is composed in float64 and only the product is cast to float32.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass

import cv2
import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry.camera import CameraModel, RenderSetup, gl_projection
from geometry.transforms import invert_T
from renderer.gl_context import create_context
from worker.synth.scene import Scene
from worker.synth.scene_mesh import MATERIALS

F64 = NDArray[np.float64]
log = logging.getLogger(__name__)

NEAR, FAR = 1.0, 15000.0
AUTO_SSAA_MAX_PIXELS = 3.0e6
CHUNK_SIZE = 48.0  # metres, ground cells for frustum culling
_MAT_TEX_WIDTH = 4096
_TEXTURE_CODES = {
    "plain": 0, "grass": 1, "ballast": 2, "concrete": 3, "metal": 4, "brick": 5,
    "foliage": 6, "wood": 7, "asphalt": 8, "gravel": 9,
}  # fmt: skip
_MAX_MATERIALS = 32

_VERTEX = """
#version 330
uniform mat4 u_mvp;
uniform mat4 u_view;
in vec3 in_pos;
out vec3 v_pos;
out float v_z;
void main() {
    vec4 p = vec4(in_pos, 1.0);
    v_pos = in_pos;
    v_z = (u_view * p).z;
    gl_Position = u_mvp * p;
}
"""

_NOISE = """
float hash13(vec3 p) {
    p = fract(p * 0.1031);
    p += dot(p, p.zyx + 31.32);
    return fract((p.x + p.y) * p.z);
}
float hash12(vec2 p) {
    vec3 p3 = fract(vec3(p.xyx) * 0.1031);
    p3 += dot(p3, p3.yzx + 33.33);
    return fract((p3.x + p3.y) * p3.z);
}
vec2 hash22(vec2 p) {
    vec3 p3 = fract(vec3(p.xyx) * vec3(0.1031, 0.1030, 0.0973));
    p3 += dot(p3, p3.yzx + 33.33);
    return fract((p3.xx + p3.yz) * p3.zy);
}
float vnoise(vec3 x) {
    vec3 i = floor(x);
    vec3 f = fract(x);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(mix(hash13(i), hash13(i + vec3(1, 0, 0)), f.x),
                   mix(hash13(i + vec3(0, 1, 0)), hash13(i + vec3(1, 1, 0)), f.x), f.y),
               mix(mix(hash13(i + vec3(0, 0, 1)), hash13(i + vec3(1, 0, 1)), f.x),
                   mix(hash13(i + vec3(0, 1, 1)), hash13(i + vec3(1, 1, 1)), f.x), f.y), f.z);
}
float vnoise2(vec2 x) {
    vec2 i = floor(x);
    vec2 f = fract(x);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(hash12(i), hash12(i + vec2(1, 0)), f.x),
               mix(hash12(i + vec2(0, 1)), hash12(i + vec2(1, 1)), f.x), f.y);
}
// detail weight: 1 when a feature of frequency f (1/m) spans several pixels, 0 when aliased
float detail(float f, float footprint) { return clamp(1.6 - 2.0 * f * footprint, 0.0, 1.0); }
float fbm(vec3 p, float footprint) {
    float a = 0.5, s = 0.0, w = 0.0, f = 1.0;
    for (int i = 0; i < 4; ++i) {
        float d = detail(f, footprint);
        s += a * d * vnoise(p * f) + a * (1.0 - d) * 0.5;
        w += a; f *= 2.03; a *= 0.5;
    }
    return s / w;
}
// cellular pattern on a plane: (distance to nearest feature, id of that cell)
vec2 cells(vec2 p) {
    vec2 i = floor(p), f = fract(p);
    float best = 8.0, id = 0.0;
    for (int y = -1; y <= 1; ++y)
        for (int x = -1; x <= 1; ++x) {
            vec2 g = vec2(x, y);
            vec2 o = hash22(i + g);
            float d = length(g + o - f);
            if (d < best) { best = d; id = hash12(i + g + 17.0); }
        }
    return vec2(best, id);
}
"""

_FRAGMENT = (
    """
#version 330
uniform usampler2D u_mat_tex;
uniform vec3 u_albedo[32];
uniform int u_texture[32];
uniform vec3 u_sun;
uniform vec3 u_cam;
uniform vec3 u_haze;
uniform float u_fog_dist;
uniform int u_mode;
uniform int u_prim_base;
in vec3 v_pos;
in float v_z;
out vec4 f_out;
"""
    + _NOISE
    + """
vec3 textured(int tex, vec3 alb, vec3 p, vec3 n, float fp, out float spec) {
    spec = 0.0;
    if (tex == 1) {  // grass
        float big = vnoise(p * 0.03);
        float mid = fbm(p * 0.35, fp * 0.35);
        float fine = mix(0.5, vnoise(p * 6.0), detail(6.0, fp));
        vec3 dry = vec3(0.42, 0.38, 0.20);
        vec3 c = mix(alb, dry, smoothstep(0.45, 0.85, big) * 0.7);
        c = mix(c, alb * vec3(0.7, 0.95, 0.6), smoothstep(0.55, 0.8, mid) * 0.5);
        return c * (0.7 + 0.45 * mid) * (0.85 + 0.3 * fine);
    }
    if (tex == 2) {  // ballast: stones with dark gaps, some rust tint
        float d = detail(18.0, fp);
        vec2 c = cells(p.xy * 18.0 + p.z * 3.0);
        float stone = (0.65 + 0.6 * c.y) * mix(1.0, smoothstep(0.05, 0.6, c.x) * 0.5 + 0.55, 0.0);
        stone = (0.62 + 0.55 * c.y) * (1.1 - 0.55 * smoothstep(0.35, 0.9, c.x));
        float rust = smoothstep(0.5, 0.9, vnoise(p * 1.3));
        vec3 col = alb * mix(1.0, stone, d);
        return mix(col, col * vec3(1.05, 0.85, 0.7), rust * 0.5);
    }
    if (tex == 3) {  // concrete
        float m = fbm(p * 2.0, fp * 2.0);
        float f = mix(0.5, vnoise(p * 25.0), detail(25.0, fp));
        return alb * (0.8 + 0.3 * m + 0.12 * (f - 0.5));
    }
    if (tex == 4) {  // metal: polished rail head on top, rusty sides
        if (n.z > 0.93 && alb.r > 0.52) {
            spec = 0.8;
            return vec3(0.78, 0.78, 0.80);
        }
        float r = fbm(p * 4.0, fp * 4.0);
        if (alb.r > 0.52) return vec3(0.36, 0.22, 0.14) * (0.75 + 0.5 * r);
        spec = 0.15;
        return alb * (0.85 + 0.3 * r);
    }
    if (tex == 5) {  // brick walls with windows
        if (abs(n.z) > 0.5) return alb * 0.8;
        float u = abs(n.x) > abs(n.y) ? p.y : p.x;
        float v = p.z;
        vec2 w = fract(vec2(u / 3.2, v / 3.0));
        if (w.x > 0.3 && w.x < 0.7 && w.y > 0.35 && w.y < 0.8) {
            spec = 0.5;
            return vec3(0.06, 0.07, 0.09) + 0.05 * vnoise(p * 0.5);
        }
        float row = floor(v / 0.075);
        float uu = u / 0.25 + 0.5 * mod(row, 2.0);
        float mortar = max(step(fract(v / 0.075), 0.14), step(fract(uu), 0.06));
        float d = detail(1.0 / 0.075, fp);
        vec3 b = alb * (0.8 + 0.4 * hash12(vec2(row, floor(uu))));
        vec3 c = mix(b, vec3(0.55, 0.53, 0.5), mortar);
        return mix(alb * 0.93, c, d);
    }
    if (tex == 6) {  // foliage
        float tint = vnoise(p * 0.12);
        float m = fbm(p * 1.4, fp * 1.4);
        float f = mix(0.5, vnoise(p * 9.0), detail(9.0, fp));
        vec3 c = mix(alb, alb * vec3(1.35, 1.2, 0.7), tint);
        return c * (0.55 + 0.8 * m) * (0.75 + 0.5 * f);
    }
    if (tex == 7) {  // wood / bark
        float f = vnoise(vec3(p.xy * 30.0, p.z * 2.0));
        return alb * (0.7 + 0.5 * mix(0.5, f, detail(30.0, fp)));
    }
    if (tex == 8) {  // asphalt
        float m = fbm(p * 0.8, fp * 0.8);
        float f = mix(0.5, vnoise(p * 40.0), detail(40.0, fp));
        return alb * (0.85 + 0.25 * m + 0.2 * (f - 0.5));
    }
    if (tex == 9) {  // gravel
        float d = detail(30.0, fp);
        vec2 c = cells(p.xy * 30.0);
        return alb * mix(1.0, 0.7 + 0.5 * c.y, d) * (0.85 + 0.3 * vnoise(p * 0.7));
    }
    return alb;
}

void main() {
    int pid = gl_PrimitiveID + u_prim_base;
    uint mid = texelFetch(u_mat_tex, ivec2(pid % 4096, pid / 4096), 0).r;
    int m = int(mid);
    if (u_mode == 1) { f_out = vec4(v_z, 0.0, 0.0, 1.0); return; }
    if (u_mode == 2) { f_out = vec4(float(m), 0.0, 0.0, 1.0); return; }
    vec3 dx = dFdx(v_pos), dy = dFdy(v_pos);
    vec3 n = normalize(cross(dx, dy));
    vec3 to_cam = u_cam - v_pos;
    float dist = length(to_cam);
    if (dot(n, to_cam) < 0.0) n = -n;
    float fp = max(length(dx), length(dy));
    float spec_k;
    vec3 alb = textured(u_texture[m], u_albedo[m], v_pos, n, fp, spec_k);
    float sun = max(dot(n, u_sun), 0.0);
    vec3 sky_amb = mix(vec3(0.20, 0.19, 0.16), vec3(0.42, 0.47, 0.56), 0.5 + 0.5 * n.z);
    vec3 col = alb * (sky_amb + vec3(0.95, 0.89, 0.80) * sun) * 0.85;
    vec3 h = normalize(u_sun + to_cam / dist);
    col += spec_k * pow(max(dot(n, h), 0.0), 40.0) * vec3(1.0, 0.97, 0.9) * step(0.0, sun);
    float fog = 1.0 - exp(-dist / u_fog_dist);
    col = mix(col, u_haze, fog);
    f_out = vec4(pow(clamp(col, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
"""
)

_SKY_VERTEX = """
#version 330
in vec2 in_xy;
void main() { gl_Position = vec4(in_xy, 0.9999, 1.0); }
"""

_SKY_FRAGMENT = (
    """
#version 330
uniform mat3 u_R_world_opt;
uniform vec4 u_K;   // fx, fy, cx, cy of the pinhole render
uniform vec3 u_sun;
uniform vec3 u_haze;
uniform vec2 u_cloud_shift;
uniform float u_cloud_cover;
out vec4 f_out;
"""
    + _NOISE
    + """
void main() {
    vec2 uv = gl_FragCoord.xy - 0.5;   // image column, image row (rows are not flipped)
    vec3 r_opt = vec3((uv.x - u_K.z) / u_K.x, (uv.y - u_K.w) / u_K.y, 1.0);
    vec3 d = normalize(u_R_world_opt * r_opt);
    float e = d.z;
    vec3 zenith = vec3(0.22, 0.38, 0.75);
    vec3 col = mix(u_haze, zenith, pow(clamp(e, 0.0, 1.0), 0.45));
    if (e > 0.0) {
        vec2 q = d.xy / max(e, 0.02) * 1.5 + u_cloud_shift;
        float fp = 1.5 / max(e, 0.02) * 0.002;
        float c = fbm(vec3(q * 0.9, 0.0), fp * 0.9);
        float cover = smoothstep(1.0 - u_cloud_cover, 1.05 - 0.6 * u_cloud_cover, c);
        float shade = 0.75 + 0.35 * fbm(vec3(q * 2.1 + 7.0, 1.0), fp * 2.1);
        vec3 cloud = vec3(0.93, 0.93, 0.95) * shade;
        col = mix(col, cloud, cover * smoothstep(0.0, 0.12, e));
    }
    float sun = max(dot(d, u_sun), 0.0);
    col += vec3(1.0, 0.9, 0.7) * (0.25 * pow(sun, 60.0) + 2.0 * pow(sun, 2000.0));
    f_out = vec4(pow(clamp(col, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
"""
)


@dataclass
class _CameraState:
    cam: CameraModel
    setup: RenderSetup
    P: F64  # projection of the pinhole render (depth, labels)
    K_col: F64  # colour render: the pinhole supersampled by ``ss``
    P_col: F64
    size_col: tuple[int, int]
    fbo_ms: moderngl.Framebuffer
    fbo_rgb: moderngl.Framebuffer
    fbo_f32: moderngl.Framebuffer
    vignette: NDArray[np.float32]
    noise: NDArray[np.int8]


class CameraSimulator:
    """Renders a :class:`Scene` through calibrated cameras.

    Parameters
    ----------
    scene : the scene (its mesh is uploaded once).
    cameras : name -> CameraModel, at the resolution to render (e.g. ``cam.scaled(0.25)``).
    sun_dir : (3,) world direction towards the sun (normalised here).
    seed : seeds the sensor noise and the clouds.
    noise_sigma : sensor noise standard deviation in 8-bit counts.
    vignetting : relative light fall-off in the image corners.
    """

    def __init__(
        self,
        scene: Scene,
        cameras: dict[str, CameraModel],
        sun_dir: ArrayLike = (0.45, -0.55, 0.7),
        seed: int = 0,
        noise_sigma: float = 2.0,
        vignetting: float = 0.22,
        fog_distance: float = 2200.0,
        cloud_cover: float = 0.45,
        antialias: str = "auto",
    ) -> None:
        self.scene = scene
        self.cameras = dict(cameras)
        sun = np.asarray(sun_dir, dtype=np.float64)
        self.sun_dir = sun / np.linalg.norm(sun)
        self.seed = int(seed)
        self.noise_sigma = float(noise_sigma)
        self.vignetting = float(vignetting)
        self.ctx = create_context()
        self.samples, self.supersample = self._antialias_mode(antialias)
        self.haze = np.array([0.66, 0.72, 0.80])
        self.origin = self._choose_origin(scene)
        self.T_world_origin = np.eye(4)
        self.T_world_origin[:3, 3] = self.origin
        self._prog = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        self._sky = self.ctx.program(vertex_shader=_SKY_VERTEX, fragment_shader=_SKY_FRAGMENT)
        self._upload(scene)
        self._set_static_uniforms(fog_distance, cloud_cover)
        self._states: dict[str, _CameraState] = {}

    # ------------------------------------------------------------------ setup
    def _antialias_mode(self, antialias: str) -> tuple[int, float]:
        """(MSAA samples, supersampling factor) for ``msaa4``, ``ssaa<f>``, ``none``, ``auto``.

        ``auto``: 4x MSAA on a real GPU; on llvmpipe, whose MSAA is several times slower
        than rendering four times the pixels, 1.5x supersampling for images up to 3 MP and
        none above (a supersample factor of 0 means "decide per camera").
        """
        if antialias == "auto":
            renderer = str(self.ctx.info.get("GL_RENDERER", "")).lower()
            if "llvmpipe" in renderer or "softpipe" in renderer:
                return 0, 0.0
            antialias = "msaa4"
        if antialias == "none":
            return 0, 1.0
        if antialias.startswith("msaa"):
            return int(antialias[4:]), 1.0
        if antialias.startswith("ssaa"):
            return 0, float(antialias[4:])
        raise ValueError(f"antialias must be auto, none, msaa<n> or ssaa<f>, got {antialias!r}")

    @staticmethod
    def _choose_origin(scene: Scene) -> F64:
        """A point near the middle of the driven part of the ego track (float64 world)."""
        s_mid = 0.5 * (scene.drive_range[0] + scene.drive_range[1])
        return np.round(scene.ego.point(s_mid)[0], 0)

    def _upload(self, scene: Scene) -> None:
        ctx = self.ctx
        v64 = scene.mesh.vertices - self.origin
        faces, mats = self._make_chunks(v64, scene.mesh.faces, scene.mesh.material)
        v = v64.astype(np.float32)
        faces = faces.astype(np.uint32)
        mats = mats.astype(np.uint8)
        if len(MATERIALS) > _MAX_MATERIALS:
            raise ValueError("too many materials for the shader")
        rows = max(1, int(np.ceil(len(mats) / _MAT_TEX_WIDTH)))
        tex_data = np.zeros(rows * _MAT_TEX_WIDTH, np.uint8)
        tex_data[: len(mats)] = mats
        self._mat_tex = ctx.texture((_MAT_TEX_WIDTH, rows), 1, tex_data.tobytes(), dtype="u1")
        self._mat_tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._vbo = ctx.buffer(v.tobytes())
        self._ibo = ctx.buffer(faces.tobytes())
        self._vao = ctx.vertex_array(
            self._prog, [(self._vbo, "3f", "in_pos")], index_buffer=self._ibo, index_element_size=4
        )
        quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype=np.float32)
        self._quad = ctx.buffer(quad.tobytes())
        self._sky_vao = ctx.vertex_array(self._sky, [(self._quad, "2f", "in_xy")])
        log.info("uploaded %d vertices, %d triangles", len(v), len(faces))

    def _make_chunks(
        self, v: F64, faces: NDArray[np.int64], mats: NDArray[np.int64]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Sort faces into square ground cells for view-frustum culling.

        Stores per chunk (first face, face count) and its bounding box corners (m, 8, 3)
        (origin-relative); returns the reordered faces and materials.
        """
        tri = v[faces]  # (m, 3, 3)
        cell = np.floor(tri.mean(axis=1)[:, :2] / CHUNK_SIZE).astype(np.int64)
        cell -= cell.min(axis=0)
        key = cell[:, 0] * (cell[:, 1].max() + 1) + cell[:, 1]
        order = np.argsort(key, kind="stable")
        faces, mats, tri, key = faces[order], mats[order], tri[order], key[order]
        _, first, count = np.unique(key, return_index=True, return_counts=True)
        lo = np.minimum.reduceat(tri.min(axis=1), first)
        hi = np.maximum.reduceat(tri.max(axis=1), first)
        sel = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=bool)
        self._chunk_first = first
        self._chunk_count = count
        self._chunk_corners = np.where(sel[None], hi[:, None, :], lo[:, None, :])
        return faces, mats

    def _visible_runs(self, mvp: F64) -> list[tuple[int, int]]:
        """(first face, face count) runs of chunks that intersect the view frustum."""
        c = self._chunk_corners
        clip = c @ mvp[:3, :3].T + mvp[:3, 3]
        w = c @ mvp[3, :3] + mvp[3, 3]
        out = np.zeros(len(c), dtype=bool)
        for k in range(3):
            out |= np.all(clip[..., k] < -w, axis=1) | np.all(clip[..., k] > w, axis=1)
        runs: list[tuple[int, int]] = []
        for i in np.flatnonzero(~out):
            f, n = int(self._chunk_first[i]), int(self._chunk_count[i])
            if runs and runs[-1][0] + runs[-1][1] == f:
                runs[-1] = (runs[-1][0], runs[-1][1] + n)
            else:
                runs.append((f, n))
        return runs

    def _set_static_uniforms(self, fog_distance: float, cloud_cover: float) -> None:
        alb = np.zeros((_MAX_MATERIALS, 3), np.float32)
        tex = np.zeros(_MAX_MATERIALS, np.int32)
        for i, m in enumerate(MATERIALS):
            alb[i] = m.albedo
            tex[i] = _TEXTURE_CODES.get(m.texture, 0)
        self._prog["u_albedo"].write(alb.tobytes())
        self._prog["u_texture"].write(tex.tobytes())
        self._prog["u_sun"].value = tuple(self.sun_dir)
        self._prog["u_haze"].value = tuple(self.haze)
        self._prog["u_fog_dist"].value = float(fog_distance)
        self._prog["u_mat_tex"].value = 0
        self._sky["u_sun"].value = tuple(self.sun_dir)
        self._sky["u_haze"].value = tuple(self.haze)
        rng = np.random.default_rng([self.seed, 7])
        self._sky["u_cloud_shift"].value = tuple(rng.uniform(-500, 500, 2))
        self._sky["u_cloud_cover"].value = float(cloud_cover)

    def _state(self, name: str) -> _CameraState:
        st = self._states.get(name)
        if st is not None:
            return st
        cam = self.cameras[name]
        setup = cam.render_setup(margin_px=2.0)
        size = (setup.width, setup.height)
        ss = self.supersample or (1.5 if cam.width * cam.height <= AUTO_SSAA_MAX_PIXELS else 1.0)
        size_col = (int(np.ceil(setup.width * ss)), int(np.ceil(setup.height * ss)))
        K_col = setup.K.copy()
        K_col[:2, :2] *= ss
        K_col[:2, 2] = ss * (setup.K[:2, 2] + 0.5) - 0.5
        ctx = self.ctx
        fbo_ms = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer(size_col, 4, samples=self.samples)],
            depth_attachment=ctx.depth_renderbuffer(size_col, samples=self.samples),
        )
        fbo_rgb = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size_col, 4)])
        fbo_f32 = ctx.framebuffer(
            color_attachments=[ctx.renderbuffer(size, 1, dtype="f4")],
            depth_attachment=ctx.depth_renderbuffer(size),
        )
        P = gl_projection(setup.K, setup.width, setup.height, NEAR, FAR)
        P_col = gl_projection(K_col, size_col[0], size_col[1], NEAR, FAR)
        st = _CameraState(
            cam,
            setup,
            P,
            K_col,
            P_col,
            size_col,
            fbo_ms,
            fbo_rgb,
            fbo_f32,
            self._vignette(cam),
            self._noise_bank(cam),
        )
        self._states[name] = st
        log.info(
            "camera %s: pinhole render %dx%d for %dx%d image",
            name,
            setup.width,
            setup.height,
            cam.width,
            cam.height,
        )
        return st

    def _vignette(self, cam: CameraModel) -> NDArray[np.float32]:
        v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
        r2 = ((u - cam.K[0, 2]) / (0.5 * cam.width)) ** 2 + (
            (v - cam.K[1, 2]) / (0.5 * cam.width)
        ) ** 2
        return (1.0 - self.vignetting * np.clip(r2 / 1.4, 0.0, 1.0) ** 1.2).astype(np.float32)[
            ..., None
        ]

    def _noise_bank(self, cam: CameraModel) -> NDArray[np.int8]:
        rng = np.random.default_rng([self.seed, zlib.crc32(cam.name.encode())])
        shape = (cam.height + 64, cam.width + 64, 3)
        n = rng.normal(0.0, self.noise_sigma, size=shape).astype(np.float32)
        return np.clip(np.round(n), -127, 127).astype(np.int8)

    # ------------------------------------------------------------------ rendering
    def _matrices(self, st: _CameraState, T_world_base: ArrayLike) -> tuple[F64, F64]:
        """(T_opt_origin (4,4), T_world_opt (4,4)), composed in float64."""
        T_world_opt = np.asarray(T_world_base, dtype=np.float64) @ st.cam.T_base_opt
        T_opt_origin = invert_T(T_world_opt) @ self.T_world_origin
        return T_opt_origin, T_world_opt

    def _draw(self, st: _CameraState, T_world_base: ArrayLike, mode: int, P: F64) -> None:
        T_opt_origin, T_world_opt = self._matrices(st, T_world_base)
        mvp = P @ T_opt_origin
        self._prog["u_mvp"].write(mvp.T.astype("f4").tobytes())
        self._prog["u_view"].write(T_opt_origin.T.astype("f4").tobytes())
        self._prog["u_cam"].value = tuple(T_world_opt[:3, 3] - self.origin)
        self._prog["u_mode"].value = mode
        self._mat_tex.use(0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        for first, count in self._visible_runs(mvp):
            self._prog["u_prim_base"].value = first
            self._vao.render(moderngl.TRIANGLES, vertices=3 * count, first=3 * first)

    def _draw_sky(self, st: _CameraState, T_world_base: ArrayLike) -> None:
        _, T_world_opt = self._matrices(st, T_world_base)
        K = st.K_col
        self._sky["u_R_world_opt"].write(T_world_opt[:3, :3].T.astype("f4").tobytes())
        self._sky["u_K"].value = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        self.ctx.disable(moderngl.DEPTH_TEST)
        self._sky_vao.render(moderngl.TRIANGLE_STRIP)

    def render_pinhole(self, camera_name: str, T_world_base: ArrayLike) -> NDArray[np.uint8]:
        """The undistorted pinhole render (h, w, 3) uint8 of ``render_setup()``, no noise.

        Supersampled renders are reduced to the pinhole size with area averaging.
        """
        st = self._state(camera_name)
        st.fbo_ms.use()
        st.fbo_ms.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        self._draw_sky(st, T_world_base)
        self._draw(st, T_world_base, 0, st.P_col)
        fbo = st.fbo_ms
        if self.samples > 0:
            self.ctx.copy_framebuffer(st.fbo_rgb, st.fbo_ms)
            fbo = st.fbo_rgb
        data = fbo.read(components=3, alignment=1)
        img = np.frombuffer(data, np.uint8).reshape(st.size_col[1], st.size_col[0], 3)
        if st.size_col != (st.setup.width, st.setup.height):
            img = cv2.resize(img, (st.setup.width, st.setup.height), interpolation=cv2.INTER_AREA)
        return img

    def render(
        self, camera_name: str, T_world_base: ArrayLike, noise_seed: int | None = None
    ) -> NDArray[np.uint8]:
        """RGB image (H, W, 3) uint8 of a camera at vehicle pose T_world_base (4, 4).

        noise_seed selects the sensor-noise pattern (default: derived from the pose, so the
        same pose always gives the same image).
        """
        st = self._state(camera_name)
        pin = self.render_pinhole(camera_name, T_world_base)
        img = cv2.remap(
            pin, st.setup.map_x, st.setup.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )
        if noise_seed is None:
            noise_seed = zlib.crc32(np.asarray(T_world_base, np.float64).tobytes())
        rng = np.random.default_rng([self.seed, int(noise_seed) & 0xFFFFFFFF])
        dy, dx = rng.integers(0, 64, 2)
        H, W = img.shape[:2]
        noise = st.noise[dy : dy + H, dx : dx + W]
        out = img.astype(np.float32) * st.vignette + noise
        return np.clip(out, 0, 255).astype(np.uint8)

    def _render_f32(
        self, camera_name: str, T_world_base: ArrayLike, mode: int
    ) -> NDArray[np.float32]:
        st = self._state(camera_name)
        st.fbo_f32.use()
        st.fbo_f32.clear(-1.0, 0.0, 0.0, 0.0, depth=1.0)
        self._draw(st, T_world_base, mode, st.P)
        raw = st.fbo_f32.read(components=1, dtype="f4", alignment=1)
        pin = np.frombuffer(raw, np.float32).reshape(st.setup.height, st.setup.width)
        return cv2.remap(
            pin, st.setup.map_x, st.setup.map_y, cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0,
        )  # fmt: skip

    def render_depth(self, camera_name: str, T_world_base: ArrayLike) -> NDArray[np.float32]:
        """Metric depth along the optical z (H, W) float32 in the distorted image; NaN = sky."""
        d = self._render_f32(camera_name, T_world_base, 1)
        d[d <= 0.0] = np.nan
        return d

    def render_labels(self, camera_name: str, T_world_base: ArrayLike) -> NDArray[np.int16]:
        """Material index (into MATERIALS) per pixel (H, W) int16, distorted image; -1: sky."""
        m = self._render_f32(camera_name, T_world_base, 2)
        return np.round(m).astype(np.int16)

    def close(self) -> None:
        """Release the GPU objects (the shared context stays)."""
        for st in self._states.values():
            for fbo in (st.fbo_ms, st.fbo_rgb, st.fbo_f32):
                for a in (*fbo.color_attachments, fbo.depth_attachment):
                    if a is not None:
                        a.release()
                fbo.release()
        self._states.clear()
        for obj in (
            self._vao,
            self._sky_vao,
            self._vbo,
            self._ibo,
            self._quad,
            self._mat_tex,
            self._prog,
            self._sky,
        ):
            obj.release()
