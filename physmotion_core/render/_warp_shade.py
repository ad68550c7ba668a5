"""The photo texture's per-pixel passes compiled with Warp (CPU): photo coordinates, stretch, bicubic sampling
and blending, in three loops over the textured pixels instead of some forty whole-image tensor operations.

``photo_texture.shade`` holds the model and a tensor implementation of it (``compiled=False``, the fallback when
Warp is unavailable); this module computes the same values, with the arithmetic in the same precision (photo
coordinates and the stretch in float64, colours in float32), so the two agree to float32 round-off
(tests/test_photo_texture.py compares them to 1e-5).

* ``coords``: one loop over the box of pixels the seen splats reach: the pixel's photo coordinate (the one rigid
  map applied to its surface point, or its ray plus the composited displacement) and whether it has one.
* ``stretch``: per pixel, the photo's weight left by the stretch of the photo coordinates (the inverse of the
  smallest singular value of their Jacobian with respect to the pixel position, from the neighbours' coordinates).
* ``blend``: per pixel, the photo's share of the pixel (times that weight, spread by a minimum filter in between),
  the photo sampled bicubically (Keys' cubic, a = -0.75, zero outside the photo) and the frame's colour and
  coverage. The splats' interior floor needs a distance transform; OpenCV computes it and the minimum filter.

``stretch`` and ``blend`` loop over a row in C++ (Warp native functions, as ``_warp_raster._ROW``): plain pointer
arithmetic that the compiler optimises as a whole; the same loop in Warp's kernel language ran 3-4x slower
(16 against 4.4 ms on push_a_jelly's 146k-pixel box, one thread).
"""

# No "from __future__ import annotations": Warp reads the kernels' annotations, which name the local `wp`.

import numpy as np
import torch

from ..warp_build import built_once

#: ``stretch``'s loop over one row of the box (C++).
_STRETCH_ROW = r"""
const double* U = u.data + (size_t)by * bw;
const double* V = v.data + (size_t)by * bw;
const unsigned char* OK = ok.data + (size_t)by * bw;
float* F = fade.data + (size_t)by * bw;
// d c / d (pixel) at i from its neighbours (`stride` apart in memory): central where both have coordinates,
// one-sided where one has; false where none.
auto deriv = [&](const double* c, int i, bool lo_in, bool hi_in, long stride, double& d) -> bool {
    bool lo = lo_in && OK[i - stride] != 0, hi = hi_in && OK[i + stride] != 0;
    if (lo && hi) { d = (c[i + stride] - c[i - stride]) * 0.5; return true; }
    if (hi) { d = c[i + stride] - c[i]; return true; }
    if (lo) { d = c[i] - c[i - stride]; return true; }
    return false;
};
for (int bx = 0; bx < bw; ++bx) {
    double f = 1.0;
    if (OK[bx]) {
        double ux, vx, uy, vy;
        if (deriv(U, bx, bx > 0, bx < bw - 1, 1, ux)) {
            deriv(V, bx, bx > 0, bx < bw - 1, 1, vx);
        } else { ux = 1.0; vx = 0.0; }
        if (deriv(U, bx, by > 0, by < bh - 1, bw, uy)) {
            deriv(V, bx, by > 0, by < bh - 1, bw, vy);
        } else { uy = 0.0; vy = 1.0; }
        const double E = ux * ux + vx * vx + uy * uy + vy * vy;
        const double D = __builtin_fabs(ux * vy - uy * vx);
        const double q = E * E - 4.0 * D * D;
        const double smin2 = 0.5 * (E - __builtin_sqrt(q > 0.0 ? q : 0.0));
        if (smin2 * st1 * st1 < 1.0) f = 0.0;
        else if (smin2 * st0 * st0 < 1.0) f = (st1 - 1.0 / __builtin_sqrt(smin2)) / (st1 - st0);
    }
    F[bx] = (float)f;
}
return 0;
"""

#: ``blend``'s loop over one row of the box (C++).
_BLEND_ROW = r"""
const double* U = u.data + (size_t)by * bw;
const double* V = v.data + (size_t)by * bw;
const unsigned char* OK = ok.data + (size_t)by * bw;
const float* F = fade.data + (size_t)by * bw;
const float* P = planes.data;
const float* dr = dist.data + (size_t)by * bw;
const int y = y0 + by;
auto keys = [](float t, float* w) {
    const float a = -0.75f;
    float s = t + 1.0f;
    w[0] = ((a * s - 5.0f * a) * s + 8.0f * a) * s - 4.0f * a;
    w[1] = ((a + 2.0f) * t - (a + 3.0f)) * t * t + 1.0f;
    float r = 1.0f - t;
    w[2] = ((a + 2.0f) * r - (a + 3.0f)) * r * r + 1.0f;
    w[3] = 1.0f - w[0] - w[1] - w[2];
};
typedef float pm_v4f __attribute__((ext_vector_type(4)));
// The interior ramp's slope, once (exactly the division's result for INTERIOR_PX's 2 px span: a power of two).
const float inv_in = 1.0f / (in1 - in0);
for (int bx = 0; bx < bw; ++bx) {
    // A pixel without a photo coordinate keeps the frame's colour and coverage, which the caller put in out_rgb and
    // out_a (the formulas below give them back exactly there: w = 0, no floor excess).
    if (!OK[bx]) continue;
    const long p = (long)y * W + x0 + bx;
    const float a = alpha.data[p];
    float w = 0.0f;
    float smp[4] = {0.0f, 0.0f, 0.0f, 0.0f};
    {
        const float S = ext.data[p * C + C - 1];
        float sh = S / (a > 1e-12f ? a : 1e-12f);
        sh = sh < 0.0f ? 0.0f : (sh > 1.0f ? 1.0f : sh);
        float ramp = a * (1.0f / min_cov);
        ramp = ramp < 0.0f ? 0.0f : (ramp > 1.0f ? 1.0f : ramp);
        w = sh * ramp;
        w = w * F[bx];
        const double mx = U[bx] - 0.5, my = V[bx] - 0.5;
        const double fx = __builtin_floor(mx), fy = __builtin_floor(my);
        if (fx > -3.0 && fx < (double)(PW + 1) && fy > -3.0 && fy < (double)(PH + 1)) {
            const int ix = (int)fx, iy = (int)fy;
            float wx[4], wy[4];
            keys((float)(mx - fx), wx);
            keys((float)(my - fy), wy);
            if (ix >= 1 && ix + 2 < PW && iy >= 1 && iy + 2 < PH) {
                // All 16 taps inside the photo (most pixels): each tap's 4 floats as one vector, no bounds tests.
                pm_v4f acc = 0.0f;
                for (int j = 0; j < 4; ++j) {
                    const float* t = P + 4 * ((long)(iy - 1 + j) * PW + ix - 1);
                    pm_v4f t0, t1, t2, t3;
                    __builtin_memcpy(&t0, t, 16);
                    __builtin_memcpy(&t1, t + 4, 16);
                    __builtin_memcpy(&t2, t + 8, 16);
                    __builtin_memcpy(&t3, t + 12, 16);
                    pm_v4f row = 0.0f;
                    row += wx[0] * t0;
                    row += wx[1] * t1;
                    row += wx[2] * t2;
                    row += wx[3] * t3;
                    acc += wy[j] * row;
                }
                smp[0] = acc[0]; smp[1] = acc[1]; smp[2] = acc[2]; smp[3] = acc[3];
            } else for (int j = 0; j < 4; ++j) {
                const int yy = iy - 1 + j;
                if (yy < 0 || yy >= PH) continue;
                float row[4] = {0.0f, 0.0f, 0.0f, 0.0f};
                for (int k = 0; k < 4; ++k) {
                    const int xx = ix - 1 + k;
                    if (xx < 0 || xx >= PW) continue;
                    const float* t = P + 4 * ((long)yy * PW + xx);
                    row[0] += wx[k] * t[0]; row[1] += wx[k] * t[1]; row[2] += wx[k] * t[2]; row[3] += wx[k] * t[3];
                }
                smp[0] += wy[j] * row[0]; smp[1] += wy[j] * row[1]; smp[2] += wy[j] * row[2]; smp[3] += wy[j] * row[3];
            }
        }
    }
    float m_s = smp[3] < 0.0f ? 0.0f : (smp[3] > 1.0f ? 1.0f : smp[3]);
    const float keep = 1.0f - w;
    const float am = w * m_s + keep * a;
    float ramp_in = (dr[bx] - in0) * inv_in;
    ramp_in = ramp_in < 0.0f ? 0.0f : (ramp_in > 1.0f ? 1.0f : ramp_in);
    const float fl = a * ramp_in;
    const float ex = fl - am > 0.0f ? fl - am : 0.0f;
    out_a.data[p] = am + ex;
    float g = 0.0f;  // the floor's excess, relative: mostly none (a branch, not a division on every pixel)
    if (__builtin_expect(ex > 0.0f, 0)) g = ex / (a > 1e-6f ? a : 1e-6f);
    for (int k = 0; k < 3; ++k) {
        float cs = smp[k] > 0.0f ? smp[k] : 0.0f;
        cs = cs < m_s ? cs : m_s;
        const float ck = rgb.data[3 * p + k];
        out_rgb.data[3 * p + k] = w * cs + keep * ck + g * ck;
    }
}
return 0;
"""



#: ``coords``' loop over one row of the box (C++): the photo coordinates of its pixels and whether they have one.
_COORDS_ROW = r"""
const int y = y0 + by;
const double ry = ((double)y + 0.5 - rcy) / rfy;
double* U = u_out.data + (size_t)by * bw;
double* V = v_out.data + (size_t)by * bw;
unsigned char* OK = ok.data + (size_t)by * bw;
const float* E = ext.data + ((size_t)y * W + x0) * C;
const float* D = depth.data + (size_t)y * W + x0;
for (int bx = 0; bx < bw; ++bx) {
    const float S = E[(size_t)bx * C + C - 1];
    double uu = 0.0, vv = 0.0;
    bool good = S > 1.0e-6f;
    const double rx = ((double)(x0 + bx) + 0.5 - rcx) / rfx;
    if (good) {
        if (one != 0) {
            const double d = (double)D[bx];
            double X = A.data[0][0] * rx + A.data[0][1] * ry + A.data[0][2];
            double Y = A.data[1][0] * rx + A.data[1][1] * ry + A.data[1][2];
            double Z = A.data[2][0] * rx + A.data[2][1] * ry + A.data[2][2];
            X = d * X + b.c[0];
            Y = d * Y + b.c[1];
            Z = d * Z + b.c[2];
            if (Z > 1.0e-9) {
                uu = pfx * X / Z + pcx;
                vv = pfy * Y / Z + pcy;
            } else {
                good = false;
            }
        } else {
            const double sd = (double)S;
            uu = pfx * rx + pcx + (double)E[(size_t)bx * C] / sd;
            vv = pfy * ry + pcy + (double)E[(size_t)bx * C + 1] / sd;
        }
    }
    U[bx] = uu;
    V[bx] = vv;
    OK[bx] = good ? 1 : 0;
}
return 0;
"""

@built_once
def _build(wp):
    f64 = wp.float64

    @wp.func_native(_COORDS_ROW)
    def coords_row(ext: wp.array(dtype=float), C: int, depth: wp.array(dtype=float), W: int, x0: int, y0: int,
                   bw: int, by: int, one: int, A: wp.mat33d, b: wp.vec3d, rfx: f64, rfy: f64, rcx: f64, rcy: f64,
                   pfx: f64, pfy: f64, pcx: f64, pcy: f64, u_out: wp.array(dtype=f64), v_out: wp.array(dtype=f64),
                   ok: wp.array(dtype=wp.uint8)) -> int:
        ...

    @wp.kernel(enable_backward=False)
    def coords(ext: wp.array(dtype=float), C: int, depth: wp.array(dtype=float), W: int, x0: int, y0: int,
               bw: int, one: int, A: wp.mat33d, b: wp.vec3d, rfx: f64, rfy: f64, rcx: f64, rcy: f64,
               pfx: f64, pfy: f64, pcx: f64, pcy: f64, u_out: wp.array(dtype=f64),
               v_out: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8)):
        # One row of the box: each pixel's photo coordinate (pixel units, centres at +0.5) and whether it has one
        # (seen splats reach it, and under the one map its surface point lies in front of the photo's camera):
        # ``_COORDS_ROW``.
        coords_row(ext, C, depth, W, x0, y0, bw, wp.tid(), one, A, b, rfx, rfy, rcx, rcy, pfx, pfy, pcx, pcy, u_out,
                   v_out, ok)

    @wp.func_native(_STRETCH_ROW)
    def stretch_row(u: wp.array(dtype=f64), v: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8), bw: int,
                    bh: int, by: int, st0: f64, st1: f64, fade: wp.array(dtype=float)) -> int:
        ...

    @wp.kernel(enable_backward=False)
    def stretch(u: wp.array(dtype=f64), v: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8), bw: int, bh: int,
                st0: f64, st1: f64, fade: wp.array(dtype=float)):
        # One row of the box: the photo's weight left by the stretch of its coordinates (``_STRETCH_ROW``).
        stretch_row(u, v, ok, bw, bh, wp.tid(), st0, st1, fade)

    @wp.func_native(_BLEND_ROW)
    def blend_row(u: wp.array(dtype=f64), v: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8),
                  ext: wp.array(dtype=float), C: int, rgb: wp.array(dtype=float), alpha: wp.array(dtype=float),
                  dist: wp.array(dtype=float), W: int, x0: int, y0: int, bw: int, bh: int, by: int,
                  planes: wp.array(dtype=float), PW: int, PH: int, min_cov: float, in0: float, in1: float,
                  fade: wp.array(dtype=float), out_rgb: wp.array(dtype=float),
                  out_a: wp.array(dtype=float)) -> int:
        ...

    @wp.kernel(enable_backward=False)
    def blend(u: wp.array(dtype=f64), v: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8),
              ext: wp.array(dtype=float), C: int, rgb: wp.array(dtype=float), alpha: wp.array(dtype=float),
              dist: wp.array(dtype=float), W: int, x0: int, y0: int, bw: int, bh: int,
              planes: wp.array(dtype=float), PW: int, PH: int, min_cov: float, in0: float, in1: float,
              fade: wp.array(dtype=float), out_rgb: wp.array(dtype=float), out_a: wp.array(dtype=float)):
        # One row of the box: per pixel the photo's share (times ``fade``), the bicubic sample of (premultiplied
        # colour, matte) and the frame's colour and coverage (``_BLEND_ROW``).
        by = wp.tid()
        blend_row(u, v, ok, ext, C, rgb, alpha, dist, W, x0, y0, bw, bh, by, planes, PW, PH, min_cov, in0, in1,
                  fade, out_rgb, out_a)

    @wp.kernel(enable_backward=False)
    def shift_features(means: wp.array(dtype=wp.vec3d), R: wp.mat33d, t: wp.vec3d, pfx: f64, pfy: f64, pcx: f64,
                       pcy: f64, uv0: wp.array(dtype=wp.vec2d), seen: wp.array(dtype=f64),
                       out: wp.array(dtype=wp.vec3)):
        # One splat: its centre now in the render camera, the photo pixel its ray meets (the render camera is the
        # photo's, possibly resized), the shift from there to where the photo shows the centre at rest, times the
        # seen weight, and the weight (``photo_texture.texture_features``), in float64, stored in float32.
        i = wp.tid()
        p = R * means[i] + t
        z = wp.max(p[2], f64(1.0e-9))
        s = seen[i]
        q = uv0[i]
        out[i] = wp.vec3(float((q[0] - (pfx * (p[0] / z) + pcx)) * s), float((q[1] - (pfy * (p[1] / z) + pcy)) * s),
                         float(s))

    return wp, coords, stretch, blend, shift_features


def available() -> bool:
    """Whether the compiled passes can run (the compiled compositor's Warp, built once)."""
    from . import _warp_raster

    if not _warp_raster.available():
        return False
    try:
        _build()
        return True
    except Exception as exc:  # noqa: BLE001 - a failed build turns the compiled passes off, with a warning
        _warp_raster.mark_failed(exc)
        return False


def _arr(wp, t: torch.Tensor, dtype, keep: list):
    t = t.detach().contiguous()
    keep.append(t)
    return wp.array(t.numpy().reshape(-1) if dtype in (float, wp.float64, wp.uint8) else t.numpy(), dtype=dtype,
                    device="cpu", copy=False)


def planes_array(planes: np.ndarray):
    """The texture's (H,W,4) float32 planes as a flat Warp array (no copy)."""
    wp = _build()[0]
    return wp.array(planes.reshape(-1), dtype=float, device="cpu", copy=False)


def photo_coords(ext: torch.Tensor, depth: torch.Tensor, box: tuple, camera, photo_camera, one_map=None):
    """(u, v) float64 (bh*bw) and ok uint8 (bh*bw): the photo coordinates of the box's pixels (``coords``)."""
    wp, coords, _, _, _ = _build()
    y0, y1, x0, x1 = box
    bh, bw = y1 - y0, x1 - x0
    H, W, C = ext.shape
    keep: list = []
    u = torch.empty(bh * bw, dtype=torch.float64)
    v = torch.empty(bh * bw, dtype=torch.float64)
    ok = torch.empty(bh * bw, dtype=torch.uint8)
    if one_map is not None:
        A, b = one_map
        Aw = wp.mat33d(*[float(x) for x in A.reshape(-1).tolist()])
        bv = wp.vec3d(*[float(x) for x in b.tolist()])
    else:
        Aw, bv = wp.mat33d(), wp.vec3d()
    pc = photo_camera
    wp.launch(coords, dim=bh, device="cpu",
              inputs=[_arr(wp, ext, float, keep), C, _arr(wp, depth, float, keep), W, x0, y0, bw,
                      int(one_map is not None), Aw, bv, float(camera.fx), float(camera.fy), float(camera.cx),
                      float(camera.cy), float(pc.fx), float(pc.fy), float(pc.cx), float(pc.cy),
                      _arr(wp, u, wp.float64, keep), _arr(wp, v, wp.float64, keep), _arr(wp, ok, wp.uint8, keep)])
    wp.synchronize_device("cpu")
    return u, v, ok


def stretch_fade(u, v, ok, box, lo: float, hi: float) -> torch.Tensor:
    """(bh, bw) float32: the photo's weight left by the stretch of the box's photo coordinates (``_STRETCH_ROW``:
    1 up to a magnification of ``lo``, 0 from ``hi``, linear in it between; 1 where a pixel has no coordinate)."""
    wp, _, kernel, _, _ = _build()
    y0, y1, x0, x1 = box
    bh, bw = y1 - y0, x1 - x0
    keep: list = []
    fade = torch.empty(bh, bw, dtype=torch.float32)
    wp.launch(kernel, dim=bh, device="cpu",
              inputs=[_arr(wp, u, wp.float64, keep), _arr(wp, v, wp.float64, keep), _arr(wp, ok, wp.uint8, keep), bw,
                      bh, float(lo), float(hi), _arr(wp, fade, float, keep)])
    wp.synchronize_device("cpu")
    return fade


def blend(u, v, ok, fade, ext, rgb, alpha, dist, box, planes, planes_wp, consts, out_rgb, out_a) -> None:
    """The ``blend`` loop over the box, writing ``out_rgb`` (H,W,3) and ``out_a`` (H,W) there (contiguous)."""
    wp, _, _, kernel, _ = _build()
    y0, y1, x0, x1 = box
    bh, bw = y1 - y0, x1 - x0
    H, W, C = ext.shape
    keep: list = []
    PH, PW = planes.shape[:2]
    min_cov, in0, in1 = consts
    wp.launch(kernel, dim=bh, device="cpu",
              inputs=[_arr(wp, u, wp.float64, keep), _arr(wp, v, wp.float64, keep), _arr(wp, ok, wp.uint8, keep),
                      _arr(wp, ext, float, keep), C, _arr(wp, rgb, float, keep), _arr(wp, alpha, float, keep),
                      _arr(wp, dist, float, keep), W, x0, y0, bw, bh, planes_wp, PW, PH, float(min_cov), float(in0),
                      float(in1), _arr(wp, fade, float, keep)],
              outputs=[wp.array(out_rgb.numpy().reshape(-1), dtype=float, device="cpu", copy=False),
                       wp.array(out_a.numpy().reshape(-1), dtype=float, device="cpu", copy=False)])
    wp.synchronize_device("cpu")


def texture_shift_features(means: torch.Tensor, w2c: torch.Tensor, photo_camera, uv0: torch.Tensor,
                           seen: torch.Tensor) -> torch.Tensor:
    """(N, 3) float32: ``photo_texture.texture_features`` of the splats at ``means`` (N, 3) for a render camera
    ``w2c`` (4x4, OpenCV axes) that is ``photo_camera`` possibly resized: s·Δ and s, Δ = ``uv0`` (N, 2, the photo
    pixels of the centres at rest) minus the photo pixel of each centre's ray now; computed in float64 in one loop
    (``shift_features``) instead of a dozen whole-array tensor operations."""
    wp, _, _, _, kernel = _build()
    n = int(means.shape[0])
    out = torch.empty(n, 3, dtype=torch.float32)
    if n == 0:
        return out
    keep: list = []
    w = w2c.detach().double()
    R = wp.mat33d(*[float(x) for x in w[:3, :3].reshape(-1).tolist()])
    t = wp.vec3d(*[float(x) for x in w[:3, 3].tolist()])
    pc = photo_camera
    wp.launch(kernel, dim=n, device="cpu",
              inputs=[_arr(wp, means.detach().double(), wp.vec3d, keep), R, t, float(pc.fx), float(pc.fy), float(pc.cx),
                      float(pc.cy), _arr(wp, uv0.double(), wp.vec2d, keep), _arr(wp, seen.double(), wp.float64, keep),
                      _arr(wp, out, wp.vec3, keep)])
    wp.synchronize_device("cpu")
    return out
