"""Forward-only Gaussian-splat projection and compositing compiled with Warp, for CPU renders that need no
gradients.

The PyTorch rasterizer (``_torch_raster``) composites dense blocks [tiles, splats, pixels] with tensor
operations: every (splat, pixel) entry of a tile's list goes through a GEMM, exp2, threshold, clamp, a running
product and a batched matmul, each a pass over memory, for all 64 pixels of the tile, and a frame takes dozens
of such steps. Without gradients none of those intermediates is needed: here a compiled loop walks each tile's
depth-ordered list once, and each splat visits only the pixels of the tile that its box at alpha = 1/255 holds,
row by row (a box wider than 16 px: only each row's span of the ellipse, plus a margin); every pixel keeps its own
transmittance and stops at its own saturation, and the tile stops once all its pixels have. On the CPU templates'
thin, faint shells (about 27 splats contribute to each pixel, which rarely saturates) that visits a fraction of the
(splat, pixel) pairs the tensor tiles evaluate. A splat's box on a row (at most 16 px: one or two vectors, the same
count on every row) costs less than the row's span: the span's square root and divisions, and a varying count of
vectors per row, cost more than the pixels off the ellipse (0.88x the compositing time on five CPU templates,
measured 2026-12-06). The loop over one row's pixels (``_ROW``) is C++ in explicit 8-float vectors (an inlined
polynomial exp, no branches): the same loop in Warp's kernel language runs one pixel at a time with expf a library
call, and compositing took 1.3-1.7x longer (the CPU templates' Wan clips, one core, measured 2026-12-03); left to
the compiler's own vectorisation, the rows' short spans (5-8 pixels on the CPU templates) mostly ran its scalar
remainder loop, and compositing took 1.5x longer (1.3-1.9x per frame) than in explicit vectors (measured
2026-12-06).

Same image-formation model and the same inputs as ``composite_tiles``: the projection, culling and depth
order of ``project_gaussians``, alpha = min(0.99, o exp(-½ dᵀ conic d)) at the pixel centre, entries with
alpha <= 1/255 skipped, w_k = alpha_k T_{k-1}, and the splat that would bring T to ``T_DONE`` or below is not
counted, nor any after it. A tile lists the splats whose ellipse at alpha = 1/255 (plus a margin) reaches one
of its pixel centres, so no entry that could count is left out. The values differ from the PyTorch path only
by the order of float32 operations (exp instead of exp2 of a tile-local expansion, sums in list order instead
of per chunk, a polynomial exp within a float32 ulp of the exact one), so by round-off, and where round-off
moves an entry across the 1/255 threshold or a pixel across the termination test (single pixels, by at most
about 1/255 of a colour).

The projection (``project_warp``: culling, EWA covariance, conic, pixel box, key for the depth sort) is compiled
too, one loop over the splats with ``project_gaussians``' arithmetic, so the same splats come out in the same
order with the same boxes; its conics differ by float32 round-off.

The tile lists are built in one serial loop over the splats in depth order (so each tile's list comes out in
depth order with no sort). That loop is serial by construction, so this path is for the CPU: on CUDA, gsplat
does this job.
"""

# No "from __future__ import annotations": Warp reads the kernels' annotations, which name the local `wp`.

import math
from typing import Optional

import torch

from ..errors import InputError
from ..warp_build import built_once
from ._torch_raster import (ALPHA_MAX, ALPHA_MIN, MAX_EXTENT, MAX_INTERSECTIONS, T_DONE, Projected,
                            check_intersections)

#: Pixel side of a tile for a whole frame. Larger tiles than ``composite_tiles``' 8: a pixel only visits the splats
#: whose ellipse holds it (row spans, below), so a larger tile costs no more per pixel, lists each splat in fewer
#: tiles and gives ``row`` longer spans to vectorise. Measured on the CPU templates' Wan clips (832x480, one core,
#: compositing alone): 16 px 10-25 % slower than 32, 64 px 2-10 % faster than 32, and 96-256 px within a few % of 64.
TILE = 64


_failed = False


def _f32(x: float) -> str:
    """A C++ float literal that rounds to the float32 value Warp gives the Python constant ``x``."""
    import numpy as np

    return f"{float(np.float32(x))!r}f"


#: ``expo(x)``, a float32 exp for C++ loops the compiler should vectorise (a lambda that inlines, with no library
#: call), shared by ``_ROW`` and ``_warp_grad``'s loops: Cephes' single-precision range reduction and polynomial
#: (x = n ln 2 + r, |r| <= ln 2 / 2, e^r to degree 7, then scaled by 2^n through the exponent bits), x clamped to
#: [-87, 0]. Over the range the splat loops use (x in [-ln 255, 0]; lower values are rejected by the threshold,
#: higher ones clamped to 0.99 either way) within 7.7e-8 of the exact value relative, under one float32 ulp (2M
#: points against float64), where expf itself is within 1.9e-7.
EXPO = r"""
auto expo = [](float x) -> float {
    float pw = x < -87.0f ? -87.0f : (x > 0.0f ? 0.0f : x);
    float n = __builtin_floorf(pw * 1.44269504088896341f + 0.5f);
    float r = (pw - n * 0.693359375f) + n * 2.12194440e-4f;
    float e = 1.9875691500e-4f;
    e = e * r + 1.3981999507e-3f;
    e = e * r + 8.3334519073e-3f;
    e = e * r + 4.1665795894e-2f;
    e = e * r + 1.6666665459e-1f;
    e = e * r + 5.0000001201e-1f;
    e = e * r * r + r + 1.0f;
    int bits = ((int)n + 127) << 23;
    float scale;
    __builtin_memcpy(&scale, &bits, 4);
    return e * scale;
};
"""

#: Lanes of ``_ROW``'s vectors: 8 floats (AVX's 256 bits; two NEON or SSE registers where those are the widest).
LANES = 8

#: ``K`` (floats per pixel) that ``_ROW`` composites eight pixels at a time; other K take its scalar loop.
VECTOR_K = (4, 5, 7, 8)


def _row_vector_k(K: int) -> str:
    """C++ for eight pixels' K channels (``_ROW``'s vector loop, one K): the 8 K floats of pixels xs..xs+7 are
    contiguous in ``out``, so they are K vectors; vector j holds floats 8 j .. 8 j + 7, i.e. pixel (8 j + i) / K's
    channel (8 j + i) % K in lane i: the pixels' weights and the splat's channels are put in those lanes by constant
    shuffles (the channels' once per call)."""
    fe = "\n".join(f"    const pm_v8f fe{j} = __builtin_shufflevector(fv, fv, "
                   f"{', '.join(str((LANES * j + i) % K) for i in range(LANES))});" for j in range(K))
    upd = "\n".join(f"        PM_ADD({j}, {', '.join(str((LANES * j + i) // K) for i in range(LANES))})"
                    for j in range(K))
    return f"""if (K == {K}) {{
    pm_v8f fv;
    __builtin_memcpy(&fv, f, sizeof(fv));
{fe}
    for (int xs = x0; xs <= x1; xs += 8) {{
        PM_LANES
        float* ob = o + (size_t){K} * xs;
{upd}
    }}
}}"""


#: The inner loop of ``composite``, in C++ (a Warp native function): one splat over the pixels x0..x1 of one row of
#: a tile. Returns how many pixels saturated.
#:
#: Eight pixels at a time in explicit vectors (clang's vector extensions) for the K of ``VECTOR_K``: a row's span is
#: short (the CPU templates' splats: 5-8 pixels on average, median 5-8), too short for the compiler's own
#: vectorisation of the pixel loop, whose vector body needs 16 or more pixels (measured: most visits ran its scalar
#: remainder). Here a span of up to 8 pixels is one pass, its lanes past x1 masked out of every test, so they add
#: exactly 0 (their w is selected, not computed: T there may be any float, another tile's or unset) and write back
#: what they read (the buffers are padded by 8 pixels, ``composite_warp``; a frame is one serial launch, so reading
#: and rewriting a neighbouring pixel's value is safe). The exp is ``EXPO``'s, lane by lane, its polynomial evaluated
#: by Estrin's scheme (shorter dependency chains). ``vec`` = 0 (features that are not all finite, where 0 x inf would
#: reach the masked lanes) and other K take the scalar loop, which skips pixels that add nothing.
_ROW = EXPO + r"""
const float* f = feats.data + (size_t)m * K;
float* Tr = T.data + base;
float* ar = aout.data + base;
float* o = out.data + (size_t)base * K;
const float A = 0.5f * ca, B = cb, q0 = lm - 0.5f * cc * dy * dy;
int died = 0;
bool vector_k = false;
#define PM_VK(N) vector_k = vector_k || K == N;
VECTOR_KS
#undef PM_VK
if (vec != 0 && vector_k) {
    typedef float pm_v8f __attribute__((ext_vector_type(8)));
    typedef int pm_v8i __attribute__((ext_vector_type(8)));
    auto vexpo = [](pm_v8f x) -> pm_v8f {
        pm_v8f pw = x < -87.0f ? (pm_v8f)(-87.0f) : (x > 0.0f ? (pm_v8f)(0.0f) : x);
        pm_v8f y = pw * 1.44269504088896341f + 0.5f;
#if __has_builtin(__builtin_elementwise_floor)
        pm_v8f n = __builtin_elementwise_floor(y);
#else
        // An older clang (as some Warp releases bundle): floor by truncation and a step down where that rounded up
        // (exact here, |y| < 2^23; 5 % slower compositing).
        pm_v8f n = __builtin_convertvector(__builtin_convertvector(y, pm_v8i), pm_v8f);
        n += __builtin_convertvector(n > y, pm_v8f);  // a true lane compares as -1
#endif
        pm_v8f r = (pw - n * 0.693359375f) + n * 2.12194440e-4f;
        // EXPO's polynomial by Estrin's scheme (pairs of terms, then powers of r²): a chain of 4 dependent
        // multiply-adds instead of Horner's 7, for the loop's latency; within 1.2e-7 of exp relative (EXPO: 7.7e-8;
        // expf: 1.9e-7), 2M points over [-ln 255 - 0.2, 0] against float64, measured 2026-12-06.
        pm_v8f r2 = r * r;
        pm_v8f pa = r * 1.6666665459e-1f + 5.0000001201e-1f;
        pm_v8f pb = r * 8.3334519073e-3f + 4.1665795894e-2f;
        pm_v8f pc = r * 1.9875691500e-4f + 1.3981999507e-3f;
        pm_v8f e = (pa + r2 * (pb + r2 * pc)) * r2 + (r + 1.0f);
        pm_v8i bits = (__builtin_convertvector(n, pm_v8i) + 127) << 23;
        return e * __builtin_bit_cast(pm_v8f, bits);
    };
    const pm_v8i lane = {0, 1, 2, 3, 4, 5, 6, 7};
    const pm_v8f zero = 0.0f;
    pm_v8i dead = 0;
    // w and T for pixels xs..xs+7 (the lanes past x1 unused: w = 0, T rewritten as read).
#define PM_LANES                                                                        \
        pm_v8f t;                                                                       \
        __builtin_memcpy(&t, Tr + xs, sizeof(t));                                       \
        pm_v8f dx = u - (__builtin_convertvector(xs + lane, pm_v8f) + 0.5f);           \
        pm_v8f power = q0 - (A * dx * dx + B * dx * dy);                                \
        pm_v8f al = vexpo(power);                                                       \
        al = al > ALPHA_MAX ? (pm_v8f)(ALPHA_MAX) : al;                                 \
        pm_v8i use = (power > -LN_255) & (al > ALPHA_MIN) & (t > 0.0f) & (xs + lane <= x1); \
        al = use != 0 ? al : zero;                                                      \
        pm_v8f tn = t * (1.0f - al);                                                    \
        pm_v8i done = use & (tn <= T_DONE);                                             \
        dead += done;                                                                   \
        pm_v8f tw = done != 0 ? zero : tn;                                              \
        __builtin_memcpy(Tr + xs, &tw, sizeof(tw));                                     \
        pm_v8f w = (use & ~done) != 0 ? al * t : zero;                                  \
        pm_v8f av;                                                                      \
        __builtin_memcpy(&av, ar + xs, sizeof(av));                                     \
        av += w;                                                                        \
        __builtin_memcpy(ar + xs, &av, sizeof(av));
#define PM_ADD(J, ...)                                                                  \
        {                                                                               \
            pm_v8f q;                                                                   \
            __builtin_memcpy(&q, ob + 8 * J, sizeof(q));                                \
            q += __builtin_shufflevector(w, w, __VA_ARGS__) * fe##J;                    \
            __builtin_memcpy(ob + 8 * J, &q, sizeof(q));                                \
        }
VECTOR_ROWS
#undef PM_LANES
#undef PM_ADD
    return -(dead[0] + dead[1] + dead[2] + dead[3] + dead[4] + dead[5] + dead[6] + dead[7]);
}
auto weight = [&](int x, float t, int& died) -> float {
    float dx = u - ((float)x + 0.5f);
    float power = q0 - (A * dx * dx + B * dx * dy);
    float al = expo(power);
    al = al > ALPHA_MAX ? ALPHA_MAX : al;
    bool use = (power > -LN_255) & (al > ALPHA_MIN) & (t > 0.0f);
    al = use ? al : 0.0f;
    float tn = t * (1.0f - al);
    bool done = use & (tn <= T_DONE);
    died += done ? 1 : 0;
    Tr[x] = done ? 0.0f : tn;
    return done ? 0.0f : al * t;
};
for (int x = x0; x <= x1; ++x) {
    float w = weight(x, Tr[x], died);
    if (w != 0.0f) {
        for (int k = 0; k < K; ++k)
            o[K * x + k] += w * f[k];
        ar[x] += w;
    }
}
return died;
""".replace("VECTOR_KS", " ".join(f"PM_VK({k})" for k in VECTOR_K)).replace(
    "VECTOR_ROWS", "\nelse ".join(_row_vector_k(k) for k in VECTOR_K)).replace(
    "ALPHA_MAX", _f32(ALPHA_MAX)).replace("ALPHA_MIN", _f32(ALPHA_MIN)).replace(
    "T_DONE", _f32(T_DONE)).replace("LN_255", _f32(math.log(255.0)))


def available() -> bool:
    """Whether Warp imports and the kernels build (Warp is a dependency; a broken install falls back to the
    PyTorch path, and is not tried again)."""
    if _failed:
        return False
    try:
        _build()
        return True
    except Exception as exc:  # ImportError, or a Warp that cannot initialise
        mark_failed(exc)
        return False


def mark_failed(exc: BaseException) -> None:
    """Turn this path off for the rest of the process (a failed import, build or launch), with one warning."""
    global _failed
    if not _failed:
        import logging

        logging.getLogger(__name__).warning("The compiled CPU compositing failed (%s: %s); CPU renders use the "
                                            "PyTorch compositing for the rest of this session.",
                                            type(exc).__name__, exc)
    _failed = True


@built_once
def projection_funcs(wp):
    """The Warp functions both compiled projections (``project`` here, ``project_fwd`` / ``project_diff`` of
    ``_warp_grad``) are made of, with ``project_gaussians``' arithmetic: (ewa, store).

    ``ewa(p, M, S, ...)``: the splat at camera-space p (OpenCV axes) whose covariance is M S Mᵀ, projected by EWA
    with the Jacobian's x/z, y/z clamped to lim = (-x, +x, -y, +y) bounds; returns (u, v, a, b, c, z): the 2D mean,
    the 2D covariance [[a, b], [b, c]] (eps2d added) and z. ``store(i, z, o, u, v, a, b, c, ...)``: culls a
    degenerate or non-finite projection and a pixel box (at the opacity o's extent) that holds no pixel centre, and
    writes a drawn splat's key (z), mean, conic, log-opacity and box."""
    ALPHA_MIN_ = wp.constant(ALPHA_MIN)
    MAX_EXTENT_ = wp.constant(MAX_EXTENT)

    @wp.func
    def ewa(p: wp.vec3, M: wp.mat33, S: wp.mat33, fx: float, fy: float, cx: float, cy: float, lim: wp.vec4,
            eps2d: float):
        z = p[2]
        rz = 1.0 / z
        tx = z * wp.clamp(p[0] * rz, -lim[0], lim[1])
        ty = z * wp.clamp(p[1] * rz, -lim[2], lim[3])
        r0 = wp.vec3(M[0, 0], M[0, 1], M[0, 2])
        r1 = wp.vec3(M[1, 0], M[1, 1], M[1, 2])
        r2 = wp.vec3(M[2, 0], M[2, 1], M[2, 2])
        m0 = (fx * rz) * r0 + (-fx * tx * rz * rz) * r2  # rows of J M, the Jacobian of the splat's frame -> screen
        m1 = (fy * rz) * r1 + (-fy * ty * rz * rz) * r2
        s0 = S * m0
        s1 = S * m1
        a = wp.dot(m0, s0) + eps2d
        b = 0.5 * (wp.dot(m1, s0) + wp.dot(m0, s1))  # a non-symmetric S acts as its symmetric part
        c = wp.dot(m1, s1) + eps2d
        return wp.spatial_vector(fx * p[0] * rz + cx, fy * p[1] * rz + cy, a, b, c, z)

    @wp.func
    def store(i: int, z: float, o: float, u: float, v: float, a: float, b: float, c: float, W: int, H: int,
              big: float, key: wp.array(dtype=float), uv: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3),
              logo: wp.array(dtype=float), lo: wp.array(dtype=wp.vec2i), hi: wp.array(dtype=wp.vec2i)):
        det = a * c - b * b
        if not (det > 0.0 and wp.isfinite(det) and wp.isfinite(a) and wp.isfinite(c) and wp.isfinite(u)
                and wp.isfinite(v)):
            return
        extent = wp.min(wp.sqrt(2.0 * wp.log(wp.max(o, ALPHA_MIN_) / ALPHA_MIN_)), MAX_EXTENT_)
        rx = extent * wp.sqrt(wp.max(a, 0.0))
        ry = extent * wp.sqrt(wp.max(c, 0.0))
        lu = wp.max(wp.ceil(wp.clamp(u - rx - 0.5 - 1.0e-3, -big, big)), 0.0)
        hu = wp.min(wp.floor(wp.clamp(u + rx - 0.5 + 1.0e-3, -big, big)), float(W - 1))
        lv = wp.max(wp.ceil(wp.clamp(v - ry - 0.5 - 1.0e-3, -big, big)), 0.0)
        hv = wp.min(wp.floor(wp.clamp(v + ry - 0.5 + 1.0e-3, -big, big)), float(H - 1))
        if lu > hu or lv > hv:
            return
        key[i] = z
        uv[i] = wp.vec2(u, v)
        inv = 1.0 / det
        conic[i] = wp.vec3(c * inv, -b * inv, a * inv)
        logo[i] = wp.log(o)
        lo[i] = wp.vec2i(int(lu), int(lv))
        hi[i] = wp.vec2i(int(hu), int(hv))

    return ewa, store


@built_once
def _build(wp):
    # Constants the kernels read (Warp folds captured constants in when it compiles them).
    ALPHA_MIN_ = wp.constant(ALPHA_MIN)
    ALPHA_MAX_ = wp.constant(ALPHA_MAX)
    T_DONE_ = wp.constant(T_DONE)
    LN_255 = wp.constant(math.log(255.0))
    SPAN_FROM = wp.constant(2 * LANES)

    @wp.func
    def reaches(u: float, v: float, ca: float, cb: float, cc: float, r2: float, x0: float, x1: float,
                y0: float, y1: float):
        # Whether the ellipse ca dx² + 2 cb dx dy + cc dy² <= r2 about (u, v) meets the rectangle of pixel
        # centres [x0, x1] x [y0, y1]: the smallest value of the form over the rectangle, <= r2. The minimum of
        # a positive-definite form over a rectangle is at the centre when the rectangle holds it, else on an edge,
        # where along x = const the minimising y is the unconstrained one clamped to the edge (and likewise).
        if u >= x0 and u <= x1 and v >= y0 and v <= y1:
            return True
        best = float(1.0e30)
        for side in range(4):
            dx = float(0.0)
            dy = float(0.0)
            if side < 2:  # a vertical edge: dx fixed, dy free on the edge
                if side == 0:
                    dx = x0 - u
                else:
                    dx = x1 - u
                dy = wp.clamp(-cb * dx / cc, y0 - v, y1 - v)
            else:  # a horizontal edge
                if side == 2:
                    dy = y0 - v
                else:
                    dy = y1 - v
                dx = wp.clamp(-cb * dy / ca, x0 - u, x1 - u)
            q = ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy
            best = wp.min(best, q)
        return best <= r2

    @wp.func
    def level(ca: float, cc: float, logo: float):
        # alpha >= 1/255 <=> the form <= 2 (log o - ln(1/255)); widened by a margin above the float32 round-off
        # of the row spans and the per-pixel test, so a tile's list and a row's span hold every pixel the test
        # passes (a superset: the others fail the test and add nothing). The form's error at a span end is about
        # 2 sqrt(ca r2) times the end's error, ~1e-7 |u| px: under 0.07 for ca <= 100 and |u| <= 1e4 px, and
        # 1e-3 ca grows faster than it beyond. (composite_tiles' culling needs a margin that grows with the
        # tile's side squared, for its tile-local expansion; here each pixel's offset is taken directly.)
        return 2.0 * (logo + LN_255) + 0.1 + 1.0e-3 * (ca + cc)

    @wp.func
    def listed(uv: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), logo: wp.array(dtype=float),
               lo: wp.array(dtype=wp.vec2i), hi: wp.array(dtype=wp.vec2i), ts: int, m: int, tx: int, ty: int):
        # Whether splat m goes in the list of tile (tx, ty): its ellipse reaches a pixel centre of the tile
        # inside the splat's box.
        c = conic[m]
        x0 = float(wp.max(tx * ts, lo[m][0])) + 0.5
        x1 = float(wp.min(tx * ts + ts - 1, hi[m][0])) + 0.5
        y0 = float(wp.max(ty * ts, lo[m][1])) + 0.5
        y1 = float(wp.min(ty * ts + ts - 1, hi[m][1])) + 0.5
        return reaches(uv[m][0], uv[m][1], c[0], c[1], c[2], level(c[0], c[2], logo[m]), x0, x1, y0, y1)

    @wp.kernel(enable_backward=False)
    def count(uv: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), logo: wp.array(dtype=float),
              lo: wp.array(dtype=wp.vec2i), hi: wp.array(dtype=wp.vec2i), ts: int, TX: int,
              hold: wp.array(dtype=wp.uint8), per_tile: wp.array(dtype=int)):
        # One splat: +1 to every tile it goes in (the counts do not depend on the order). ``hold`` (empty: every
        # tile): only the tiles that hold an asked pixel get lists.
        m = wp.tid()
        for ty in range(lo[m][1] / ts, hi[m][1] / ts + 1):
            for tx in range(lo[m][0] / ts, hi[m][0] / ts + 1):
                t = ty * TX + tx
                if hold.shape[0] == 0 or hold[t] != wp.uint8(0):
                    if listed(uv, conic, logo, lo, hi, ts, m, tx, ty):
                        wp.atomic_add(per_tile, t, 1)

    @wp.kernel(enable_backward=False)
    def fill(uv: wp.array(dtype=wp.vec2), conic: wp.array(dtype=wp.vec3), logo: wp.array(dtype=float),
             lo: wp.array(dtype=wp.vec2i), hi: wp.array(dtype=wp.vec2i), ts: int, TX: int, M: int,
             hold: wp.array(dtype=wp.uint8), cursor: wp.array(dtype=int), lists: wp.array(dtype=int)):
        # Launched once (dim 1): the splats in depth order, each appended to the tiles it goes in (of those
        # ``hold`` names, as count), so every tile's list is in depth order. ``cursor`` starts at each tile's
        # first slot.
        for m in range(M):
            for ty in range(lo[m][1] / ts, hi[m][1] / ts + 1):
                for tx in range(lo[m][0] / ts, hi[m][0] / ts + 1):
                    t = ty * TX + tx
                    if hold.shape[0] == 0 or hold[t] != wp.uint8(0):
                        if listed(uv, conic, logo, lo, hi, ts, m, tx, ty):
                            lists[cursor[t]] = m
                            cursor[t] = cursor[t] + 1

    @wp.func
    def span(a: float, b: float, c: float, r2: float, u: float, v: float, y: int, x0: int, x1: int):
        # The pixel columns of row y, within [x0, x1], whose centres the ellipse a dx² + 2 b dx dy + c dy² <= r2
        # about (u, v) holds: dx = (-b dy ± sqrt(a r2 - det dy²)) / a. Empty: first > last.
        dy = float(y) + 0.5 - v
        disc = a * r2 - (a * c - b * b) * dy * dy
        if disc < 0.0:
            return wp.vec2i(1, 0)
        s = wp.sqrt(disc)
        lo = wp.ceil(u + (-b * dy - s) / a - 0.5)
        hi = wp.floor(u + (-b * dy + s) / a - 0.5)
        return wp.vec2i(wp.max(x0, int(wp.max(lo, -1.0e9))), wp.min(x1, int(wp.min(hi, 1.0e9))))

    @wp.func_native(_ROW)
    def row(T: wp.array(dtype=float), out: wp.array(dtype=float), aout: wp.array(dtype=float),
            feats: wp.array(dtype=float), K: int, vec: int, m: int, base: int, x0: int, x1: int, u: float,
            dy: float, ca: float, cb: float, cc: float, lm: float) -> int:
        ...

    @wp.kernel(enable_backward=False)
    def composite(start: wp.array(dtype=int), stop: wp.array(dtype=int), lists: wp.array(dtype=int),
                  uv: wp.array(dtype=wp.vec2),
                  conic: wp.array(dtype=wp.vec3), logo: wp.array(dtype=float), lo: wp.array(dtype=wp.vec2i),
                  hi: wp.array(dtype=wp.vec2i), feats: wp.array(dtype=float), K: int, vec: int, ts: int, TX: int,
                  W: int, H: int, asked: wp.array(dtype=wp.uint8), T: wp.array(dtype=float),
                  out: wp.array(dtype=float), alpha_out: wp.array(dtype=float)):
        # One tile: its splats front to back, each over the pixels of the tile its box holds (of a box over 16 px
        # wide, its ellipse at alpha = 1/255 plus the margin), row by row (``row``); a pixel keeps its
        # transmittance in T (0 once saturated, or not asked). ``feats`` and ``out`` hold K floats per splat /
        # pixel; ``vec``: the row loop may use its vectors (``_ROW``).
        tile = wp.tid()
        s0 = start[tile]
        s1 = stop[tile]
        if s1 <= s0:
            return
        bx0 = (tile % TX) * ts
        by0 = (tile / TX) * ts
        bx1 = wp.min(bx0 + ts, W) - 1
        by1 = wp.min(by0 + ts, H) - 1
        alive = int(0)
        for y in range(by0, by1 + 1):
            for x in range(bx0, bx1 + 1):
                p = y * W + x
                if asked.shape[0] == 0 or asked[p] != wp.uint8(0):
                    T[p] = 1.0
                    alive += 1
                else:
                    T[p] = 0.0
        for i in range(s0, s1):
            if alive == 0:
                break
            m = lists[i]
            cn = conic[m]
            u = uv[m][0]
            v = uv[m][1]
            lm = logo[m]
            r2 = level(cn[0], cn[2], lm)
            x0 = wp.max(lo[m][0], bx0)
            x1 = wp.min(hi[m][0], bx1)
            for y in range(wp.max(lo[m][1], by0), wp.min(hi[m][1], by1) + 1):
                # A box up to 16 px wide (nearly every splat) is walked whole on every row: the same pixel tests
                # decide (a pixel off the ellipse adds nothing), in one or two vectors a row, the same count on
                # every row, which keeps the row loop predictable; a wider one (a long thin splat across the tile)
                # walks each row's span only.
                sp = wp.vec2i(x0, x1)
                if x1 - x0 >= SPAN_FROM:
                    sp = span(cn[0], cn[1], cn[2], r2, u, v, y, x0, x1)
                if sp[0] <= sp[1]:
                    alive -= row(T, out, alpha_out, feats, K, vec, m, y * W, sp[0], sp[1], u,
                                 v - (float(y) + 0.5), cn[0], cn[1], cn[2], lm)

    INF = wp.constant(math.inf)
    ewa, store = projection_funcs()

    @wp.kernel(enable_backward=False)
    def project(means: wp.array(dtype=wp.vec3), cov: wp.array(dtype=wp.mat33), opac: wp.array(dtype=float),
                R: wp.mat33, t: wp.vec3, fx: float, fy: float, cx: float, cy: float, W: int, H: int,
                near: float, far: float, eps2d: float, lim: wp.vec4, big: float,
                mc: wp.array(dtype=wp.vec3), key: wp.array(dtype=float), uv: wp.array(dtype=wp.vec2),
                conic: wp.array(dtype=wp.vec3), logo: wp.array(dtype=float), lo: wp.array(dtype=wp.vec2i),
                hi: wp.array(dtype=wp.vec2i)):
        # One splat, as project_gaussians computes it: camera-space mean, EWA 2D covariance (the Jacobian's
        # x/z, y/z clamped to lim = (-x, +x, -y, +y) bounds), conic, pixel box at the opacity's extent; key = its
        # z when it is drawn, +inf when culled (behind near, past far, opacity < 1/255, a degenerate or
        # non-finite projection, a box that holds no pixel centre).
        i = wp.tid()
        p = R * means[i] + t
        mc[i] = p
        key[i] = INF
        z = p[2]
        o = opac[i]
        if not (z > near and z < far and o >= ALPHA_MIN_):
            return
        q = ewa(p, R, cov[i], fx, fy, cx, cy, lim, eps2d)
        store(i, z, o, q[0], q[1], q[2], q[3], q[4], W, H, big, key, uv, conic, logo, lo, hi)

    return (wp, count, fill, composite, project)




def attempt(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``, or None when it fails with anything but an InputError (a failed Warp build or
    launch): this path is then off for the rest of the process (``mark_failed``) and the caller takes the
    PyTorch one."""
    try:
        return fn(*args, **kwargs)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure of the compiled path falls back
        mark_failed(exc)
        return None


def _view(wp, t: torch.Tensor, dtype):
    t = t.detach().contiguous()
    return wp.array(t.numpy(), dtype=dtype, device="cpu", copy=False), t


def composite_warp(proj: Projected, features: torch.Tensor, width: int, height: int, *, tile_size: int = TILE,
                   pixels: Optional[torch.Tensor] = None, split: bool = False):
    """``composite_tiles`` without gradients, on the CPU: (H, W, C + 1), the composited features Σ f w then
    alpha Σ w, of the projected splats ``proj`` (front to back) with features (M, C) in the same order.
    ``pixels`` (H, W) bool: only these pixels (the others stay 0). Computed in float32. ``split``: return the two
    buffers the kernel writes instead, (H, W, K) features (K = C for 5 or 7 channels, else 4 ceil(C / 4): the first
    C channels, the rest 0) and (H, W) alpha, without the copy that joins them (a whole frame's worth of memory
    traffic)."""
    wp, count, fill, composite, _ = _build()
    f32 = torch.float32
    M, C = features.shape
    ts = int(tile_size)
    TX, TY = -(-width // ts), -(-height // ts)
    if M == 0:
        if split:
            return torch.zeros(height, width, 4 * -(-C // 4), dtype=f32), torch.zeros(height, width, dtype=f32)
        return torch.zeros(height, width, C + 1, dtype=f32)
    with torch.no_grad():
        check_intersections(proj, ts, width, height, MAX_INTERSECTIONS)
        keep = []

        def view(t, dtype):
            a, t = _view(wp, t, dtype)
            keep.append(t)
            return a

        uv = view(proj.uv.to(f32), wp.vec2)
        conic = view(proj.conic.to(f32), wp.vec3)
        logo = view(proj.log_opacity.to(f32), float)
        lo = view(proj.pix_lo.to(torch.int32), wp.vec2i)
        hi = view(proj.pix_hi.to(torch.int32), wp.vec2i)
        if pixels is None:
            asked = hold = torch.zeros(0, dtype=torch.uint8)
        else:
            asked = pixels.to(torch.bool).reshape(-1).to(torch.uint8)
            # Only the tiles holding an asked pixel get lists; the others stay empty.
            grid = torch.nn.functional.pad(pixels.to(torch.bool), (0, TX * ts - width, 0, TY * ts - height))
            hold = grid.view(TY, ts, TX, ts).any(3).any(1).reshape(-1).to(torch.uint8)
        holds = view(hold, wp.uint8)
        per_tile = torch.zeros(TX * TY + 1, dtype=torch.int32)
        wp.launch(count, dim=M, device="cpu", inputs=[uv, conic, logo, lo, hi, ts, TX, holds,
                                                      view(per_tile[1:], int)])
        start = torch.cumsum(per_tile, 0, dtype=torch.int32)  # start[t] .. start[t + 1]: tile t's list
        lists = torch.empty(max(int(start[-1]), 1), dtype=torch.int32)
        cursor = start[:-1].clone()
        wp.launch(fill, dim=1, device="cpu", inputs=[uv, conic, logo, lo, hi, ts, TX, M, holds, view(cursor, int),
                                                     view(lists, int)])
        # K floats per splat and pixel: the channels as they are for 5-7 of them (the photo texture's), else in
        # groups of four, zero-padded.
        K = C if C in (5, 7) else 4 * -(-C // 4)
        # Every buffer the row loop reads eight pixels (one splat's 8 floats) at a time from has LANES more at its
        # end (``_ROW``: a row's last vector reaches up to 7 pixels past the row's end).
        fq = torch.zeros(M * K + LANES, dtype=f32)
        fq[:M * K].view(M, K)[:, :C] = features
        # 0 x inf would reach the vectors' unused lanes: all finite when their sum is (one pass, no mask; a sum that
        # overflows only sends the frame to the scalar loop).
        vec = int(math.isfinite(float(fq.sum())))
        n = height * width
        out = torch.zeros((n + LANES) * K, dtype=f32)
        alpha = torch.zeros(n + LANES, dtype=f32)
        trans = torch.empty(n + LANES, dtype=f32)
        first, last = start[:-1], start[1:]
        wp.launch(composite, dim=TX * TY, device="cpu",
                  inputs=[view(first, int), view(last, int), view(lists, int), uv, conic, logo, lo, hi,
                          view(fq, float), K, vec, ts, TX, width, height, view(asked, wp.uint8),
                          view(trans, float), view(out, float), view(alpha, float)])
        wp.synchronize_device("cpu")
        out, alpha = out[:n * K].view(n, K), alpha[:n]
        if split:
            return out.view(height, width, K), alpha.view(height, width)
        img = torch.cat([out[:, :C], alpha[:, None]], 1) if K != C else torch.cat([out, alpha[:, None]], 1)
    return img.view(height, width, C + 1)


def projection_outputs(n: int) -> tuple[torch.Tensor, ...]:
    """The buffers a projection kernel (``project`` here, ``_warp_grad``'s ``project_fwd``) fills for n splats: key
    (n,), uv (n, 2), conic (n, 3), log-opacity (n,) float32 and the pixel box lo, hi (n, 2) int32 (only the drawn
    splats' entries are written, beyond the key)."""
    f32, i32 = torch.float32, torch.int32
    return (torch.empty(n, dtype=f32), torch.empty(n, 2, dtype=f32), torch.empty(n, 3, dtype=f32),
            torch.empty(n, dtype=f32), torch.empty(n, 2, dtype=i32), torch.empty(n, 2, dtype=i32))


def screen_bounds(wp, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    """The projection kernels' ``lim`` (the bounds (-x, +x, -y, +y) of the Jacobian's x/z, y/z: 30 % of the
    half-frame beyond each edge, as ``project_gaussians``) and ``big`` (the clamp of pixel-box coordinates)."""
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim = wp.vec4(cx / fx + 0.3 * tan_x, (width - cx) / fx + 0.3 * tan_x,
                  cy / fy + 0.3 * tan_y, (height - cy) / fy + 0.3 * tan_y)
    return lim, float(max(width, height) * 4 + 16)


def depth_order(key: torch.Tensor) -> torch.Tensor:
    """(M,) int64: the indices of the finite entries of the float32 ``key`` (N,) (a projection kernel's: the drawn
    splats' z, +inf for the culled), in a stable ascending sort by key: Warp's radix sort of (key, index) pairs, the
    same order as torch's stable argsort (keys equal: by index) in a fifth of its time (45k splats: 0.6 against
    2.8 ms, one core, measured 2026-12-06). Culled keys (+inf) sort last and are dropped."""
    wp = _build()[0]
    n = int(key.shape[0])
    if n == 0:
        return torch.zeros(0, dtype=torch.long)
    keys = torch.empty(2 * n, dtype=torch.float32)  # the sort's scratch: twice the length
    vals = torch.empty(2 * n, dtype=torch.int32)
    torch.add(key, 0.0, out=keys[:n])  # -0 -> +0: the radix sort orders -0 before +0, the comparison sort ties them
    torch.arange(n, dtype=torch.int32, out=vals[:n])
    wp.utils.radix_sort_pairs(wp.array(keys.numpy(), dtype=float, device="cpu", copy=False),
                              wp.array(vals.numpy(), dtype=int, device="cpu", copy=False), n)
    m = int(torch.searchsorted(keys[:n], torch.tensor([math.inf]), side="left"))  # sorted: the finite ones first
    return vals[:m].long()


def drawn(key: torch.Tensor, uv: torch.Tensor, conic: torch.Tensor, logo: torch.Tensor, lo: torch.Tensor,
          hi: torch.Tensor) -> Projected:
    """The drawn splats (finite key) of a projection kernel's outputs, front to back (a stable sort by key)."""
    order = depth_order(key)
    return Projected(index=order, uv=uv.index_select(0, order), conic=conic.index_select(0, order),
                     log_opacity=logo.index_select(0, order), pix_lo=lo.index_select(0, order).long(),
                     pix_hi=hi.index_select(0, order).long())


def project_warp(means: torch.Tensor, cov3d: torch.Tensor, opacities: torch.Tensor, w2c: torch.Tensor, fx: float,
                 fy: float, cx: float, cy: float, width: int, height: int, near: float, far: float,
                 eps2d: float) -> tuple[Projected, torch.Tensor]:
    """``project_gaussians`` compiled, for CPU float32 inputs without gradients: the same culling, projection and
    front-to-back order (a stable sort by z), in one loop over the splats instead of some forty whole-array
    tensor operations and batched 2x3 / 3x3 matrix products (56k splats: 25 -> 5 ms on one core). Values equal
    the tensor path's to float32 round-off (the order of a few sums differs)."""
    wp, _, _, _, project = _build()
    f32 = torch.float32
    with torch.no_grad():
        means = means.detach().to(f32).contiguous()
        N = int(means.shape[0])
        keep = []

        def view(t, dtype):
            a, t = _view(wp, t, dtype)
            keep.append(t)
            return a

        mc = torch.empty(N, 3, dtype=f32)
        outs = projection_outputs(N)
        key, uv, conic, logo, lo, hi = outs
        if N:
            w = w2c.detach().to(f32)
            R = wp.mat33(*[float(v) for v in w[:3, :3].reshape(-1).tolist()])
            t = wp.vec3(*[float(v) for v in w[:3, 3].tolist()])
            lim, big = screen_bounds(wp, fx, fy, cx, cy, width, height)
            wp.launch(project, dim=N, device="cpu",
                      inputs=[view(means, wp.vec3), view(cov3d.detach().to(f32), wp.mat33),
                              view(opacities.detach().to(f32).reshape(-1), float), R, t, float(fx), float(fy),
                              float(cx), float(cy), int(width), int(height), float(near), float(far), float(eps2d),
                              lim, big, view(mc, wp.vec3), view(key, float), view(uv, wp.vec2), view(conic, wp.vec3),
                              view(logo, float), view(lo, wp.vec2i), view(hi, wp.vec2i)])
            wp.synchronize_device("cpu")
        proj = drawn(*outs)
    return proj, mc


def usable(device: torch.device, dtype: torch.dtype, *tensors: Optional[torch.Tensor]) -> bool:
    """Whether a render can take this path: CPU float32 (float64 keeps the exact-precision PyTorch path), no
    gradient asked of any input, and Warp available."""
    if torch.device(device).type != "cpu" or dtype != torch.float32:
        return False
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors):
        return False
    return available()


