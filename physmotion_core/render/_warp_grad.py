"""Differentiable Gaussian-splat rendering compiled with Warp, for the CPU renders of the photo fit
(``lift/fit.py``), which need gradients w.r.t. the object's pose, size and the focal.

The tensor path (``_torch_raster``) places and projects every splat through some forty autograd nodes and
composites dense [tiles, splats, pixels] blocks, with about thirty whole-block passes per chunk in its backward
pass (``_BlendChunk``); on the fit's small, deep renders that was most of a refinement step. Here:

* ``project_affine``: splats X with covariances C under one affine map into the camera, x -> A x + b
  (covariance A C Aᵀ), which is what the fit's placement is. One compiled loop culls, projects and keys the
  splats with ``project_gaussians``' arithmetic (``screen``); the gradient w.r.t. A and b (12 numbers) is
  Warp's generated adjoint of the same formulas (``project_diff``), summed over the drawn splats;
* ``tile_lists_warp``: each 4x4-px tile's depth-ordered list of the splats whose ellipse at the lowest alpha
  evaluated reaches one of its pixel centres (an exact ellipse-rectangle test, once per box tile, compiled),
  then a serial fill in depth order (no sort);
* ``composite``: two C++ loops over a tile (Warp native functions, the tile's pixels the inner loop, which the
  compiler vectorises). Forward: the tile's list front to back; entries with alpha <= 1/255 skipped; every
  pixel stops at the splat that would bring its transmittance to ``T_DONE`` or below (exclusive, the rule of
  ``composite_tiles``), and keeps its final transmittance and how far along the list it counted. Backward:
  the list from there back to the front, the transmittance before each splat recovered by division
  (T_{k-1} = T_k / (1 - alpha_k), as 3DGS's backward kernel does), with the running sum S of the later
  splats' contributions, so that

      dL/dalpha_k = T_{k-1} v_k - S_k / (1 - alpha_k),   v_k = f_k · dL/dF + dL/dA,  S_k = Σ_{j>k} w_j v_j,

  chained to the exponent (d alpha / d power = alpha below the 0.99 clamp, 0 at it) and on to the 2D mean,
  the conic and the log-opacity; dL/df_k = w_k dL/dF. Each splat's gradients are summed over the tile's
  pixels, then added to its totals (a serial loop on the CPU, so plain adds).

Image-formation model, culling and termination are those of ``project_gaussians`` and ``composite_tiles``:
alpha = min(0.99, o exp(-½ dᵀ conic d)) at the pixel centre (x + 0.5, y + 0.5), w_k = alpha_k T_{k-1}.
Computed in float32 (a polynomial exp within a float32 ulp), so values and gradients differ from the float64
tensor path by float32 round-off, and where round-off moves an entry across the 1/255 threshold or a pixel
across the termination test.

Inputs that are not CPU float32 take the tensor path; when Warp cannot be imported or built (or a launch
fails) this module is off for the rest of the process, with one warning, and the tensor path renders.
"""

# No "from __future__ import annotations": Warp reads the kernels' annotations, which name the local `wp`.

import dataclasses
import logging
import math
from typing import Optional

import torch

from ..errors import InputError
from ..warp_build import built_once
from ._torch_raster import ALPHA_MAX, ALPHA_MIN, T_DONE, Projected, check_intersections, composite_tiles
from ._warp_raster import EXPO, drawn, projection_funcs, projection_outputs, screen_bounds

log = logging.getLogger(__name__)

#: Tile side (px) of the lists the pixels walk, compiled into the loops when they are first built (changing it
#: later in a process has no effect on them). Every pixel of a tile walks the tile's whole list: smaller tiles mean
#: shorter walks but more (splat, tile) entries. The fit's splats are a few pixels across; measured on the bread
#: lift's 12 610 splats at 160x100 (one core, CPU time per launch): 8 px: forward 2.2 ms, backward 7.1 ms;
#: 4 px: 1.2 ms and 3.1 ms (2.3x fewer (splat, pixel) evaluations for 1.7x more entries).
TILE = 4

#: Most features per splat the compiled path composites (the fit's: colour and depth, 4); more go to
#: ``composite_tiles``.
MAX_FEATURES = 8

_failed = False

# Shared by the two C++ loops below (Warp native functions, compiled by Warp's clang with -O2 -march=native). A
# tile's pixels are the inner loop, written without branches (selects) and with an inlined polynomial exp so
# that the compiler vectorises it; sums over the pixels are kept in LANES partial sums (a float reduction is not
# vectorised without reassociation, which the compiler may not do on its own). exp: Cephes' single-precision
# range reduction and degree-7 polynomial (``_warp_raster.EXPO``, within a float32 ulp over the range used,
# [ln(1/255), 0]); the forward and backward loops evaluate it identically, so they make the same skip and
# termination decisions.
_COMMON = EXPO + r"""
constexpr int TS = TILE_SIDE, P = TS * TS, LANES = 16, CMAX = MAX_FEATURES;
const int bx = (tile % TX) * TS, by = (tile / TX) * TS;
const int s0 = start.data[tile], cnt = count.data[tile];
float px[P], py[P];
int inside[P];
for (int j = 0; j < P; ++j) {
    int x = bx + (j % TS), y = by + (j / TS);
    px[j] = (float)x + 0.5f;
    py[j] = (float)y + 0.5f;
    inside[j] = (x < W) & (y < H);
}
"""

_FORWARD = _COMMON + r"""
float T[P], wb[P], acc[CMAX + 1][P];
int alive[P], lst[P];
int nalive = 0;
for (int j = 0; j < P; ++j) {
    T[j] = 1.0f;
    alive[j] = inside[j];
    lst[j] = 0;
    nalive += inside[j];
}
for (int c = 0; c <= C; ++c)
    for (int j = 0; j < P; ++j)
        acc[c][j] = 0.0f;
for (int k = 0; k < cnt && nalive > 0; ++k) {
    const float* r = table.data + (size_t)glist.data[s0 + k] * D;
    const float u = r[0], v = r[1], A = r[2], B = r[3], Cc = r[4], lo = r[5];
    int n = 0, any = 0;
    for (int j = 0; j < P; ++j) {
        float dx = u - px[j], dy = v - py[j];
        float pw = lo - (A * dx * dx + B * dx * dy + Cc * dy * dy);
        float al = expo(pw);
        al = al > ALPHA_MAX ? ALPHA_MAX : al;
        int use = (pw > POWER_MIN) & (al > ALPHA_MIN) & alive[j];
        float t = T[j];
        float tn = t * (1.0f - al);
        int die = use & (tn <= T_DONE);
        int keep = use & (die ^ 1);
        wb[j] = keep ? al * t : 0.0f;
        T[j] = keep ? tn : t;
        alive[j] = die ? 0 : alive[j];
        lst[j] = keep ? k + 1 : lst[j];
        n += alive[j];
        any |= keep;
    }
    nalive = n;
    if (any) {
        for (int c = 0; c < C; ++c) {
            const float f = r[6 + c];
            for (int j = 0; j < P; ++j)
                acc[c][j] += wb[j] * f;
        }
        for (int j = 0; j < P; ++j)
            acc[C][j] += wb[j];
    }
}
for (int j = 0; j < P; ++j) {
    if (!inside[j])
        continue;
    size_t p = (size_t)(by + (j / TS)) * W + bx + (j % TS);
    for (int c = 0; c <= C; ++c)
        out.data[p * (C + 1) + c] = acc[c][j];
    tfin.data[p] = T[j];
    last.data[p] = lst[j];
}
return 0;
"""

_BACKWARD = _COMMON + r"""
float T[P], S[P], vb[P], wb[P], g[CMAX + 1][P];
int lst[P];
int kmax = 0;
for (int j = 0; j < P; ++j) {
    size_t p = inside[j] ? (size_t)(by + (j / TS)) * W + bx + (j % TS) : 0;
    T[j] = inside[j] ? tfin.data[p] : 1.0f;
    lst[j] = inside[j] ? last.data[p] : 0;
    S[j] = 0.0f;
    for (int c = 0; c <= C; ++c)
        g[c][j] = inside[j] ? gout.data[p * (C + 1) + c] : 0.0f;
    kmax = lst[j] > kmax ? lst[j] : kmax;
}
auto total = [](const float* part) -> float {  // LANES partial sums, added as a tree
    float h[LANES];
    for (int l = 0; l < LANES; ++l)
        h[l] = part[l];
    for (int n = LANES / 2; n > 0; n /= 2)
        for (int l = 0; l < n; ++l)
            h[l] += h[l + n];
    return h[0];
};
for (int k = kmax - 1; k >= 0; --k) {
    const int m = glist.data[s0 + k];
    const float* r = table.data + (size_t)m * D;
    const float u = r[0], v = r[1], A = r[2], B = r[3], Cc = r[4], lo = r[5];
    const float A2 = 2.0f * A, C2 = 2.0f * Cc;
    for (int j = 0; j < P; ++j)
        vb[j] = g[C][j];
    for (int c = 0; c < C; ++c) {
        const float f = r[6 + c];
        for (int j = 0; j < P; ++j)
            vb[j] += f * g[c][j];
    }
    // Sums over the pixels in LANES partial sums (the inner loop is what the compiler vectorises).
    float s0[LANES], s1[LANES], s2[LANES], s3[LANES], s4[LANES], s5[LANES];
    int any[LANES];
    for (int l = 0; l < LANES; ++l) {
        s0[l] = s1[l] = s2[l] = s3[l] = s4[l] = s5[l] = 0.0f;
        any[l] = 0;
    }
    for (int jb = 0; jb < P; jb += LANES) {
        for (int l = 0; l < LANES; ++l) {
            const int j = jb + l;
            float dx = u - px[j], dy = v - py[j];
            float pw = lo - (A * dx * dx + B * dx * dy + Cc * dy * dy);
            float raw = expo(pw);
            float al = raw > ALPHA_MAX ? ALPHA_MAX : raw;
            int use = (pw > POWER_MIN) & (al > ALPHA_MIN) & (k < lst[j]);
            float iq = 1.0f / (1.0f - al);
            float t = T[j];
            float tb = t * iq;  // T before this splat
            float w = al * tb;
            float vv = vb[j];
            float da = tb * vv - S[j] * iq;  // dL/dalpha
            S[j] = use ? S[j] + w * vv : S[j];
            T[j] = use ? tb : t;
            float gp = (use & (raw < ALPHA_MAX)) ? da * al : 0.0f;  // dL/dpower (0 where alpha is clamped)
            wb[j] = use ? w : 0.0f;
            s0[l] += gp;
            s1[l] -= gp * (A2 * dx + B * dy);
            s2[l] -= gp * (B * dx + C2 * dy);
            s3[l] -= gp * dx * dx;
            s4[l] -= gp * dx * dy;
            s5[l] -= gp * dy * dy;
            any[l] |= use;
        }
    }
    int used = 0;
    for (int l = 0; l < LANES; ++l)
        used |= any[l];
    if (!used)
        continue;
    float* gr = gtable.data + (size_t)m * D;
    gr[0] += total(s1);
    gr[1] += total(s2);
    gr[2] += total(s3);
    gr[3] += total(s4);
    gr[4] += total(s5);
    gr[5] += total(s0);
    for (int c = 0; c < C; ++c) {
        for (int l = 0; l < LANES; ++l)
            s0[l] = 0.0f;
        for (int jb = 0; jb < P; jb += LANES)
            for (int l = 0; l < LANES; ++l)
                s0[l] += wb[jb + l] * g[c][jb + l];
        gr[6 + c] += total(s0);
    }
}
return 0;
"""


def _f32(x: float) -> str:
    """A C++ float literal of the float32 nearest to ``x``."""
    import numpy as np

    return f"{float(np.float32(x))!r}f"


def _source(code: str) -> str:
    # Below POWER_MIN alpha is under 1/255 for any rounding of the exponential (a margin of 1e-4 on ln(1/255)).
    for name, value in (("ALPHA_MAX", _f32(ALPHA_MAX)), ("ALPHA_MIN", _f32(ALPHA_MIN)), ("T_DONE", _f32(T_DONE)),
                        ("POWER_MIN", _f32(math.log(ALPHA_MIN) - 1e-4)), ("MAX_FEATURES", str(MAX_FEATURES)),
                        ("TILE_SIDE", str(TILE))):
        code = code.replace(name, value)
    return code


@built_once
def _build(wp):
    TILE_ = wp.constant(TILE)

    # Below this exponent no pixel is evaluated (POWER_MIN), plus a relative margin far above float32 round-off.
    R2_LOG255 = wp.constant(math.log(255.0) + 1e-4)

    @wp.func
    def reaches(a: float, b: float, c: float, ia: float, ic: float, r2: float, X0: float, X1: float, Y0: float,
                Y1: float):
        # Whether the ellipse q = a dx² + 2 b dx dy + c dy² <= r2 holds a point of the rectangle
        # [X0, X1] x [Y0, Y1] (a tile's pixel centres, relative to the splat's centre): the minimum of the
        # convex q over the rectangle is 0 when the centre is inside, else on an edge, where q is a parabola
        # whose minimiser is clamped to the edge. ia, ic: 1 / a, 1 / c.
        if X0 <= 0.0 and X1 >= 0.0 and Y0 <= 0.0 and Y1 >= 0.0:
            return True
        best = float(1.0e30)
        for e in range(2):
            Y = Y0
            X = X0
            if e == 1:
                Y = Y1
                X = X1
            dx = wp.clamp(-b * Y * ia, X0, X1)
            best = wp.min(best, a * dx * dx + 2.0 * b * dx * Y + c * Y * Y)
            dy = wp.clamp(-b * X * ic, Y0, Y1)
            best = wp.min(best, a * X * X + 2.0 * b * X * dy + c * dy * dy)
        return best <= r2

    @wp.kernel(enable_backward=False)
    def tile_hits(uv: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), logo: wp.array(dtype=float),
                  lo: wp.array(dtype=wp.vec2i), hi: wp.array(dtype=wp.vec2i), offset: wp.array(dtype=wp.int32),
                  TX: int, W: int, H: int, per_tile: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.int32)):
        # Splat m's box tiles, in order from offset[m]: the tile's index when the splat's ellipse at the lowest
        # alpha the loops evaluate (exponent ln(1/255) - 1e-4, plus a relative margin far above float32
        # round-off) reaches one of its pixel centres, else -1; per_tile counts them.
        m = wp.tid()
        u = uv[m][0]
        v = uv[m][1]
        cn = conic[m]
        r2 = 2.0 * (logo[m] + R2_LOG255) * 1.001 + 1.0e-3
        ia = 1.0 / cn[0]
        ic = 1.0 / cn[2]
        k = offset[m]
        for ty in range(lo[m][1] / TILE_, hi[m][1] / TILE_ + 1):
            Y0 = float(ty * TILE_) + 0.5 - v
            Y1 = float(wp.min(ty * TILE_ + TILE_, H) - 1) + 0.5 - v
            for tx in range(lo[m][0] / TILE_, hi[m][0] / TILE_ + 1):
                X0 = float(tx * TILE_) + 0.5 - u
                X1 = float(wp.min(tx * TILE_ + TILE_, W) - 1) + 0.5 - u
                t = int(-1)
                if r2 > 0.0 and reaches(cn[0], cn[1], cn[2], ia, ic, r2, X0, X1, Y0, Y1):
                    t = ty * TX + tx
                    wp.atomic_add(per_tile, t, 1)
                hits[k] = t
                k += 1

    @wp.kernel(enable_backward=False)
    def fill_tiles(offset: wp.array(dtype=wp.int32), hits: wp.array(dtype=wp.int32), M: int,
                   cursor: wp.array(dtype=wp.int32), glist: wp.array(dtype=wp.int32)):
        # One thread, the splats in depth order: each tile's list comes out front to back.
        for m in range(M):
            for k in range(offset[m], offset[m + 1]):
                t = hits[k]
                if t >= 0:
                    glist[cursor[t]] = m
                    cursor[t] = cursor[t] + 1

    @wp.func_native(_source(_FORWARD))
    def tile_forward(start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                     glist: wp.array(dtype=wp.int32), table: wp.array(dtype=float), D: int, C: int, TX: int,
                     W: int, H: int, tile: int, out: wp.array(dtype=float), tfin: wp.array(dtype=float),
                     last: wp.array(dtype=wp.int32)) -> int:
        ...

    @wp.func_native(_source(_BACKWARD))
    def tile_backward(start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                      glist: wp.array(dtype=wp.int32), table: wp.array(dtype=float), D: int, C: int, TX: int,
                      W: int, H: int, tile: int, tfin: wp.array(dtype=float), last: wp.array(dtype=wp.int32),
                      gout: wp.array(dtype=float), gtable: wp.array(dtype=float)) -> int:
        ...

    @wp.kernel(enable_backward=False)
    def forward(start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                glist: wp.array(dtype=wp.int32), table: wp.array(dtype=float), D: int, C: int, TX: int, W: int,
                H: int, out: wp.array(dtype=float), tfin: wp.array(dtype=float),
                last: wp.array(dtype=wp.int32)):
        tile_forward(start, count, glist, table, D, C, TX, W, H, wp.tid(), out, tfin, last)

    @wp.kernel(enable_backward=False)
    def backward(start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                 glist: wp.array(dtype=wp.int32), table: wp.array(dtype=float), D: int, C: int, TX: int,
                 W: int, H: int, tfin: wp.array(dtype=float), last: wp.array(dtype=wp.int32),
                 gout: wp.array(dtype=float), gtable: wp.array(dtype=float)):
        tile_backward(start, count, glist, table, D, C, TX, W, H, wp.tid(), tfin, last, gout, gtable)

    ALPHA_MIN_ = wp.constant(ALPHA_MIN)
    INF = wp.constant(math.inf)
    ewa, store = projection_funcs()  # _warp_raster's: project_gaussians' projection, culling and box

    @wp.func
    def screen(X: wp.vec3, C: wp.mat33, A: wp.mat33, b: wp.vec3, fx: float, fy: float, cx: float, cy: float,
               lim: wp.vec4, eps2d: float):
        # The splat at A X + b (camera space) with covariance A C Aᵀ, projected: (u, v, a, b, c, z).
        return ewa(A * X + b, A, C, fx, fy, cx, cy, lim, eps2d)

    @wp.kernel(enable_backward=False)
    def project_fwd(X: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33), opac: wp.array(dtype=float),
                    Ab: wp.array(dtype=wp.mat33), bb: wp.array(dtype=wp.vec3), fx: float, fy: float, cx: float,
                    cy: float, W: int, H: int, near: float, far: float, eps2d: float, lim: wp.vec4, big: float,
                    key: wp.array(dtype=float), uv: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3),
                    logo: wp.array(dtype=float), lo: wp.array(dtype=wp.vec2i), hi: wp.array(dtype=wp.vec2i)):
        # One splat, culled as project_gaussians culls: key = its z when drawn, +inf when culled (behind
        # near, past far, opacity < 1/255, a degenerate or non-finite projection, a box holding no pixel centre).
        i = wp.tid()
        key[i] = INF
        o = opac[i]
        q = screen(X[i], C[i], Ab[0], bb[0], fx, fy, cx, cy, lim, eps2d)
        z = q[5]
        if not (z > near and z < far and o >= ALPHA_MIN_):
            return
        store(i, z, o, q[0], q[1], q[2], q[3], q[4], W, H, big, key, uv, conic, logo, lo, hi)

    @wp.kernel
    def project_diff(X: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33), idx: wp.array(dtype=wp.int32),
                     Ab: wp.array(dtype=wp.mat33), bb: wp.array(dtype=wp.vec3), fx: float, fy: float, cx: float,
                     cy: float, lim: wp.vec4, eps2d: float, uv: wp.array(dtype=wp.vec2),
                     conic: wp.array(dtype=wp.vec3)):
        # The drawn splat k's (input idx[k]) 2D mean and conic, as project_fwd computes them. Only its adjoint
        # (generated by Warp) is launched, for the gradients w.r.t. the shared A and b (summed over the splats).
        k = wp.tid()
        i = idx[k]
        q = screen(X[i], C[i], Ab[0], bb[0], fx, fy, cx, cy, lim, eps2d)
        inv = 1.0 / (q[2] * q[4] - q[3] * q[3])
        uv[k] = wp.vec2(q[0], q[1])
        conic[k] = wp.vec3(q[4] * inv, -q[3] * inv, q[2] * inv)

    return (wp, forward, backward, tile_hits, fill_tiles, project_fwd, project_diff)


def available() -> bool:
    """Whether Warp imports and the kernels build (a broken install falls back to ``composite_tiles``, and is
    not tried again)."""
    if _failed:
        return False
    try:
        _build()
        return True
    except Exception as exc:  # noqa: BLE001 - ImportError, or a Warp that cannot initialise or compile
        mark_failed(exc)
        return False


def mark_failed(exc: BaseException) -> None:
    """Turn this path off for the rest of the process, with one warning."""
    global _failed
    if not _failed:
        log.warning("The compiled differentiable compositing failed (%s: %s); renders with gradients use the "
                    "PyTorch compositing for the rest of this session.", type(exc).__name__, exc)
    _failed = True


def _wp(wp, t: torch.Tensor, dtype):
    return wp.array(t.numpy(), dtype=dtype, device="cpu", copy=False)


class _Composite(torch.autograd.Function):
    """table (M, 6 + C) of (u, v, A, B, C, log o, features...) per splat, with the exponent
    log o - (A dx² + B dx dy + C dy²) -> (H, W, C + 1) image (Σ w f, then Σ w); see the module doc."""

    @staticmethod
    def forward(ctx, table, lists, width, height):
        wp, fwd = _build()[:2]
        glist, start, count = lists
        M, D = table.shape
        C = D - 6
        TX = -(-width // TILE)
        tab = table.detach().contiguous()
        out = torch.zeros(height * width, C + 1, dtype=torch.float32)
        tfin = torch.empty(height * width, dtype=torch.float32)
        last = torch.empty(height * width, dtype=torch.int32)
        n_tiles = int(start.numel())
        if n_tiles:
            wp.launch(fwd, dim=n_tiles, device="cpu",
                      inputs=[_wp(wp, start, wp.int32), _wp(wp, count, wp.int32), _wp(wp, glist, wp.int32),
                              _wp(wp, tab.view(-1), float), int(D), int(C), int(TX), int(width), int(height),
                              _wp(wp, out.view(-1), float), _wp(wp, tfin, float), _wp(wp, last, wp.int32)])
            wp.synchronize_device("cpu")
        ctx.save_for_backward(tab, glist, start, count, tfin, last)
        ctx.dims = (int(width), int(height), int(TX))
        return out.view(height, width, C + 1)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_img):
        wp, bwd = _build()[0], _build()[2]
        tab, glist, start, count, tfin, last = ctx.saved_tensors
        width, height, TX = ctx.dims
        M, D = tab.shape
        C = D - 6
        g_out = g_img.detach().to(torch.float32).contiguous().view(-1)
        g_tab = torch.zeros(M, D, dtype=torch.float32)
        n_tiles = int(start.numel())
        if n_tiles:
            wp.launch(bwd, dim=n_tiles, device="cpu",
                      inputs=[_wp(wp, start, wp.int32), _wp(wp, count, wp.int32), _wp(wp, glist, wp.int32),
                              _wp(wp, tab.view(-1), float), int(D), int(C), int(TX), int(width), int(height),
                              _wp(wp, tfin, float), _wp(wp, last, wp.int32), _wp(wp, g_out, float),
                              _wp(wp, g_tab.view(-1), float)])
            wp.synchronize_device("cpu")
        return g_tab, None, None, None


def tile_lists_warp(proj: Projected, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each ``TILE`` px tile's depth-ordered list of the splats whose ellipse at the lowest alpha the loops
    evaluate (exponent ln(1/255) - 1e-4, plus a margin) reaches one of its pixel centres, compiled (one test per
    box tile, then a serial fill in depth order): (glist, start, count), int32, tile t's list being
    ``glist[start[t]:start[t] + count[t]]``. The same job as
    ``_torch_raster.tile_lists`` (whose lists are a superset: its test is per tile row) without its dozens
    of whole-array passes, float64 arithmetic and sort."""
    wp, _, _, tile_hits, fill_tiles = _build()[:5]
    M = int(proj.uv.shape[0])
    TX, TY = -(-width // TILE), -(-height // TILE)
    with torch.no_grad():
        check_intersections(proj, TILE, width, height)
        f32 = torch.float32
        uv = _wp(wp, proj.uv.detach().to(f32).contiguous(), wp.vec2)
        conic = _wp(wp, proj.conic.detach().to(f32).contiguous(), wp.vec3)
        logo = _wp(wp, proj.log_opacity.detach().to(f32).contiguous(), float)
        lo_t = proj.pix_lo.to(torch.int32).contiguous()
        hi_t = proj.pix_hi.to(torch.int32).contiguous()
        box = (torch.div(hi_t, TILE, rounding_mode="floor") - torch.div(lo_t, TILE, rounding_mode="floor") + 1).prod(1)
        offset = torch.zeros(M + 1, dtype=torch.int32)
        torch.cumsum(box, 0, dtype=torch.int32, out=offset[1:])
        hits = torch.empty(max(int(offset[-1]), 1), dtype=torch.int32)
        count = torch.zeros(TX * TY, dtype=torch.int32)
        wp.launch(tile_hits, dim=M, device="cpu",
                  inputs=[uv, conic, logo, _wp(wp, lo_t, wp.vec2i), _wp(wp, hi_t, wp.vec2i), _wp(wp, offset, wp.int32),
                          TX, width, height, _wp(wp, count, wp.int32), _wp(wp, hits, wp.int32)])
        start = (torch.cumsum(count, 0, dtype=torch.int32) - count).contiguous()
        glist = torch.empty(max(int(count.sum()), 1), dtype=torch.int32)
        cursor = start.clone()
        wp.launch(fill_tiles, dim=1, device="cpu", inputs=[_wp(wp, offset, wp.int32), _wp(wp, hits, wp.int32), M,
                                                            _wp(wp, cursor, wp.int32), _wp(wp, glist, wp.int32)])
        wp.synchronize_device("cpu")
    return glist, start, count


class _Project(torch.autograd.Function):
    """(A (3, 3), b (3,)) -> the drawn splats' 2D means (K, 2) and conics (K, 3), in ``order``, for splats X
    (N, 3) with covariances C (N, 3, 3) placed at A X + b with covariance A C Aᵀ. Forward: the values
    ``project_affine`` computed; backward: the adjoint of ``project_diff``."""

    @staticmethod
    def forward(ctx, A, b, uv, conic, state):
        ctx.state = state
        ctx.save_for_backward(A.detach().to(torch.float32).contiguous(), b.detach().to(torch.float32).contiguous())
        return uv.clone(), conic.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_uv, g_conic):
        built = _build()
        wp, project_diff = built[0], built[6]
        A, b = ctx.saved_tensors
        X, C, idx, consts = ctx.state
        f32 = torch.float32
        K = int(idx.numel())
        g_A = torch.zeros(1, 3, 3, dtype=f32)
        g_b = torch.zeros(1, 3, dtype=f32)
        if K:
            g_uv = (torch.zeros(K, 2, dtype=f32) if g_uv is None else g_uv.to(f32)).contiguous()
            g_conic = (torch.zeros(K, 3, dtype=f32) if g_conic is None else g_conic.to(f32)).contiguous()
            ins = [_wp(wp, X, wp.vec3), _wp(wp, C, wp.mat33), _wp(wp, idx, wp.int32),
                   _wp(wp, A.view(1, 3, 3), wp.mat33), _wp(wp, b.view(1, 3), wp.vec3), *consts]
            outs = [_wp(wp, torch.empty(K, 2, dtype=f32), wp.vec2), _wp(wp, torch.empty(K, 3, dtype=f32), wp.vec3)]
            adj_ins = [None, None, None, _wp(wp, g_A, wp.mat33), _wp(wp, g_b, wp.vec3), 0.0, 0.0, 0.0, 0.0,
                       wp.vec4(), 0.0]
            adj_outs = [_wp(wp, g_uv, wp.vec2), _wp(wp, g_conic, wp.vec3)]
            wp.launch(project_diff, dim=K, inputs=ins, outputs=outs, adj_inputs=adj_ins, adj_outputs=adj_outs,
                      adjoint=True, device="cpu")
            wp.synchronize_device("cpu")
        return g_A[0], g_b[0], None, None, None


def project_affine(X: torch.Tensor, C: torch.Tensor, opacities: torch.Tensor, A: torch.Tensor, b: torch.Tensor, *,
                   fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
                   eps2d: float) -> Optional[Projected]:
    """``project_gaussians`` of splats X (N, 3) with covariances C (N, 3, 3) under one affine map into OpenCV
    camera space, x -> A x + b (covariance A C Aᵀ), with gradients w.r.t. A (3, 3) and b (3,) only (the fit's
    case: the splats are fixed, the pose and scale are fitted), compiled: one loop culls and projects (the
    same culling, formulas and front-to-back order as ``project_gaussians``, in float32) and Warp's adjoint
    of the same formulas sums the gradient over the drawn splats, where the tensor path would place every
    splat (N 3x3 products) and go through some forty autograd nodes over all of them. None when Warp is
    not available (the caller then takes the tensor path)."""
    if not available():
        return None
    built = _build()
    wp, project_fwd = built[0], built[5]
    f32 = torch.float32
    N = int(X.shape[0])
    Xc = X.detach().to(f32).contiguous()
    Cc = C.detach().to(f32).contiguous()
    with torch.no_grad():
        A_ = A.detach().to(f32).contiguous().view(1, 3, 3)
        b_ = b.detach().to(f32).contiguous().view(1, 3)
        outs = projection_outputs(N)
        key, uv, conic, logo, lo, hi = outs
        lim, big = screen_bounds(wp, fx, fy, cx, cy, width, height)
        consts = [float(fx), float(fy), float(cx), float(cy), lim, float(eps2d)]
        if N:
            wp.launch(project_fwd, dim=N, device="cpu",
                      inputs=[_wp(wp, Xc, wp.vec3), _wp(wp, Cc, wp.mat33),
                              _wp(wp, opacities.detach().to(f32).contiguous(), float),
                              _wp(wp, A_, wp.mat33), _wp(wp, b_, wp.vec3), float(fx), float(fy), float(cx), float(cy),
                              int(width), int(height), float(near), float(far), float(eps2d), lim, big,
                              _wp(wp, key, float), _wp(wp, uv, wp.vec2), _wp(wp, conic, wp.vec3),
                              _wp(wp, logo, float), _wp(wp, lo, wp.vec2i), _wp(wp, hi, wp.vec2i)])
            wp.synchronize_device("cpu")
        proj = drawn(*outs)
    if A.requires_grad or b.requires_grad:
        uv_k, conic_k = _Project.apply(A, b, proj.uv, proj.conic, (Xc, Cc, proj.index.to(torch.int32), consts))
        proj = dataclasses.replace(proj, uv=uv_k, conic=conic_k)
    return proj


def usable(*tensors: torch.Tensor) -> bool:
    """Whether this path takes these inputs: CPU float32 tensors and Warp available (float64 keeps the exact
    tensor path)."""
    if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in tensors):
        return False
    return available()


def composite(proj: Projected, features: torch.Tensor, width: int, height: int, *, cull: bool = True,
              fallback: Optional[dict] = None) -> torch.Tensor:
    """``composite_tiles`` with gradients, compiled: (H, W, C + 1), the composited features Σ f w then alpha Σ w,
    of the projected splats ``proj`` (front to back) with features (M, C) in the same order, differentiable
    w.r.t. ``proj.uv``, ``proj.conic``, ``proj.log_opacity`` and ``features``. Inputs that are not CPU float32,
    more than ``MAX_FEATURES`` features, or no working Warp go to ``composite_tiles`` (with ``cull`` and
    ``fallback`` as its tiling options; the compiled path's lists are always culled to the splats' ellipses)."""
    ins = (proj.uv, proj.conic, proj.log_opacity, features)
    if features.shape[1] <= MAX_FEATURES and usable(*ins):
        try:
            M = int(features.shape[0])
            if M == 0:
                return features.new_zeros(height, width, features.shape[1] + 1) + features.sum() * 0
            glist, start, count = tile_lists_warp(proj, int(width), int(height))
            c = proj.conic
            table = torch.cat([proj.uv, 0.5 * c[:, :1], c[:, 1:2], 0.5 * c[:, 2:], proj.log_opacity[:, None],
                               features], 1)
            return _Composite.apply(table, (glist, start, count), int(width), int(height))
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of the compiled path falls back
            mark_failed(exc)
    return composite_tiles(proj, features, width, height, cull=cull, **(fallback or {}))


__all__ = ["MAX_FEATURES", "TILE", "available", "composite", "project_affine", "usable"]
