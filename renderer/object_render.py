"""Render a virtual object into a real camera image: colour, coverage, depth and shadow.

One :class:`ObjectRenderer` per camera (moderngl on EGL: llvmpipe or a GPU, same code).
Per call, for the object at ``T_world_obj`` seen from the vehicle pose ``T_world_base``:

1. **Geometry in float64, GPU in small numbers.** ``T_opt_obj = inv(T_world_base @
   T_base_opt) @ T_world_obj`` is composed in float64; the object's vertices are uploaded
   once in its own frame (metres around its origin), proxies relative to an origin on a
   10 m grid next to the object. Only products of float64 matrices are cast to float32,
   so world magnitudes (UTM, ECEF) never reach the GPU.
2. **Region of interest.** The object's (and, with proxies and sun, its ground shadow's)
   extent is found in undistorted normalised coordinates, clipped at the near plane
   (edges crossing it are cut there), bounded by the camera's undistorted pinhole
   (``CameraModel.render_setup``), then mapped through the real distortion (the rectangle's
   boundary, radially clamped at the distortion fold ``r_valid``) into the distorted
   image: ``roi`` = that box + ``ROI_MARGIN_PX``, clipped to the image. With
   ``roi=False`` the whole image is the ROI.
3. **Pinhole render of the ROI.** The sub-window of the render-setup pinhole that the
   ROI's remap reads is rendered (supersampled ``s`` x ``s``), with a reversed-Z depth
   (:class:`renderer.gl_context.ReversedZ`: window depth ``near / z`` in a 32-bit float
   buffer, relative precision ~1e-7 of the distance at every range, so objects standing
   on a ground proxy do not z-fight). It is exact when interpolated from the vertices,
   so no pass writes ``gl_FragDepth`` and llvmpipe tests depth before shading: hidden
   fragments cost no shading.

   - shadow map: the object's depth seen from the sun (orthographic, object frame; its
     size a power of two from the camera's footprint at the object); drawn once per
     mesh, sun direction and size: a static object seen again reuses it;
   - object pass: lit colour (:mod:`renderer.lighting`'s model, self-shadowed), coverage,
     optical z;
   - proxy passes (depth only for the image): proxies drawn behind the object's depth
     with a relative bias ``PROXY_DEPTH_BIAS`` (a proxy must be really in front to hide
     the object), first their depth alone, then, where a proxy is the nearest surface
     (depth equal), it records "occluded" and the fraction of sun light the object
     blocks there (percentage-closer filtering of the shadow map): the filter runs once
     a pixel, not once per proxy layer (the scene's proxies overlap 4-5 deep).
4. **Distort, then resolve.** The layers (premultiplied by coverage) are resampled
   bilinearly from the supersampled pinhole onto an ``s`` x ``s`` sub-grid of each
   distorted ROI pixel, at the positions the camera's own pinhole<-distorted maps give
   (``RenderSetup.map_x/map_y``, interpolated bilinearly between pixel centres as the
   map itself is between its nodes), then each pixel's ``s`` x ``s`` sub-samples are
   averaged: the object lands where the real lens puts it and its edge is the ``s``
   samples' box (variance ``(s^2 - 1) / (12 s^2)`` px^2) plus the bilinear resampling's at
   the sub-sample pitch, ``phi (1 - phi) / s^2`` at the map's phase ``phi`` (1/(6 s^2) on
   average, ``(s^2 + 1) / (12 s^2)`` in all; ``ObjectRender.edge_var_px2`` has it at the
   render's own phases, :func:`resample_var_px2`). Resampling the
   averaged pinhole pixels instead (distort after resolving) adds the bilinear's 1/6 px^2
   at the pixel pitch: a 0.5 px edge instead of 0.30 px at s = 4.

Anti-aliasing (``antialias``): ``"none"`` (s = 1), ``"ssaa<s>"`` (fixed integer s), or
``"auto"``: the largest s <= ``AUTO_SSAA_MAX`` with s^2 x (sub-window pixels) <=
``AUTO_SSAA_SAMPLES`` (small far objects get 4 x 4 samples, a full-image elephant 1).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry.camera import TOL, CameraModel, gl_projection_reversed_z
from geometry.transforms import invert_T
from renderer.gl_context import create_context, reversed_z
from renderer.lighting import SRGB8_TO_LINEAR, Lighting
from renderer.mesh import Material, ObjectMesh, ProxyMesh

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

ROI_MARGIN_PX = 8  # around the projected extent (blur and feathering room for composite)
AUTO_SSAA_MAX = 4
AUTO_SSAA_SAMPLES = 1.2e5  # llvmpipe cost grows with triangles x samples
PROXY_DEPTH_BIAS = 2e-4  # relative depth a proxy must be in front to hide the object
SHADOW_MAP_MIN, SHADOW_MAP_MAX = 64, 2048
_SHADOW_MAPS_KEPT = 3
SHADOW_MAX_LENGTH = 4.0  # ground shadow length at most this x the object's height (ROI)
_BOUNDARY_SAMPLES = 96  # per edge, when mapping the ROI rectangle through the distortion
_PROXY_ORIGIN_GRID = 10.0  # m
TEXTURE_ANISOTROPY = 1.0  # llvmpipe: 8x costs 3.4x the render (0.42 vs 0.12 s); SSAA averages
_REMAP_GRID = 256.0  # sub-pixel map positions are multiples of 1 / _REMAP_GRID


# ---------------------------------------------------------------------------- shaders
_SHADOW_FN = """
uniform sampler2D u_shadow;
uniform int u_use_shadow;
uniform vec2 u_sm_size;
// Fraction of sun light blocked at light-space point l = (x_ndc, y_ndc, depth along the
// light in m), 4x4 percentage-closer filter with bilinear weights.
float shadow_at(vec3 l, float bias) {
    if (u_use_shadow == 0) return 0.0;
    vec2 t = (l.xy * 0.5 + 0.5) * u_sm_size - 0.5;
    if (t.x < -1.0 || t.y < -1.0 || t.x > u_sm_size.x || t.y > u_sm_size.y) return 0.0;
    vec2 f = fract(t);
    ivec2 i0 = ivec2(floor(t));
    ivec2 hi = ivec2(u_sm_size) - 1;
    float acc = 0.0, wsum = 0.0;
    for (int y = -1; y <= 2; ++y) {
        float wy = y == -1 ? 1.0 - f.y : (y == 2 ? f.y : 1.0);
        for (int x = -1; x <= 2; ++x) {
            float wx = x == -1 ? 1.0 - f.x : (x == 2 ? f.x : 1.0);
            float d = texelFetch(u_shadow, clamp(i0 + ivec2(x, y), ivec2(0), hi), 0).r;
            acc += wx * wy * (d < l.z - bias ? 1.0 : 0.0);
            wsum += wx * wy;
        }
    }
    return acc / wsum;
}
"""

# The same filter from four textureGather calls (GL 4.0 / ARB_texture_gather) instead of
# sixteen texelFetch: each gathers the 2 x 2 texels around a texel corner, the map's
# CLAMP_TO_EDGE doing the clamp; the taps are summed in the loop's order. On llvmpipe,
# which runs every branch of a SIMD block, this is 40 % of the proxy and object passes.
_SHADOW_FN_GATHER = """
uniform sampler2D u_shadow;
uniform int u_use_shadow;
uniform vec2 u_sm_size;
// Fraction of sun light blocked at light-space point l = (x_ndc, y_ndc, depth along the
// light in m), 4x4 percentage-closer filter with bilinear weights.
float shadow_at(vec3 l, float bias) {
    if (u_use_shadow == 0) return 0.0;
    vec2 t = (l.xy * 0.5 + 0.5) * u_sm_size - 0.5;
    if (t.x < -1.0 || t.y < -1.0 || t.x > u_sm_size.x || t.y > u_sm_size.y) return 0.0;
    vec2 f = fract(t);
    vec2 i0 = floor(t);
    vec2 inv = 1.0 / u_sm_size;  // a power of two: the corners below are exact
    vec4 zb = vec4(l.z - bias);
    // texels (i0.x - 1 + k, i0.y - 1 + m): a = k, m in 0..1, b = k 2..3, c = m 2..3, d both;
    // gather order (u_lo, v_hi), (u_hi, v_hi), (u_hi, v_lo), (u_lo, v_lo)
    vec4 a = vec4(lessThan(textureGather(u_shadow, i0 * inv), zb));
    vec4 b = vec4(lessThan(textureGather(u_shadow, (i0 + vec2(2.0, 0.0)) * inv), zb));
    vec4 c = vec4(lessThan(textureGather(u_shadow, (i0 + vec2(0.0, 2.0)) * inv), zb));
    vec4 d = vec4(lessThan(textureGather(u_shadow, (i0 + vec2(2.0, 2.0)) * inv), zb));
    float s[16] = float[16](a.w, a.z, b.w, b.z, a.x, a.y, b.x, b.y,
                            c.w, c.z, d.w, d.z, c.x, c.y, d.x, d.y);
    float acc = 0.0, wsum = 0.0;
    for (int y = -1; y <= 2; ++y) {
        float wy = y == -1 ? 1.0 - f.y : (y == 2 ? f.y : 1.0);
        for (int x = -1; x <= 2; ++x) {
            float wx = x == -1 ? 1.0 - f.x : (x == 2 ? f.x : 1.0);
            acc += wx * wy * s[4 * (y + 1) + x + 1];
            wsum += wx * wy;
        }
    }
    return acc / wsum;
}
"""


def shadow_source(src: str, gather: bool) -> str:
    """A fragment shader's source with the shadow filter that suits the context:
    ``gather`` (textureGather available) swaps in :data:`_SHADOW_FN_GATHER` and enables
    ARB_texture_gather after the ``#version`` line."""
    if not gather:
        return src
    src = src.replace(_SHADOW_FN, _SHADOW_FN_GATHER)
    ext = "#version 330\n#extension GL_ARB_texture_gather : require\n"
    return src.replace("#version 330\n", ext, 1)


def _material_uniforms(sf: _Surface) -> dict[str, object]:
    """A surface's material uniforms (textures on units 1-3; unit 0 is the shadow map)."""
    m = sf.material
    return {
        "u_base_factor": tuple(float(x) for x in m.base_color),
        "u_normal_scale": float(m.normal_scale),
        "u_roughness": float(m.roughness),
        "u_metallic": float(m.metallic),
        "u_alpha_cutoff": -1.0 if m.alpha_cutoff is None else float(m.alpha_cutoff),
        "u_triplanar": 0.0 if m.triplanar_m is None else float(m.triplanar_m),
        "u_base_tex": 1,
        "u_normal_tex": 2,
        "u_mr_tex": 3,
    }


def _set_uniforms(pg: moderngl.Program, values: dict[str, object]) -> None:
    """Set the uniforms the program kept (the GLSL compiler drops unused ones)."""
    for k, v in values.items():
        if k in pg:
            pg[k].value = v


def with_defines(src: str, defines: tuple[str, ...]) -> str:
    """A shader's source with ``#define NAME`` lines after its ``#version`` (and
    ``#extension``) lines."""
    if not defines:
        return src
    lines = src.split("\n")
    at = max(i for i, ln in enumerate(lines) if ln.startswith(("#version", "#extension"))) + 1
    return "\n".join(lines[:at] + [f"#define {d}" for d in defines] + lines[at:])


def material_defines(
    m: Material, *, base: bool, normal: bool, mr: bool, shadow: bool
) -> tuple[str, ...]:
    """The object fragment shader's variant for a material (``base``, ``normal``, ``mr``:
    which of its textures are on the GPU) and whether a shadow map is bound: only the
    code the material uses is compiled. llvmpipe runs both sides of a branch for every
    block of fragments, so a branch on a uniform costs what both sides cost: one shader
    with every feature behind uniforms took 400 ms for a fallen tree filling 1400 x 640
    pixels of rgb_highres_center, against 55 ms for the same pass with a trivial shader."""
    tri = m.triplanar_m is not None and float(m.triplanar_m) > 0.0
    d = []
    if base:
        d.append("HAS_BASE")
    if tri:
        d.append("TRIPLANAR")
    if normal and not tri:
        d.append("NORMAL_MAP")
    if m.alpha_cutoff is not None and float(m.alpha_cutoff) >= 0.0:
        d.append("ALPHA_CUTOFF")
    if m.specular:
        d.append("SPECULAR")
        if mr:
            d.append("HAS_MR")
    if shadow:
        d.append("SHADOW")
    return tuple(d)


_OBJ_VERTEX = """
#version 330
uniform mat4 u_mvp;
uniform mat4 u_light;
in vec3 in_pos;
in vec3 in_nrm;
in vec3 in_col;
in vec2 in_uv;
in vec4 in_tan;
out vec3 v_pos;
out vec3 v_nrm;
out vec3 v_col;
out vec3 v_light;
out vec2 v_uv;
out vec4 v_tan;
void main() {
    v_pos = in_pos;
    v_nrm = in_nrm;
    v_col = in_col;
    v_uv = in_uv;
    v_tan = in_tan;
    v_light = (u_light * vec4(in_pos, 1.0)).xyz;
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
"""

_OBJ_FRAGMENT = (
    """
#version 330
uniform vec3 u_sun;      // towards the sun, object frame
uniform vec3 u_up;       // world up, object frame
uniform vec3 u_cam;      // camera centre, object frame
uniform vec3 u_sun_rgb;
uniform vec3 u_sky;
uniform vec3 u_ground;
uniform float u_self_bias;
// material (renderer.mesh.Material)
uniform sampler2D u_base_tex;    // sRGB texture: sampled values are linear
uniform sampler2D u_normal_tex;
uniform sampler2D u_mr_tex;
uniform vec4 u_base_factor;
uniform float u_normal_scale;
uniform float u_roughness;
uniform float u_metallic;
uniform float u_alpha_cutoff;    // with ALPHA_CUTOFF
uniform float u_triplanar;       // with TRIPLANAR: period (m) of position-mapped textures
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_col;
in vec3 v_light;
in vec2 v_uv;
in vec4 v_tan;
layout(location = 0) out vec4 f_col;
layout(location = 1) out vec4 f_aux;
"""
    + _SHADOW_FN
    + """
const float PI = 3.14159265;
// A texture at this fragment: by UV, or by the object-space position seen along the
// three axes, blended by the geometric normal (triplanar mapping).
vec4 surface_tex(sampler2D t, vec3 ng) {
#ifdef TRIPLANAR
    vec3 w = pow(abs(ng), vec3(4.0));
    w /= (w.x + w.y + w.z + 1e-6);
    vec3 p = v_pos / u_triplanar;
    return w.x * texture(t, p.yz) + w.y * texture(t, p.xz) + w.z * texture(t, p.xy);
#else
    return texture(t, v_uv);
#endif
}
void main() {
    float z = 1.0 / gl_FragCoord.w;
    vec3 n = normalize(v_nrm);
    vec3 ng = normalize(cross(dFdx(v_pos), dFdy(v_pos)));
    if (dot(ng, n) < 0.0) ng = -ng;
    vec4 base = u_base_factor * vec4(v_col, 1.0);
#ifdef HAS_BASE
    base *= surface_tex(u_base_tex, ng);
#endif
#ifdef ALPHA_CUTOFF
    if (base.a < u_alpha_cutoff) discard;
#endif
    if (dot(ng, n) < 0.8) n = ng;          // hard edge: the smooth normal is meaningless
#ifdef NORMAL_MAP
    {  // tangent-space normal map
        vec3 t = v_tan.xyz - n * dot(n, v_tan.xyz);
        if (dot(t, t) > 1e-12) {
            t = normalize(t);
            vec3 b = cross(n, t) * (v_tan.w < 0.0 ? -1.0 : 1.0);
            vec3 tn = texture(u_normal_tex, v_uv).xyz * 2.0 - 1.0;
            tn.xy *= u_normal_scale;
            n = normalize(t * tn.x + b * tn.y + n * max(tn.z, 1e-3));
        }
    }
#endif
    vec3 V = normalize(u_cam - v_pos);
    if (dot(ng, V) < 0.0) n = -n;          // back faces of open meshes
    float lam = max(dot(n, u_sun), 0.0);
#ifdef SHADOW
    float lit = lam > 0.0 ? 1.0 - shadow_at(v_light, u_self_bias) : 0.0;
#else
    float lit = 1.0;                       // only ever multiplied by lam
#endif
    vec3 amb = mix(u_ground, u_sky, 0.5 + 0.5 * dot(n, u_up));
    vec3 albedo = base.rgb;
    vec3 col;
#ifndef SPECULAR
    col = albedo * (amb + u_sun_rgb * lam * lit);
#else  // glTF metallic-roughness: GGX sun lobe, Schlick-Fresnel sky reflection
    float rough = u_roughness, metal = u_metallic;
#ifdef HAS_MR
    vec4 mr = surface_tex(u_mr_tex, ng);
    rough *= mr.g;
    metal *= mr.b;
#endif
    vec3 f0 = mix(vec3(0.04), albedo, metal);
    float nv = max(dot(n, V), 1e-4);
    float a = max(rough * rough, 2e-3);
    vec3 h = normalize(u_sun + V);
    float nh = max(dot(n, h), 0.0), vh = max(dot(V, h), 0.0);
    float d = nh * nh * (a * a - 1.0) + 1.0;
    float D = a * a / (PI * d * d);
    float k = 0.5 * a;
    float G = (lam / (lam * (1.0 - k) + k)) * (nv / (nv * (1.0 - k) + k));
    vec3 F = f0 + (1.0 - f0) * pow(1.0 - vh, 5.0);
    vec3 brdf = D * G * F / max(4.0 * lam * nv, 1e-4);
    vec3 fe = f0 + (max(vec3(1.0 - rough), f0) - f0) * pow(1.0 - nv, 5.0);
    vec3 env = mix(u_ground, u_sky, 0.5 + 0.5 * dot(reflect(-V, n), u_up));
    vec3 kd = (1.0 - metal) * (1.0 - fe);
    col = kd * albedo * (amb + u_sun_rgb * lam * lit)
        + PI * brdf * u_sun_rgb * lam * lit + fe * env;
#endif
    f_col = vec4(col, 1.0);
    f_aux = vec4(z, 0.0, 0.0, 1.0);
}
"""
)

# The proxies' depth pass and shading pass share this vertex shader: the shading pass
# tests for the depth the first wrote (GL_EQUAL), which ``invariant`` makes bit-exact.
_PROXY_VERTEX = """
#version 330
uniform mat4 u_mvp;
uniform mat4 u_light;
in vec3 in_pos;
out vec3 v_light;
invariant gl_Position;
void main() {
    v_light = (u_light * vec4(in_pos, 1.0)).xyz;
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
"""

_PROXY_DEPTH_FRAGMENT = """
#version 330
void main() {}
"""

_PROXY_FRAGMENT = (
    """
#version 330
in vec3 v_light;
layout(location = 0) out vec4 f_aux;
"""
    + _SHADOW_FN
    + """
void main() {
    f_aux = vec4(0.0, 1.0, shadow_at(v_light, 0.0), 1.0);
}
"""
)

_SM_VERTEX = """
#version 330
uniform mat4 u_light;
uniform float u_zr;
in vec3 in_pos;
out float v_d;
void main() {
    vec3 l = (u_light * vec4(in_pos, 1.0)).xyz;
    v_d = l.z;
    gl_Position = vec4(l.xy, l.z / u_zr, 1.0);
}
"""

_SM_FRAGMENT = """
#version 330
in float v_d;
out vec4 f_d;
void main() { f_d = vec4(v_d, 0.0, 0.0, 1.0); }
"""


# ---------------------------------------------------------------------------- results
@dataclass
class ObjectRender:
    """The object in one distorted camera image, for the ROI only.

    roi : (u0, v0, u1, v1) pixel box, exclusive ends, clipped to the image; None when
        neither the object nor its shadow covers any pixel (then the arrays are empty).
    color : (h, w, 3) float32 linear RGB of the object (straight, not premultiplied;
        meaningful where alpha > 0).
    alpha : (h, w) float32 anti-aliased coverage in [0, 1] after occlusion by proxies.
    depth : (h, w) float32 optical z (m) of the visible object, NaN where alpha == 0.
    shadow : (h, w) float32 in [0, 1]: fraction of sun light the object blocks on the
        proxy surfaces visible at that pixel (its non-object part), 0 elsewhere.
    visible_fraction : visible object coverage / coverage without occluders (in-image).
    anchor_uv : (2,) distorted pixel of the object's origin (NaN if not projectable).
    bbox : (u0, v0, u1, v1) float pixel-edge box of the visible mask (alpha > 0.5, or
        > 0 for sub-pixel objects); NaN if nothing of the object is visible.
    distance_m : distance from the camera centre to the object's origin (m).
    motion_uv_per_m : (2,) image motion (px) of the anchor per metre the vehicle travels
        forward (base +x); composite's motion blur uses it. [addition to the contract]
    focal_px : the camera's fx at this image's resolution. [addition]
    pixel_scale : the camera's scale relative to the sensor's real resolution. [addition]
    edge_var_px2 : the render's own edge spread (variance of its line spread function,
        px^2): ``(s^2 - 1) / (12 s^2)`` for ``s`` x ``s`` supersamples plus the bilinear
        resampling's at this render's phases (:func:`resample_var_px2`; on average
        ``1 / (6 s^2)``, :func:`edge_var_px2`); 1/12, a pixel's box, for an exactly
        integrated coverage. [addition]
    """

    roi: tuple[int, int, int, int] | None
    color: F32
    alpha: F32
    depth: F32
    shadow: F32
    visible_fraction: float
    anchor_uv: F64
    bbox: tuple[float, float, float, float]
    distance_m: float
    motion_uv_per_m: F64 = field(default_factory=lambda: np.zeros(2))
    focal_px: float = 0.0
    pixel_scale: float = 1.0
    edge_var_px2: float = 1.0 / 12.0


@dataclass
class _Targets:
    size: tuple[int, int]
    col: moderngl.Texture
    aux: moderngl.Texture
    depth: moderngl.Renderbuffer
    fbo_obj: moderngl.Framebuffer
    fbo_proxy: moderngl.Framebuffer
    fbo_depth: moderngl.Framebuffer

    def release(self) -> None:
        for o in (self.fbo_obj, self.fbo_proxy, self.fbo_depth, self.col, self.aux, self.depth):
            o.release()


@dataclass
class _Surface:
    """One material's faces in the index buffer (first index, index count) and its
    textures on the GPU (None where the material has none)."""

    material: Material
    first: int
    count: int
    base: moderngl.Texture | None = None
    normal: moderngl.Texture | None = None
    mr: moderngl.Texture | None = None

    def release(self) -> None:
        for t in (self.base, self.normal, self.mr):
            if t is not None:
                t.release()


@dataclass
class _Upload:
    ref: object
    key: tuple
    vbo: moderngl.Buffer
    ibo: moderngl.Buffer
    vao: moderngl.VertexArray | None  # proxies: the proxy program's
    vao_sm: moderngl.VertexArray | None
    surfaces: list[_Surface] = field(default_factory=list)
    #: objects: one vertex array per shader variant (:func:`material_defines`), made on use;
    #: proxies: their depth pass's under ``("depth",)``
    vaos: dict[tuple[str, ...], moderngl.VertexArray] = field(default_factory=dict)

    def release(self) -> None:
        for o in (self.vao, self.vao_sm, *self.vaos.values(), self.vbo, self.ibo):
            if o is not None:
                o.release()
        for sf in self.surfaces:
            sf.release()


def edge_var_px2(s: int) -> float:
    """Variance (px^2) of the line spread of a render with ``s`` x ``s`` supersamples: the
    mean of ``s`` point samples across a pixel, ``(s^2 - 1) / (12 s^2)``, plus the
    bilinear resampling between samples ``1 / s`` px apart, ``1 / (6 s^2)`` on average over
    the edge's phase (:func:`resample_var_px2` has it at the render's own phases)."""
    return float((s * s + 1) / (12.0 * s * s))


def resample_var_px2(mx: F32, my: F32, alpha: F32, s: int) -> float | None:
    """Variance (px^2) the bilinear resampling adds to the edges of one render: at source
    positions ``mx``, ``my`` ((s h, s w), in sub-samples) of fractional parts
    ``(phi_u, phi_v)`` a step's line spread gets ``phi (1 - phi)`` along each axis (two
    taps, weights ``1 - phi`` and ``phi``, one sub-sample apart), ``(n_u^2 phi_u (1 -
    phi_u) + n_v^2 phi_v (1 - phi_v)) / s^2`` across an edge of unit normal ``n``, here
    averaged along the outline of the coverage ``alpha`` (h, w) (its contours at 0.5, each
    point's normal from the points 3 to either side, its phase term the mean over its
    pixel's sub-samples). Where the lens map's phase hardly changes over the object (a
    camera's centre, s = 1) this is far from the average ``1 / (6 s^2)`` (0.088-0.161 px^2
    at s = 1 where the average says 0.167: the composite, giving the frame's blur less the
    render's own, left such objects too sharp). The outline rather than the coverage's
    gradient over the whole ROI: 78 -> 6 ms on a 2200 x 1200 ROI. None without an outline.
    """
    inside = np.ascontiguousarray(alpha >= 0.5, dtype=np.uint8)
    contours, _ = cv2.findContours(inside, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    pts, tangents = [], []
    for c in contours:
        c = c[:, 0, :].astype(np.float64)  # (n, 2) u, v of a closed outline
        if len(c) < 8:
            continue
        pts.append(c)
        tangents.append(np.roll(c, -3, axis=0) - np.roll(c, 3, axis=0))
    if not pts:
        return None
    p = np.concatenate(pts).astype(np.intp)
    t = np.concatenate(tangents)
    t2 = t * t
    norm2 = t2.sum(axis=1)
    ok = norm2 > 0
    p, t2, norm2 = p[ok], t2[ok], norm2[ok]
    if not len(p):
        return None
    # the normal's components squared: n_u^2 = t_v^2 / |t|^2, n_v^2 = t_u^2 / |t|^2
    nu2, nv2 = t2[:, 1] / norm2, t2[:, 0] / norm2
    k = np.arange(s)
    rows = (s * p[:, 1:2] + k[None]).repeat(s, axis=1)  # (m, s^2) each pixel's sub-samples
    cols = np.tile(s * p[:, 0:1] + k[None], (1, s))
    q = []
    for m in (mx, my):
        v = np.asarray(m[rows, cols], np.float64)
        f = v - np.floor(v)
        q.append((f * (1.0 - f)).mean(axis=1))
    return float(np.mean(nu2 * q[0] + nv2 * q[1])) / (s * s)


def subpixel_map(
    m: NDArray[np.float32], roi: tuple[int, int, int, int], s: int
) -> tuple[F64, NDArray[np.bool_]]:
    """A per-pixel map (H, W) read at the centres of each ROI pixel's ``s`` x ``s``
    sub-pixels: (s h, s w) values (bilinear between pixel centres, float64; linear
    extrapolation across the image border) and (s h, s w) "invalid" flags (a sub-pixel
    next to a negative map value). Sub-pixel ``k`` of pixel ``u`` sits at
    ``u - 0.5 + (k + 0.5) / s``."""
    u0, v0, u1, v1 = roi
    H, W = m.shape
    a0, b0, a1, b1 = max(u0 - 1, 0), max(v0 - 1, 0), min(u1 + 1, W), min(v1 + 1, H)
    crop = m[b0:b1, a0:a1].astype(np.float64)
    pad = ((1 - (v0 - b0), 1 - (b1 - v1)), (1 - (u0 - a0), 1 - (a1 - u1)))
    if any(p for pp in pad for p in pp):
        bad = np.pad(crop < 0, pad, mode="edge")
        crop = np.pad(crop, pad, mode="reflect", reflect_type="odd")
    else:
        bad = crop < 0
    # crop row / column 0 is pixel v0 - 1 / u0 - 1
    k = (np.arange(s) + 0.5) / s - 0.5

    def axis(n: int) -> tuple[NDArray[np.int64], F64]:
        t = (np.arange(n)[:, None] + k[None]).ravel() + 1.0
        i = np.minimum(np.floor(t).astype(np.int64), n)
        return i, t - i

    iv, fv = axis(v1 - v0)
    iu, fu = axis(u1 - u0)
    rows = crop[iv] * (1.0 - fv)[:, None] + crop[iv + 1] * fv[:, None]
    out = rows[:, iu] * (1.0 - fu)[None] + rows[:, iu + 1] * fu[None]
    b_rows = bad[iv] | (bad[iv + 1] & (fv > 0)[:, None])
    b_out = b_rows[:, iu] | (b_rows[:, iu + 1] & (fu > 0)[None])
    return out, b_out


def _exact_f32(x: F64) -> F32:
    """Positions on a 1/256 px grid, exact in float32 below 65536 px: the fraction (and so
    cv2.remap's interpolation weights) does not depend on the ROI's offset."""
    return (np.round(x * _REMAP_GRID) / _REMAP_GRID).astype(np.float32)


def vertex_normals(vertices: F64, faces: NDArray[np.int64]) -> F64:
    """Area-weighted unit vertex normals (n, 3) of a mesh with outward CCW faces."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.where(norm > 1e-20, vn / np.maximum(norm, 1e-30), np.array([0.0, 0.0, 1.0]))


def _edges(faces: NDArray[np.int64]) -> NDArray[np.int64]:
    """(3m, 2) edges of the triangles (duplicates kept)."""
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def _normalized_extent(p_opt: F64, edges: NDArray[np.int64], near: float) -> F64 | None:
    """(2, 2) [[x_min, y_min], [x_max, y_max]] of undistorted x/z, y/z of the geometry in
    front of the near plane (points with z >= near and edge crossings of z = near), or
    None if nothing is in front."""
    z = p_opt[:, 2]
    front = z >= near
    pts = [p_opt[front, :2] / z[front, None]]
    if not np.all(front) and len(edges):
        za, zb = z[edges[:, 0]], z[edges[:, 1]]
        cross = (za >= near) != (zb >= near)
        if np.any(cross):
            a, b = p_opt[edges[cross, 0]], p_opt[edges[cross, 1]]
            t = (near - za[cross]) / (zb[cross] - za[cross])
            q = a + t[:, None] * (b - a)
            pts.append(q[:, :2] / near)
    xy = np.concatenate(pts)
    if len(xy) == 0:
        return None
    return np.stack([xy.min(axis=0), xy.max(axis=0)])


@dataclass(frozen=True)
class _View:
    """One render's frames: camera (optical) <- world <- object, and the sun and the world
    up in the object frame."""

    T_world_obj: F64
    T_opt_world: F64
    T_opt_obj: F64
    T_obj_opt: F64
    sun_obj: F64
    up_obj: F64

    @classmethod
    def of(cls, cam: CameraModel, T_world_obj: F64, T_world_base: F64, light: Lighting) -> _View:
        T_world_opt = T_world_base @ cam.T_base_opt
        T_opt_world = invert_T(T_world_opt)
        T_opt_obj = T_opt_world @ T_world_obj
        R_obj_world = T_world_obj[:3, :3].T
        return cls(
            T_world_obj=T_world_obj,
            T_opt_world=T_opt_world,
            T_opt_obj=T_opt_obj,
            T_obj_opt=invert_T(T_opt_obj),
            sun_obj=R_obj_world @ light.sun_dir_world,
            up_obj=R_obj_world @ np.array([0.0, 0.0, 1.0]),
        )


@dataclass(frozen=True)
class _DepthPass:
    """What the object and proxy passes share: projection (reversed Z), shadow map."""

    P: F64
    light_obj: F64
    sm_tex: moderngl.Texture | None
    sm_size: tuple[int, int]  # (0, 0): none


class ObjectRenderer:
    """Renders :class:`ObjectMesh` instances into one camera's distorted image.

    Parameters
    ----------
    camera : the camera at the resolution of the images to augment.
    roi : render only the object's region of interest (default) or the whole image.
    antialias : ``"auto"``, ``"none"`` or ``"ssaa<s>"`` (see the module docstring).
    gather_shadow : filter the shadow map with textureGather where the context has it
        (the same filter, fewer texture reads); False: sixteen texelFetch.
    """

    def __init__(
        self,
        camera: CameraModel,
        *,
        roi: bool = True,
        antialias: str = "auto",
        gather_shadow: bool = True,
    ) -> None:
        self.camera = camera
        self.use_roi = bool(roi)
        self.antialias = antialias
        self._fixed_ss = self._parse_antialias(antialias)
        self.setup = camera.render_setup()
        self.ctx = create_context()
        gather = gather_shadow and (
            self.ctx.version_code >= 400 or "GL_ARB_texture_gather" in self.ctx.extensions
        )
        self._obj_fragment = shadow_source(_OBJ_FRAGMENT, gather)
        self._obj_progs: dict[tuple[str, ...], moderngl.Program] = {}
        self._rz = reversed_z(self.ctx)
        self._prog_proxy = self.ctx.program(
            vertex_shader=_PROXY_VERTEX, fragment_shader=shadow_source(_PROXY_FRAGMENT, gather)
        )
        self._prog_proxy_depth = self.ctx.program(
            vertex_shader=_PROXY_VERTEX, fragment_shader=_PROXY_DEPTH_FRAGMENT
        )
        self._prog_sm = self.ctx.program(vertex_shader=_SM_VERTEX, fragment_shader=_SM_FRAGMENT)
        self._targets: _Targets | None = None
        #: shadow maps by size (most recent last): texture, depth buffer, framebuffer
        self._sms: dict[
            tuple[int, int], tuple[moderngl.Texture, moderngl.Renderbuffer, moderngl.Framebuffer]
        ] = {}
        #: by size, what its map holds: the object's upload and (sun, up) in its frame
        self._sm_drawn: dict[tuple[int, int], tuple[_Upload, tuple[bytes, bytes]]] = {}
        self._obj_cache: list[_Upload] = []
        self._proxy_cache: list[_Upload] = []
        # Pixel-centre extent of the pinhole render in normalised undistorted coordinates.
        K = self.setup.K
        self._pin_lo = np.array([(-0.5 - K[0, 2]) / K[0, 0], (-0.5 - K[1, 2]) / K[1, 1]])
        self._pin_hi = np.array(
            [
                (self.setup.width - 0.5 - K[0, 2]) / K[0, 0],
                (self.setup.height - 0.5 - K[1, 2]) / K[1, 1],
            ]
        )

    # ------------------------------------------------------------------ configuration
    @staticmethod
    def _parse_antialias(antialias: str) -> int:
        """0 for ``auto``, else the fixed supersampling factor."""
        if antialias == "auto":
            return 0
        if antialias == "none":
            return 1
        if antialias.startswith("ssaa"):
            s = int(antialias[4:])
            if 1 <= s <= 8:
                return s
        raise ValueError(f"antialias must be auto, none or ssaa<1..8>, got {antialias!r}")

    def _supersample(self, w: int, h: int) -> int:
        if self._fixed_ss:
            return self._fixed_ss
        s = int(np.floor(np.sqrt(AUTO_SSAA_SAMPLES / max(1, w * h))))
        return int(np.clip(s, 1, AUTO_SSAA_MAX))

    # ------------------------------------------------------------------ GPU resources
    def _get_targets(self, w: int, h: int) -> _Targets:
        t = self._targets
        if t is not None and t.size[0] >= w and t.size[1] >= h:
            return t
        if t is not None:
            t.release()
        W = int(np.ceil(max(w, t.size[0] if t else 0) / 128) * 128)
        H = int(np.ceil(max(h, t.size[1] if t else 0) / 128) * 128)
        ctx = self.ctx
        col = ctx.texture((W, H), 4, dtype="f4")
        aux = ctx.texture((W, H), 4, dtype="f4")
        depth = self._rz.depth32f_renderbuffer((W, H))
        fbo_obj = ctx.framebuffer(color_attachments=[col, aux], depth_attachment=depth)
        fbo_proxy = ctx.framebuffer(color_attachments=[aux], depth_attachment=depth)
        fbo_depth = ctx.framebuffer(color_attachments=[], depth_attachment=depth)
        self._targets = _Targets((W, H), col, aux, depth, fbo_obj, fbo_proxy, fbo_depth)
        log.debug("%s: render targets %dx%d", self.camera.name, W, H)
        return self._targets

    def _get_shadow_map(self, nx: int, ny: int) -> tuple[moderngl.Texture, moderngl.Framebuffer]:
        """A shadow map of at least ``nx`` x ``ny`` texels, each side a power of two (the
        filter's texel corners are then exact); the last ``_SHADOW_MAPS_KEPT`` sizes kept."""
        size = (int(2 ** np.ceil(np.log2(nx))), int(2 ** np.ceil(np.log2(ny))))
        got = self._sms.pop(size, None)
        if got is None:
            self._sm_drawn.pop(size, None)
            tex = self.ctx.texture(size, 1, dtype="f4")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False  # clamp to edge, as the filter clamps
            rb = self.ctx.depth_renderbuffer(size)
            fbo = self.ctx.framebuffer(color_attachments=[tex], depth_attachment=rb)
            got = (tex, rb, fbo)
        self._sms[size] = got
        while len(self._sms) > _SHADOW_MAPS_KEPT:
            evicted = next(iter(self._sms))
            self._sm_drawn.pop(evicted, None)
            old = self._sms.pop(evicted)
            for o in old[::-1]:
                o.release()
        return got[0], got[2]

    def _upload_object(self, obj: ObjectMesh) -> _Upload:
        key = (id(obj), len(obj.vertices), len(obj.faces))
        for up in self._obj_cache:
            if up.ref is obj and up.key == key:
                return up
        n = len(obj.vertices)
        nrm = obj.normals if obj.normals is not None else vertex_normals(obj.vertices, obj.faces)
        uv = obj.uv if obj.uv is not None else np.zeros((n, 2), np.float32)
        tan = obj.tangents if obj.tangents is not None else np.tile([1.0, 0, 0, 1.0], (n, 1))
        data = np.concatenate(
            [obj.vertices.astype(np.float32), nrm.astype(np.float32), obj.colors,
             uv.astype(np.float32), tan.astype(np.float32)], axis=1,
        )  # fmt: skip
        mats, face_mat = obj.surface
        order = np.argsort(face_mat, kind="stable")  # faces grouped by material
        counts = np.bincount(face_mat, minlength=len(mats))
        vbo = self.ctx.buffer(np.ascontiguousarray(data, np.float32).tobytes())
        ibo = self.ctx.buffer(obj.faces[order].astype(np.uint32).tobytes())
        vao_sm = self.ctx.vertex_array(
            self._prog_sm, [(vbo, "3f 48x", "in_pos")], index_buffer=ibo, index_element_size=4
        )
        surfaces = []
        first = 0
        for m, c in zip(mats, counts, strict=True):
            if c:
                surfaces.append(_Surface(
                    m, 3 * first, 3 * int(c),
                    self._texture(m.base_color_texture, srgb=True),
                    self._texture(m.normal_texture, srgb=False),
                    self._texture(m.metallic_roughness_texture, srgb=False),
                ))  # fmt: skip
            first += int(c)
        up = _Upload(obj, key, vbo, ibo, None, vao_sm, surfaces)
        self._obj_cache.append(up)
        if len(self._obj_cache) > 4:
            self._obj_cache.pop(0).release()
        return up

    def _texture(self, img: NDArray[np.uint8] | None, *, srgb: bool) -> moderngl.Texture | None:
        """A mipmapped, repeating texture of an (h, w, 3|4) uint8 image (row 0 = v 0);
        ``srgb``: its colour channels are sRGB, converted to linear light here and stored
        as half floats, so the sampler returns linear values and filtering and mipmaps
        average in linear light. (A GL_SRGB8_ALPHA8 texture does the same on the GPU, but
        llvmpipe decodes every texel of every fetch: a triplanar bark, three trilinear
        fetches a fragment, cost 135 of a 235 ms object pass.)"""
        if img is None:
            return None
        rgba = img if img.shape[2] == 4 else np.dstack([img, np.full(img.shape[:2], 255, np.uint8)])
        h, w = rgba.shape[:2]
        if srgb:
            lin = rgba.astype(np.float32) / 255.0
            lin[..., :3] = SRGB8_TO_LINEAR[rgba[..., :3]]
            tex = self.ctx.texture((w, h), 4, np.ascontiguousarray(lin, np.float16).tobytes(),
                                   dtype="f2")  # fmt: skip
        else:
            tex = self.ctx.texture((w, h), 4, np.ascontiguousarray(rgba).tobytes())
        tex.repeat_x = tex.repeat_y = True
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.anisotropy = TEXTURE_ANISOTROPY
        return tex

    def _upload_proxies(self, proxies: ProxyMesh, origin: F64) -> _Upload:
        key = (id(proxies), len(proxies.vertices), len(proxies.faces), tuple(origin))
        for up in self._proxy_cache:
            if up.ref is proxies and up.key == key:
                return up
        v = (proxies.vertices - origin).astype(np.float32)
        vbo = self.ctx.buffer(v.tobytes())
        ibo = self.ctx.buffer(proxies.faces.astype(np.uint32).tobytes())
        vao = self.ctx.vertex_array(
            self._prog_proxy, [(vbo, "3f", "in_pos")], index_buffer=ibo, index_element_size=4
        )
        up = _Upload(proxies, key, vbo, ibo, vao, None)
        up.vaos[("depth",)] = self.ctx.vertex_array(
            self._prog_proxy_depth, [(vbo, "3f", "in_pos")], index_buffer=ibo,
            index_element_size=4,
        )  # fmt: skip
        self._proxy_cache.append(up)
        if len(self._proxy_cache) > 2:
            self._proxy_cache.pop(0).release()
        return up

    def close(self) -> None:
        """Release this renderer's GPU objects (the shared context stays)."""
        for up in self._obj_cache + self._proxy_cache:
            up.release()
        self._obj_cache.clear()
        self._proxy_cache.clear()
        if self._targets is not None:
            self._targets.release()
            self._targets = None
        for sm in self._sms.values():
            for o in sm[::-1]:
                o.release()
        self._sms.clear()
        self._sm_drawn.clear()
        for p in (*self._obj_progs.values(), self._prog_proxy, self._prog_proxy_depth,
                  self._prog_sm):  # fmt: skip
            p.release()
        self._obj_progs.clear()

    # ------------------------------------------------------------------ geometry helpers
    def _shadow_points_obj(self, obj: ObjectMesh, sun_obj: F64, up_obj: F64) -> F64:
        """(8, 3) the object's bounding-box corners cast along the sun onto the plane
        through its origin normal to world up (object frame), length-capped."""
        b = obj.bounds
        corners = np.array(
            [[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
        )
        h = corners @ up_obj
        height = max(float(h.max()), 1e-3)
        s_up = float(sun_obj @ up_obj)
        # Horizontal shift per metre of height, capped.
        horiz = sun_obj - s_up * up_obj
        length = min(1.0 / max(s_up, 1e-6), SHADOW_MAX_LENGTH / max(np.linalg.norm(horiz), 1e-9))
        return corners - np.clip(h, 0.0, height)[:, None] * sun_obj[None] * length

    def _roi_from_extent(self, ext: F64) -> tuple[tuple[int, int, int, int], F64] | None:
        """Normalised extent -> (distorted ROI, pinhole rectangle (2, 2) in normalised)."""
        lo = np.maximum(ext[0], self._pin_lo)
        hi = np.minimum(ext[1], self._pin_hi)
        if np.any(lo > hi):
            return None
        n = _BOUNDARY_SAMPLES
        t = np.linspace(0.0, 1.0, n)
        xs = lo[0] + t * (hi[0] - lo[0])
        ys = lo[1] + t * (hi[1] - lo[1])
        border = np.concatenate(
            [
                np.stack([xs, np.full(n, lo[1])], 1),
                np.stack([xs, np.full(n, hi[1])], 1),
                np.stack([np.full(n, lo[0]), ys], 1),
                np.stack([np.full(n, hi[0]), ys], 1),
            ]
        )
        r = np.hypot(border[:, 0], border[:, 1])
        r_max = min(self.camera.r_valid, TOL.max_radius) * (1.0 - 1e-9)
        border *= np.minimum(1.0, r_max / np.maximum(r, 1e-300))[:, None]
        uv = self.camera.distort(border) @ self.camera.K[:2, :2].T + self.camera.K[:2, 2]
        m = ROI_MARGIN_PX
        u0 = int(np.floor(uv[:, 0].min())) - m
        v0 = int(np.floor(uv[:, 1].min())) - m
        u1 = int(np.ceil(uv[:, 0].max())) + 1 + m
        v1 = int(np.ceil(uv[:, 1].max())) + 1 + m
        u0, u1 = max(u0, 0), min(u1, self.camera.width)
        v0, v1 = max(v0, 0), min(v1, self.camera.height)
        if u0 >= u1 or v0 >= v1:
            return None
        return (u0, v0, u1, v1), np.stack([lo, hi])

    # ------------------------------------------------------------------ rendering
    def render(
        self,
        obj: ObjectMesh,
        T_world_obj: ArrayLike,
        T_world_base: ArrayLike,
        proxies: ProxyMesh | None = None,
        light: Lighting | None = None,
        near: float = 0.05,
    ) -> ObjectRender:
        """Render ``obj`` at ``T_world_obj`` (4, 4) from vehicle pose ``T_world_base`` (4, 4)
        (the pose at THIS camera's timestamp), occluded by and casting shadows on
        ``proxies`` (world frame), lit by ``light`` (default: ``Lighting()``).

        Returns
        -------
        ObjectRender in the distorted image of ``self.camera`` (ROI only).
        """
        light = light if light is not None else Lighting()
        T_world_obj = np.asarray(T_world_obj, dtype=np.float64)
        T_world_base = np.asarray(T_world_base, dtype=np.float64)
        if not (np.all(np.isfinite(T_world_obj)) and np.all(np.isfinite(T_world_base))):
            raise ValueError("poses must be finite")
        if not near > 0:
            raise ValueError(f"near must be > 0, got {near}")
        view = _View.of(self.camera, T_world_obj, T_world_base, light)
        anchor_uv, distance, motion = self._anchor(view.T_opt_obj)
        empty = self._empty(anchor_uv, distance, motion)

        shadows = proxies is not None and len(proxies.faces) > 0 and light.casts_shadows
        pts, edges = self._extent_points(obj, view, shadows)
        got = self._roi(pts, edges, near)
        if got is None:
            return empty
        roi, rect = got
        window = self._pinhole_window(roi, rect)
        if window is None:
            return empty
        pu0, pv0, pu1, pv1 = window
        pw, ph = pu1 - pu0, pv1 - pv0
        s = self._supersample(pw, ph)
        K_r = self.setup.K
        K_s = K_r.copy()
        K_s[0, 2] = s * (K_r[0, 2] - pu0 + 0.5) - 0.5
        K_s[1, 2] = s * (K_r[1, 2] - pv0 + 0.5) - 0.5
        K_s[0, 0] *= s
        K_s[1, 1] *= s
        W_s, H_s = pw * s, ph * s

        P = gl_projection_reversed_z(K_s, W_s, H_s, near)

        # Shadow map (object frame, orthographic along the sun).
        light_obj = np.eye(4)
        sm_tex = None
        sm_size = (0, 0)
        if light.casts_shadows:
            light_obj, sm_tex, sm_size, _, texel = self._render_shadow_map(
                obj, view.sun_obj, distance, obj_up=view.up_obj
            )
        else:
            texel = 0.0

        tg = self._get_targets(W_s, H_s)
        vp = (0, 0, W_s, H_s)
        fbo = tg.fbo_obj
        depth = _DepthPass(P, light_obj, sm_tex, sm_size)
        self._rz.zero_to_one(True)
        try:
            self._draw_object(fbo, vp, obj, view, light, depth, texel)
            if proxies is not None and len(proxies.faces):
                self._draw_proxies(tg, vp, proxies, view, depth, shadows)
        finally:  # the context's defaults for its other users
            self._rz.zero_to_one(False)
            self.ctx.depth_func = "<"

        col = np.frombuffer(fbo.read(viewport=vp, components=4, attachment=0, dtype="f4"), "f4")
        aux = np.frombuffer(fbo.read(viewport=vp, components=4, attachment=1, dtype="f4"), "f4")
        col = col.reshape(H_s, W_s, 4)
        aux = aux.reshape(H_s, W_s, 4)
        return self._resolve(col, aux, s, (pu0, pv0), roi, anchor_uv, distance, motion)

    def _anchor(self, T_opt_obj: F64) -> tuple[F64, float, F64]:
        """The object origin's pixel, its distance (m) and its image motion (px per metre
        of vehicle travel), in float64 through the camera model itself."""
        cam = self.camera
        p_opt_origin = T_opt_obj[:3, 3]
        anchor_uv = cam.project_optical(p_opt_origin)[0][0]
        distance = float(np.linalg.norm(p_opt_origin))
        motion = np.zeros(2)
        if np.all(np.isfinite(anchor_uv)):
            step = 0.01  # vehicle forward by 1 cm: the object moves by -1 cm along base x
            d_opt = cam.T_opt_base[:3, :3] @ np.array([-step, 0.0, 0.0])
            uv2 = cam.project_optical(p_opt_origin + d_opt)[0][0]
            if np.all(np.isfinite(uv2)):
                motion = (uv2 - anchor_uv) / step
        return anchor_uv, distance, motion

    def _extent_points(
        self, obj: ObjectMesh, view: _View, shadows: bool
    ) -> tuple[F64, NDArray[np.int64]]:
        """Points (optical frame) and edges whose image the render must cover: the object,
        and its ground shadow when proxies can receive it."""
        T_opt_obj = view.T_opt_obj
        p_opt = obj.vertices @ T_opt_obj[:3, :3].T + T_opt_obj[:3, 3]
        pts, edges = p_opt, _edges(obj.faces)
        if shadows:
            sp_obj = self._shadow_points_obj(obj, view.sun_obj, view.up_obj)
            b = obj.bounds
            corners = np.array(
                [[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
            )
            extra = np.concatenate([corners, sp_obj]) @ T_opt_obj[:3, :3].T + T_opt_obj[:3, 3]
            n0 = len(pts)
            pts = np.concatenate([pts, extra])
            pairs = np.stack([np.arange(8), np.arange(8, 16)], 1) + n0
            edges = np.concatenate([edges, pairs])
        return pts, edges

    def _roi(
        self, pts: F64, edges: NDArray[np.int64], near: float
    ) -> tuple[tuple[int, int, int, int], F64] | None:
        """The distorted image's ROI and the pinhole rectangle (normalised) to render; the
        whole image without ``use_roi``. None: nothing to render."""
        if self.use_roi:
            ext = _normalized_extent(pts, edges, near)
            if ext is None:
                return None
        else:
            ext = np.stack([self._pin_lo, self._pin_hi])
        got = self._roi_from_extent(ext)
        if got is None:
            return None
        if not self.use_roi:
            got = ((0, 0, self.camera.width, self.camera.height), got[1])
        return got

    def _pinhole_window(
        self, roi: tuple[int, int, int, int], rect: F64
    ) -> tuple[int, int, int, int] | None:
        """Pinhole sub-window (pu0, pv0, pu1, pv1) read by the ROI's remap (and covering
        the object's rectangle); None when the ROI reads no pinhole pixel."""
        u0, v0, u1, v1 = roi
        K_r = self.setup.K
        mx = self.setup.map_x[v0:v1, u0:u1]
        my = self.setup.map_y[v0:v1, u0:u1]
        ok = (mx >= 0) & (my >= 0)
        if not np.any(ok):
            return None
        pu0 = int(np.floor(max(mx[ok].min(), rect[0, 0] * K_r[0, 0] + K_r[0, 2]))) - 2
        pu1 = int(np.ceil(min(mx[ok].max(), rect[1, 0] * K_r[0, 0] + K_r[0, 2]))) + 3
        pv0 = int(np.floor(max(my[ok].min(), rect[0, 1] * K_r[1, 1] + K_r[1, 2]))) - 2
        pv1 = int(np.ceil(min(my[ok].max(), rect[1, 1] * K_r[1, 1] + K_r[1, 2]))) + 3
        pu0, pv0 = max(pu0, 0), max(pv0, 0)
        pu1, pv1 = min(pu1, self.setup.width), min(pv1, self.setup.height)
        if pu0 >= pu1 or pv0 >= pv1:
            return None
        return pu0, pv0, pu1, pv1

    def _draw_object(
        self,
        fbo: moderngl.Framebuffer,
        vp: tuple[int, int, int, int],
        obj: ObjectMesh,
        view: _View,
        light: Lighting,
        depth: _DepthPass,
        texel: float,
    ) -> None:
        """Clear the targets and draw the lit, shadowed object (colour and aux)."""
        ctx = self.ctx
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        ctx.depth_func = ">"  # reversed Z: nearer is greater
        fbo.use()
        fbo.viewport = vp
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=0.0, viewport=vp)

        up_o = self._upload_object(obj)
        shadow = depth.sm_tex is not None and min(depth.sm_size) > 0
        common: dict[str, object] = {
            "u_sun": tuple(view.sun_obj),
            "u_up": tuple(view.up_obj),
            "u_cam": tuple(view.T_obj_opt[:3, 3]),
            "u_sun_rgb": (light.sun_intensity,) * 3,
            "u_sky": tuple(light.sky_rgb),
            "u_ground": tuple(light.ambient_rgb),
            "u_self_bias": 2.0 * texel,
        }
        mvp = (depth.P @ view.T_opt_obj).T.astype("f4").tobytes()
        light_m = depth.light_obj.T.astype("f4").tobytes()
        for sf in up_o.surfaces:
            defines = material_defines(
                sf.material,
                base=sf.base is not None,
                normal=sf.normal is not None,
                mr=sf.mr is not None,
                shadow=shadow,
            )
            pg, vao = self._object_variant(up_o, defines)
            pg["u_mvp"].write(mvp)
            _set_uniforms(pg, {**common, **_material_uniforms(sf)})
            if "u_light" in pg:
                pg["u_light"].write(light_m)
            if "SHADOW" in defines:
                self._set_shadow_uniforms(pg, depth.sm_tex, depth.sm_size)
            for unit, tex in enumerate((sf.base, sf.normal, sf.mr), start=1):
                if tex is not None:
                    tex.use(unit)
            vao.render(moderngl.TRIANGLES, vertices=sf.count, first=sf.first)

    def _object_variant(
        self, up: _Upload, defines: tuple[str, ...]
    ) -> tuple[moderngl.Program, moderngl.VertexArray]:
        """The object program compiled with ``defines`` (made once per renderer) and the
        upload's vertex array for it."""
        pg = self._obj_progs.get(defines)
        if pg is None:
            pg = self.ctx.program(
                vertex_shader=_OBJ_VERTEX,
                fragment_shader=with_defines(self._obj_fragment, defines),
            )
            self._obj_progs[defines] = pg
        vao = up.vaos.get(defines)
        if vao is None:
            sizes = {"in_pos": 3, "in_nrm": 3, "in_col": 3, "in_uv": 2, "in_tan": 4}
            fmt = " ".join(f"{k}f" if n in pg else f"{4 * k}x" for n, k in sizes.items())
            used = [n for n in sizes if n in pg]
            vao = self.ctx.vertex_array(
                pg, [(up.vbo, fmt, *used)], index_buffer=up.ibo, index_element_size=4
            )
            up.vaos[defines] = vao
        return pg, vao

    def _draw_proxies(
        self,
        tg: _Targets,
        vp: tuple[int, int, int, int],
        proxies: ProxyMesh,
        view: _View,
        depth: _DepthPass,
        shadows: bool,
    ) -> None:
        """Draw the proxies over the object: they occlude it and receive its shadow.
        Uploaded relative to a grid-rounded origin near the object (float32 stays small).
        Their depth first (biased: clip z scaled by ``1 / (1 + PROXY_DEPTH_BIAS)``, i.e.
        each proxy read that much farther), then the shading where a proxy's depth is the
        one kept: hidden proxy layers are never shaded."""
        T_world_obj = view.T_world_obj
        origin = np.round(T_world_obj[:3, 3] / _PROXY_ORIGIN_GRID) * _PROXY_ORIGIN_GRID
        T_world_origin = np.eye(4)
        T_world_origin[:3, 3] = origin
        up_p = self._upload_proxies(proxies, origin)
        T_obj_origin = invert_T(T_world_obj) @ T_world_origin
        mvp = depth.P @ view.T_opt_world @ T_world_origin
        mvp[2] /= 1.0 + PROXY_DEPTH_BIAS
        mvp_b = mvp.T.astype("f4").tobytes()
        light_b = (depth.light_obj @ T_obj_origin).T.astype("f4").tobytes()
        for prog in (self._prog_proxy_depth, self._prog_proxy):
            prog["u_mvp"].write(mvp_b)
            if "u_light" in prog:
                prog["u_light"].write(light_b)
        ctx = self.ctx
        ctx.depth_func = ">"
        tg.fbo_depth.use()
        tg.fbo_depth.viewport = vp
        up_p.vaos[("depth",)].render(moderngl.TRIANGLES)

        pp = self._prog_proxy
        self._set_shadow_uniforms(pp, depth.sm_tex, depth.sm_size if shadows else (0, 0))
        ctx.depth_func = "=="
        fbo_p = tg.fbo_proxy
        fbo_p.use()
        fbo_p.viewport = vp
        fbo_p.depth_mask = False
        try:
            up_p.vao.render(moderngl.TRIANGLES)
        finally:
            fbo_p.depth_mask = True

    def _set_shadow_uniforms(
        self, prog: moderngl.Program, tex: moderngl.Texture | None, size: tuple[int, int]
    ) -> None:
        use = tex is not None and min(size) > 0
        prog["u_use_shadow"].value = 1 if use else 0
        prog["u_sm_size"].value = (float(max(size[0], 1)), float(max(size[1], 1)))
        if tex is not None:
            tex.use(0)
        prog["u_shadow"].value = 0

    def _render_shadow_map(
        self, obj: ObjectMesh, sun_obj: F64, distance: float, obj_up: F64
    ) -> tuple[F64, moderngl.Texture, tuple[int, int], float, float]:
        """Orthographic depth of the object along the sun, in the object frame.

        Returns (M (4, 4) object -> (x_ndc, y_ndc, depth m), texture, its size (w, h),
        depth range, texel size m: the larger side's). Texels are about the camera's pixel
        footprint at the object along each side of the object's extent across the sun (a
        square map of the longer side spent 4-6x the texels on a fallen tree).
        """
        w = -sun_obj  # light travel direction
        a = np.cross(w, obj_up if abs(w @ obj_up) < 0.99 else np.array([1.0, 0.0, 0.0]))
        a /= np.linalg.norm(a)
        b = np.cross(w, a)
        R = np.stack([a, b, w])
        c = 0.5 * (obj.bounds[0] + obj.bounds[1])
        q = (obj.vertices - c) @ R.T
        half = np.abs(q[:, :2]).max(axis=0) * 1.02 + 1e-3
        footprint = max(distance, 0.5) / self.camera.fx
        n = np.clip(np.ceil(2.0 * half / footprint), SHADOW_MAP_MIN, SHADOW_MAP_MAX).astype(int)
        tex, fbo = self._get_shadow_map(int(n[0]), int(n[1]))
        size = (int(tex.size[0]), int(tex.size[1]))
        texel = float(np.max(2.0 * half / np.asarray(size)))
        zr = float(np.abs(q[:, 2]).max() * 1.01 + 1e-3)
        M = np.eye(4)
        M[0, :3] = a / half[0]
        M[1, :3] = b / half[1]
        M[2, :3] = w
        M[:3, 3] = -(np.stack([a / half[0], b / half[1], w]) @ c)
        up = self._upload_object(obj)
        # the map is a function of the mesh, the sun and up in the object frame and its
        # size alone (not of the distance, which only picks the size): a static object
        # seen again at a size drawn before reuses it
        tag = (sun_obj.tobytes(), np.asarray(obj_up, np.float64).tobytes())
        drawn = self._sm_drawn.get(size)
        if drawn is not None and drawn[0] is up and drawn[1] == tag:
            return M, tex, size, zr, texel
        fbo.use()
        fbo.viewport = (0, 0, size[0], size[1])
        fbo.clear(1e9, 0.0, 0.0, 0.0, depth=1.0)
        self._prog_sm["u_light"].write(M.T.astype("f4").tobytes())
        self._prog_sm["u_zr"].value = zr
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        up.vao_sm.render(moderngl.TRIANGLES)
        self._sm_drawn[size] = (up, tag)
        return M, tex, size, zr, texel

    def _resolve(
        self,
        col: F32,
        aux: F32,
        s: int,
        p0: tuple[int, int],
        roi: tuple[int, int, int, int],
        anchor_uv: F64,
        distance: float,
        motion: F64,
    ) -> ObjectRender:
        """Supersampled pinhole layers -> distorted sub-pixels -> distorted ROI layers
        (module docstring, step 4)."""
        # planes split and merged by OpenCV, arithmetic on contiguous planes: numpy's ops
        # on the channels of the interleaved arrays (strides of 16 and 32 bytes) took
        # twice as long on a fallen tree's 1400 x 640 ROI
        r, g, b, obj = cv2.split(col)
        a_depth, a_proxy, a_shadow, _ = cv2.split(aux)
        vis = obj * (1.0 - a_proxy)  # covered by the object and not by a proxy
        inv = 1.0 - vis
        # two 4-channel images: OpenCV's remap and split of up to 4 channels take their
        # fast paths (an 8-channel split took 95 ms on a fallen tree's 2200 x 1200 ROI,
        # two 4-channel ones 23), and its remap then interpolates at the map's own
        # positions, where an 8-channel one rounded them to 1/32 px
        layer_sets = (
            cv2.merge([r * vis, g * vis, b * vis, vis]),
            cv2.merge([a_depth * vis, a_shadow * inv, inv, obj]),
        )
        u0, v0, u1, v1 = roi
        if s == 1:
            mx = self.setup.map_x[v0:v1, u0:u1] - np.float32(p0[0])
            my = self.setup.map_y[v0:v1, u0:u1] - np.float32(p0[1])
            bad = (self.setup.map_x[v0:v1, u0:u1] < 0) | (self.setup.map_y[v0:v1, u0:u1] < 0)
        else:  # sub-pixel positions in the supersampled pinhole (pixel centres at integers)
            sx, bad_x = subpixel_map(self.setup.map_x, roi, s)
            sy, bad_y = subpixel_map(self.setup.map_y, roi, s)
            mx = _exact_f32(s * (sx - p0[0] + 0.5) - 0.5)
            my = _exact_f32(s * (sy - p0[1] + 0.5) - 0.5)
            bad = bad_x | bad_y
        phase_x, phase_y = mx, my
        if np.any(bad):
            mx = np.where(bad, np.float32(-1e4), mx)
            my = np.where(bad, np.float32(-1e4), my)
        planes = []
        for layers in layer_sets:
            out = cv2.remap(
                layers, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
            )
            if s > 1:  # box average of each pixel's s x s sub-pixels (exact for integer s)
                out = cv2.resize(out, (u1 - u0, v1 - v0), interpolation=cv2.INTER_AREA)
            planes += cv2.split(out)
        # in place with ``where`` rather than through boolean indexing (a gather and a
        # scatter per array: 40 % of this function on a 1400 x 640 ROI)
        alpha = np.clip(planes[3], 0.0, 1.0)
        alpha[alpha < 1e-5] = 0.0
        resampled = resample_var_px2(phase_x, phase_y, alpha, s)
        own = (s * s - 1) / (12.0 * s * s) + resampled if resampled is not None else None
        has = alpha > 0
        rgb = []
        for plane in planes[:3]:
            c = np.zeros(alpha.shape, np.float32)
            np.divide(plane, alpha, out=c, where=has)
            rgb.append(c)
        color = cv2.merge(rgb)
        depth = np.full(alpha.shape, np.nan, np.float32)
        np.divide(planes[4], alpha, out=depth, where=has)
        shadow = np.zeros(alpha.shape, np.float32)
        nv = planes[6] > 1e-5
        np.divide(planes[5], planes[6], out=shadow, where=nv)
        np.clip(shadow, 0.0, 1.0, out=shadow)
        shadow[shadow < 1e-4] = 0.0
        unocc = float(planes[7].sum())
        any_obj = bool(has.any())
        if not any_obj and not shadow.any():
            return self._empty(anchor_uv, distance, motion)
        vis_frac = float(alpha.sum() / unocc) if unocc > 1e-9 else 0.0
        bbox = (np.nan, np.nan, np.nan, np.nan)
        sel = alpha > 0.5
        if not sel.any():
            sel = has
        if any_obj:
            vs = np.flatnonzero(sel.any(axis=1))
            us = np.flatnonzero(sel.any(axis=0))
            bbox = (
                float(u0 + us[0] - 0.5),
                float(v0 + vs[0] - 0.5),
                float(u0 + us[-1] + 0.5),
                float(v0 + vs[-1] + 0.5),
            )
        return ObjectRender(
            roi=roi,
            color=color,
            alpha=alpha,
            depth=depth,
            shadow=shadow,
            visible_fraction=min(vis_frac, 1.0),
            anchor_uv=anchor_uv,
            bbox=bbox,
            distance_m=distance,
            motion_uv_per_m=motion,
            focal_px=self.camera.fx,
            pixel_scale=self.camera.scale,
            edge_var_px2=edge_var_px2(s) if own is None else own,
        )

    def _empty(self, anchor_uv: F64, distance: float, motion: F64) -> ObjectRender:
        z = np.zeros((0, 0), np.float32)
        return ObjectRender(
            roi=None,
            color=np.zeros((0, 0, 3), np.float32),
            alpha=z,
            depth=z.copy(),
            shadow=z.copy(),
            visible_fraction=0.0,
            anchor_uv=anchor_uv,
            bbox=(np.nan, np.nan, np.nan, np.nan),
            distance_m=distance,
            motion_uv_per_m=motion,
            focal_px=self.camera.fx,
            pixel_scale=self.camera.scale,
        )
