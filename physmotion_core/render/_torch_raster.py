"""Vectorised, differentiable Gaussian-splat rasterizer in plain PyTorch (CPU or CUDA tensors).

Why tiles and not (Gaussian, pixel) pairs
-----------------------------------------
The obvious vectorisation lists every (Gaussian, pixel) pair inside each splat's box, stable-sorts
the millions of pairs by pixel id and composites with segmented scans and scatters. On a CPU the
sort, gathers and scatters of that design cost more than the arithmetic. Here the image is cut into
small square tiles (8x8 px by default), as CUDA rasterizers do. Only (Gaussian, tile)
intersections are listed and sorted (tens of times fewer than pairs), which yields each tile's
depth-ordered list of Gaussians, and tiles are processed as dense blocks ``[tiles, K, pixels]``:

* the exponent of every (Gaussian, pixel) entry is one small matrix product: the quadratic form
  is expanded in tile-local pixel coordinates (lx², lx·ly, ly², lx, ly, 1), so six coefficients
  per (tile, Gaussian) times a constant (6, pixels) matrix give the whole block, log-opacity
  folded into the constant term (alpha = exp(exponent));
* the transmittance is a running product of (1 - alpha) along K, w_k = alpha_k T_{k-1};
* colour, alpha, depth and extra features are one batched matmul of the weights with the
  per-Gaussian features.

A pixel evaluates every Gaussian of its tile's list, somewhat more than the Gaussians that touch
it, but each step is a regular dense kernel (GEMM, exp, products) working in place in a reused
workspace, instead of gathers and scatters of millions of pairs.

Early termination really saves work: each tile's list is walked in chunks of K Gaussians, every
pixel's transmittance is carried from chunk to chunk, and a tile leaves the working set as soon as
all its pixels are saturated or its list is exhausted. Tiles are batched so that no more than
``max_elements`` (Gaussian, pixel) entries are alive at once, which bounds memory. The backward
pass recomputes each chunk from its inputs (see ``_BlendChunk``), so a frame rendered with
gradients keeps only O(Gaussian-tile pairs) of state, not O(pairs x pixels).

Compositing rule (gsplat's / 3DGS's, see ``rasterize`` for the details):
``alpha_i = min(ALPHA_MAX, o_i exp(-½ dᵀ Σ₂ᴰ⁻¹ d))``, entries with alpha < 1/255 are skipped,
``w_i = alpha_i T_i`` with ``T_i = Π_{j<i} (1 - alpha_j)``, and the Gaussian whose contribution
would bring T to 1e-4 or below is not counted, nor any after it (exclusive termination, exactly
the test ``next_T <= 1e-4 -> done`` of gsplat's and the original 3DGS forward kernels).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Optional

import torch

from ..errors import InputError

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# Two layers at the 0.99 clamp give T = 1e-4 exactly in real arithmetic; a relative slack of 1e-5
# makes that tie resolve the same way ("done") in float32 and float64.
T_DONE = T_MIN * (1.0 + 1e-5)
# Splat extent in sigmas: a pixel farther than sqrt(2 ln(255 o)) Mahalanobis units from the centre
# has alpha < 1/255 and is skipped anyway, so this box holds every pixel that can contribute
# (gsplat uses the same bound; 3.33 caps it for opacities near 1).
MAX_EXTENT = 3.33
LOG2_E = 1.0 / math.log(2.0)
# Guard against requests that would need more memory than any machine has.
MAX_INTERSECTIONS = 64_000_000
# The longest chunk (splats per tile per step) composite_tiles grows to without gradients.
MAX_CHUNK = 1024
# Below this many (tile, pixel) entries per slice, _cumprod_ calls cumprod_ instead of looping over K.
CUMPROD_LOOP_MIN = 4096


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities of the visible Gaussians, sorted front to back."""

    index: torch.Tensor  # (M,) indices into the input Gaussians
    uv: torch.Tensor  # (M, 2) pixel coordinates of the centres (pixel centres at +0.5)
    conic: torch.Tensor  # (M, 3) inverse 2D covariance (a, b, c) of [[a, b], [b, c]]
    log_opacity: torch.Tensor  # (M,)
    pix_lo: torch.Tensor  # (M, 2) int64 first column/row touched (clipped to the image)
    pix_hi: torch.Tensor  # (M, 2) int64 last column/row touched (inclusive)


def project_gaussians(means: torch.Tensor, cov3d: torch.Tensor, opacities: torch.Tensor,
                      w2c: torch.Tensor, fx: float, fy: float, cx: float, cy: float,
                      width: int, height: int, near: float, far: float,
                      eps2d: float) -> tuple[Projected, torch.Tensor]:
    """EWA projection, culling and depth sort.

    Culls Gaussians with z <= near or z >= far, opacity below 1/255, a non-finite or degenerate
    projection, or a box that touches no pixel centre. Returns the visible ones sorted by camera z
    (front first) and the camera-space means (N, 3) of all.
    """
    R = w2c[:3, :3]
    mc = torch.addmm(w2c[:3, 3], means, R.T)
    x, y, z = mc.unbind(-1)
    opac = opacities
    cov = cov3d
    idx = None
    with torch.no_grad():
        valid = (z > near) & (z < far) & (opacities >= ALPHA_MIN)  # NaN fails every comparison
        if not bool(valid.all()):
            idx = valid.nonzero().squeeze(1)
    if idx is not None:  # only the Gaussians in front of the camera go on (gathers keep gradients)
        x, y, z = x.index_select(0, idx), y.index_select(0, idx), z.index_select(0, idx)
        cov, opac = cov.index_select(0, idx), opac.index_select(0, idx)

    rz = 1.0 / z
    # Clamp the Jacobian's x/z, y/z a little beyond the frustum (30% of the half-fov past each
    # border, as 3DGS/gsplat do) so splats far outside the view do not blow up.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    tx = z * (x * rz).clamp(-lim_xn, lim_xp)
    ty = z * (y * rz).clamp(-lim_yn, lim_yp)
    zero = torch.zeros_like(z)
    J = torch.stack([fx * rz, zero, -fx * tx * rz * rz,
                     zero, fy * rz, -fy * ty * rz * rz], dim=-1).reshape(-1, 2, 3)
    M = J @ R  # (M, 2, 3): world -> screen Jacobian
    S = M @ cov @ M.transpose(-1, -2)
    a = S[:, 0, 0] + eps2d
    b = 0.5 * (S[:, 0, 1] + S[:, 1, 0])  # = M0 sym(Σ) M1ᵀ: a non-symmetric Σ acts as its symmetric part
    c = S[:, 1, 1] + eps2d
    det = a * c - b * b
    u = fx * x * rz + cx
    v = fy * y * rz + cy

    with torch.no_grad():
        ok = (det > 0) & torch.isfinite(det) & torch.isfinite(a) & torch.isfinite(c)
        ok &= torch.isfinite(u) & torch.isfinite(v)
        extent = torch.sqrt(2.0 * torch.log(opac.clamp_min(ALPHA_MIN) / ALPHA_MIN)).clamp(max=MAX_EXTENT)
        rx = extent * torch.sqrt(a.clamp_min(0))
        ry = extent * torch.sqrt(c.clamp_min(0))
        # Pixel (i, j) has its centre at (j + 0.5, i + 0.5): columns whose centre is within rx.
        # A 1e-3 px margin keeps pixels exactly on the threshold boundary.
        big = float(max(width, height) * 4 + 16)
        lo_u = torch.ceil((u - rx - 0.5 - 1e-3).clamp(-big, big))
        hi_u = torch.floor((u + rx - 0.5 + 1e-3).clamp(-big, big))
        lo_v = torch.ceil((v - ry - 0.5 - 1e-3).clamp(-big, big))
        hi_v = torch.floor((v + ry - 0.5 + 1e-3).clamp(-big, big))
        lo_u, hi_u = lo_u.clamp(min=0), hi_u.clamp(max=width - 1)
        lo_v, hi_v = lo_v.clamp(min=0), hi_v.clamp(max=height - 1)
        ok &= (lo_u <= hi_u) & (lo_v <= hi_v)
        ok_idx = ok.nonzero().squeeze(1)
        keep = ok_idx.index_select(0, torch.argsort(z.index_select(0, ok_idx), stable=True))  # front to back
        pix_lo = torch.stack([lo_u[keep], lo_v[keep]], -1).long()
        pix_hi = torch.stack([hi_u[keep], hi_v[keep]], -1).long()

    a, b, c, det = (x.index_select(0, keep) for x in (a, b, c, det))
    inv = 1.0 / det
    proj = Projected(
        index=keep if idx is None else idx.index_select(0, keep),
        uv=torch.stack([u.index_select(0, keep), v.index_select(0, keep)], -1),
        conic=torch.stack([c * inv, -b * inv, a * inv], -1),
        log_opacity=torch.log(opac.index_select(0, keep)),
        pix_lo=pix_lo,
        pix_hi=pix_hi,
    )
    return proj, mc


def _cumprod_(x: torch.Tensor) -> torch.Tensor:
    """In-place cumulative product along dim 1 of (T, K, P). With many tiles a loop over the short K axis of
    contiguous (T, P) slices is several times faster on CPU than ``cumprod_(1)``; with few tiles and a long K
    (a probe's handful of tiles, the last steps of a frame, where the chunk has grown) the loop's fixed cost
    per slice dominates and ``cumprod_`` is faster (measured on one core: 4 x 1024 x 64, 4.8 ms loop, 0.45 ms
    cumprod_; 200 x 64 x 64, 0.65 ms loop, 1.0 ms cumprod_). The two round differently, at float round-off."""
    if x.shape[0] * x.shape[2] < CUMPROD_LOOP_MIN:
        return x.cumprod_(1)
    for k in range(1, x.shape[1]):
        x[:, k].mul_(x[:, k - 1])
    return x


def _alpha(coef: torch.Tensor, basis: torch.Tensor, out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """alpha = min(0.99, o exp(-½ dᵀ conic d)), 0 below 1/255, of every (Gaussian, pixel) entry of
    a chunk, (T, K, P), from the exponent coefficients and the tile's pixel basis (times log2 e).
    Written into ``out`` when given (a reused workspace, see ``_workspace``)."""
    T, K, _ = coef.shape
    P = basis.shape[1]
    if out is None:
        out = torch.empty(T * K * P, dtype=coef.dtype, device=coef.device)
    # ``basis`` carries a factor log2(e): exp2 is about twice as fast as exp on CPU.
    a = torch.mm(coef.reshape(T * K, 6), basis, out=out[:T * K * P].view(T * K, P)).view(T, K, P)
    a.exp2_()
    torch.nn.functional.threshold_(a, ALPHA_MIN, 0.0)  # skip alpha < 1/255
    return a.clamp_(max=ALPHA_MAX)


def _coefficients(rows: torch.Tensor, centre: torch.Tensor):
    """Exponent coefficients of a chunk in tile-local coordinates.

    rows (T, K, 6+) hold (u, v, A, B, C, log o) per Gaussian with the quadratic form
    A dx² + B dx dy + C dy² (A, C half the conic's diagonal, B its off-diagonal); centre (T, 2) is
    each tile's centre. With (a, b) the Gaussian's offset from the tile centre and (lx, ly) a
    pixel's, dx = a - lx, dy = b - ly and

        exponent = log o - (A dx² + B dx dy + C dy²)
                 = -A lx² - B lx ly - C ly² + c3 lx + c4 ly + c5,
        c3 = 2A a + B b,  c4 = B a + 2C b,  c5 = log o - ½ (a c3 + b c4).

    Returns (coef (T, K, 6), a, b).
    """
    T, K = rows.shape[:2]
    u, v, A, B, C, logo = rows.unbind(-1)[:6]
    a = u - centre[:, 0:1]
    b = v - centre[:, 1:2]
    coef = torch.empty(T, K, 6, dtype=rows.dtype, device=rows.device)
    torch.neg(rows[..., 2:5], out=coef[..., 0:3])
    c3, c4, c5 = coef[..., 3], coef[..., 4], coef[..., 5]
    torch.mul(B, b, out=c3).addcmul_(A, a, value=2.0)
    torch.mul(B, a, out=c4).addcmul_(C, b, value=2.0)
    torch.mul(a, c3, out=c5).addcmul_(b, c4).mul_(-0.5).add_(logo)
    return coef, a, b


class _BlendChunk(torch.autograd.Function):
    """Composite one depth-ordered chunk of K Gaussians over the pixels of T tiles.

    Inputs: rows (T, K, 6 + C) the gathered per-Gaussian (u, v, A, B, C, log o, features...),
    t0 (T, P) the transmittance before the chunk (0 once a pixel is saturated), centre (T, 2) the
    tile centres, basis (6, P) (times log2 e) and a workspace. Outputs: acc (T, C, P) = Σ_k w_k f_k
    and the transmittance after the chunk (T, P), 0 for pixels that saturated.

    Backward recomputes the chunk from these small inputs instead of storing (T, K, P)
    intermediates, so memory stays O(inputs). It is the usual 3DGS gradient,
    dL/dalpha_k = T_{k-1} v_k - (Σ_{j>k} w_j v_j + T_out dL/dT_out) / (1 - alpha_k), v_k = f_k · dL/dacc,
    chained through the exponent's coefficients back to (u, v, A, B, C, log o).
    """

    @staticmethod
    def forward(ctx, rows, t0, centre, basis, workspace):
        coef, _, _ = _coefficients(rows, centre)
        feat = rows[..., 6:]
        n = coef.shape[0] * coef.shape[1] * basis.shape[1]
        w = _alpha(coef, basis, workspace[0])
        t = torch.sub(1.0, w, out=workspace[1][:n].view(w.shape))
        t[:, 0].mul_(t0)
        _cumprod_(t)  # T after each Gaussian
        t_last = t[:, -1].clone()
        w[:, 0].mul_(t0)
        w[:, 1:].mul_(t[:, :-1])  # w_k = alpha_k T_{k-1}
        # Pixels that saturate inside this chunk: the Gaussian that brings T to <= 1e-4 and all
        # later ones are not counted. Few pixels cross per chunk, so only they are touched; pixels
        # saturated before the chunk have T = 0 throughout and already get zero weights.
        crossing = (t_last <= T_DONE) & (t0 > T_DONE)
        if bool(crossing.any()):
            ti, pi = crossing.nonzero(as_tuple=True)
            w[ti, :, pi] = w[ti, :, pi] * (t[ti, :, pi] > T_DONE)
        acc = torch.bmm(feat.transpose(1, 2), w)
        if ctx is not None:  # None: called directly, without autograd (see composite_tiles)
            ctx.save_for_backward(rows, t0, centre, basis, t_last)
        t_out = torch.where(t_last > T_DONE, t_last, torch.zeros((), dtype=w.dtype, device=w.device))
        return acc, t_out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_acc, g_t):
        rows, t0, centre, basis, t_last = ctx.saved_tensors
        T, K = rows.shape[:2]
        P = basis.shape[1]
        n = T * K * P
        buf = [b[:n].view(T, K, P) for b in _workspace(5, n, rows.device, rows.dtype, "backward")]
        coef, a, b = _coefficients(rows, centre)
        feat = rows[..., 6:]
        alpha = _alpha(coef, basis, buf[0])
        q = torch.sub(1.0, alpha, out=buf[1])
        p_before = buf[2]  # Π_{i<k} (1 - alpha_i): T before each, relative to t0
        p_before[:, 0] = 1.0
        p_before[:, 1:] = q[:, :-1]
        _cumprod_(p_before)
        p_last = p_before[:, -1] * q[:, -1]
        # t_last (T after the chunk) comes from the forward pass, so that the termination
        # decisions below are bit-identical to the ones the forward pass made.
        g_t_eff = torch.where(t_last > T_DONE, g_t, 0.0)  # saturated pixels pass no T on
        # Everything below is scaled by t0 through the incoming gradient: v = t0 f_k · dL/dacc.
        g_acc = g_acc * t0[:, None, :]
        w_rel = torch.mul(p_before, alpha, out=buf[3])  # w / t0
        v = torch.bmm(feat, g_acc, out=buf[4])  # (T, K, P): t0 dL/dw_k
        pv = p_before.mul_(v)  # T_{k-1} dL/dw_k
        crossing = (t_last <= T_DONE) & (t0 > T_DONE)
        if bool(crossing.any()):  # Gaussians at and after the termination did not count
            ti, pi = crossing.nonzero(as_tuple=True)
            qs = q[ti, :, pi]
            qs[:, 0] *= t0[ti, pi]  # same product order as the forward pass
            live = (torch.cumprod(qs, 1) > T_DONE).to(q.dtype)
            w_rel[ti, :, pi] = w_rel[ti, :, pi] * live
            pv[ti, :, pi] = pv[ti, :, pi] * live
        g_feat = torch.bmm(w_rel, g_acc.transpose(1, 2))  # (T, K, C)
        wv = w_rel.mul_(v)
        later = v  # t0 Σ_{j>k} w_j v_j (+ the T_out term), reusing v's buffer from the back
        later[:, -1] = g_t_eff * t_last
        for k in range(K - 2, -1, -1):
            torch.add(later[:, k + 1], wv[:, k + 1], out=later[:, k])
        total = later[:, 0] + wv[:, 0] - g_t_eff * t_last  # t0 Σ_k w_rel_k v_k
        g_alpha = pv.sub_(later.div_(q))  # dL/dalpha
        # d alpha/d exponent = alpha where alpha is not clamped at ALPHA_MAX, else 0: negate alpha
        # and zero what is not above -ALPHA_MAX, in place (no mask tensor), then undo the sign.
        torch.nn.functional.threshold_(alpha.neg_(), -ALPHA_MAX, 0.0)
        g_alpha.mul_(alpha)
        g = torch.matmul(g_alpha, basis.transpose(0, 1) * -math.log(2.0))  # dL/dcoef (T, K, 6)
        g_t0 = torch.where(t0 > 0, total / torch.where(t0 > 0, t0, 1.0), 0.0) + g_t_eff * p_last
        # Chain rule through _coefficients.
        A, B, C = rows[..., 2], rows[..., 3], rows[..., 4]
        g0, g1, g2, g3, g4, g5 = g.unbind(-1)
        c3, c4 = coef[..., 3], coef[..., 4]
        g_rows = torch.empty_like(rows)
        g_rows[..., 0] = 2.0 * A * g3 + B * g4 - c3 * g5
        g_rows[..., 1] = B * g3 + 2.0 * C * g4 - c4 * g5
        g_rows[..., 2] = 2.0 * a * g3 - a * a * g5 - g0
        g_rows[..., 3] = b * g3 + a * g4 - a * b * g5 - g1
        g_rows[..., 4] = 2.0 * b * g4 - b * b * g5 - g2
        g_rows[..., 5] = g5
        g_rows[..., 6:] = g_feat
        return g_rows, g_t0, None, None, None


_local = threading.local()


def _workspace(count: int, size: int, device: torch.device, dtype: torch.dtype,
               tag: str) -> list[torch.Tensor]:
    """``count`` scratch buffers of at least ``size`` elements, kept per thread between calls.

    Rendering a video calls the rasterizer once per frame and each call walks dozens of chunks;
    on the CPU fresh multi-megabyte buffers cost page faults every time (without this they were
    the dominant cost of the backward pass). The cache holds 7 x ``max_elements`` values per
    dtype (56 MB in float32 by default). CUDA's caching allocator already reuses memory, so on a
    GPU nothing is kept between calls.
    """
    if torch.device(device).type != "cpu":
        return [torch.empty(size, device=device, dtype=dtype) for _ in range(count)]
    cache = getattr(_local, "buffers", None)
    if cache is None:
        cache = _local.buffers = {}
    key = (tag, str(device), dtype)
    bufs = cache.get(key)
    if bufs is None or len(bufs) < count or bufs[0].numel() < size:
        # Normal tensors even when first asked for under torch.inference_mode() (ComfyUI runs nodes so):
        # an inference tensor could not be written later outside it (e.g. by Fit, which needs gradients).
        with torch.inference_mode(False):
            bufs = cache[key] = [torch.empty(size, device=device, dtype=dtype) for _ in range(count)]
    return bufs


def _tile_runs(proj: Projected, ts: int, cull: bool):
    """The (Gaussian, tile) pairs to list, as runs along tile rows: for every tile row a Gaussian's box
    spans, the Gaussian, the row, and its first and last tile column (last < first: none).

    Without ``cull`` a run is the box's columns. With it, only the tiles whose pixel centres the splat's
    ellipse at alpha = 1/255 reaches: over the band of y the row's pixel centres span, the ellipse's
    x-extent. (The larger root of the quadratic at height y is concave in y, so its maximum over the
    band is the ellipse's own x-extreme when that lies in the band, else at the nearer band edge; the
    smaller root by symmetry.) A box holds many tiles only its corners reach, where every entry is
    below 1/255 and is skipped anyway; about a third of the entries on the CPU templates' scenes. The
    level is widened by a margin far above the float32 round-off of the tile-local evaluation, so a
    dropped entry is always one the compositing would have thresholded to exactly 0.
    """
    device = proj.uv.device
    M = proj.uv.shape[0]
    lo = torch.div(proj.pix_lo, ts, rounding_mode="floor")
    hi = torch.div(proj.pix_hi, ts, rounding_mode="floor")
    rows_per = hi[:, 1] - lo[:, 1] + 1
    g = torch.repeat_interleave(torch.arange(M, device=device), rows_per)
    first = (torch.cumsum(rows_per, 0) - rows_per).index_select(0, g)
    ty = lo[:, 1].index_select(0, g) + torch.arange(g.numel(), device=device) - first
    c_lo, c_hi = lo[:, 0].index_select(0, g), hi[:, 0].index_select(0, g)
    if not cull:
        return g, ty, c_lo, c_hi
    f64 = torch.float64
    # Per Gaussian, then per run: alpha >= 1/255 <=> q = A dx² + 2B dx dy + C dy² <= 2 (log o + ln 255).
    u, v = proj.uv.detach().to(f64).unbind(-1)
    A, B, C = proj.conic.detach().to(f64).unbind(-1)
    r2 = 2.0 * (proj.log_opacity.detach().to(f64) - math.log(ALPHA_MIN))
    r2 = (r2 + 0.05 + 1e-3 * (A + C) * (ts * ts)).clamp_min(0)  # the margin
    det = (A * C - B * B).clamp_min(1e-300)
    ymax = torch.sqrt(r2 * A / det)  # the ellipse's half-height
    xmax = torch.sqrt(r2 * C / det)  # and half-width, reached at dy = ystar
    ystar = -B * xmax / C
    per = torch.stack([u, v, A * r2, det, B / A, 1.0 / A, ymax, xmax, ystar], 1).index_select(0, g)
    u, v, Ar2, det, BA, iA, ymax, xmax, ystar = per.unbind(-1)
    y0 = ty.to(f64) * ts + 0.5 - v
    ya = torch.maximum(y0, -ymax)
    yb = torch.minimum(y0 + (ts - 1), ymax)
    hit = ya <= yb
    # Roots at height y: -B y / A ± s(y) / A with s even in y, so the mirrored band needs no new roots.
    sa = torch.sqrt((Ar2 - det * ya * ya).clamp_min(0)) * iA
    sb = torch.sqrt((Ar2 - det * yb * yb).clamp_min(0)) * iA
    ba, bb = BA * ya, BA * yb
    r_max = torch.where((ystar >= ya) & (ystar <= yb), xmax, torch.maximum(sa - ba, sb - bb))
    l_min = -torch.where((ystar >= -yb) & (ystar <= -ya), xmax, torch.maximum(sa + ba, sb + bb))
    # Pixel columns whose centre (j + 0.5) lies within [u + l_min, u + r_max], as tile columns.
    big = float(1 << 30)
    t_lo = torch.div(torch.ceil(u + l_min - 0.5).clamp(-big, big).long(), ts, rounding_mode="floor")
    t_hi = torch.div(torch.floor(u + r_max - 0.5).clamp(-big, big).long(), ts, rounding_mode="floor")
    c_lo = torch.maximum(c_lo, t_lo)
    c_hi = torch.where(hit, torch.minimum(c_hi, t_hi), c_lo - 1)
    return g, ty, c_lo, c_hi


def check_intersections(proj: Projected, ts: int, width: int, height: int, limit: Optional[int] = None) -> int:
    """The (splat, tile) pairs the splats' boxes cover with ``ts`` px tiles; InputError above ``limit``
    (``MAX_INTERSECTIONS``), before any memory is committed to them."""
    limit = MAX_INTERSECTIONS if limit is None else int(limit)
    box = torch.div(proj.pix_hi, ts, rounding_mode="floor") - torch.div(proj.pix_lo, ts, rounding_mode="floor") + 1
    total = int((box[:, 0] * box[:, 1]).sum())
    if total > limit:
        raise InputError(
            f"Rasterizing would need {total:,} splat-tile intersections (limit {limit:,}): the Gaussians are too "
            f"many or too large on screen for this {width}x{height} image. Lower the resolution, move the camera "
            "back, or shrink/drop huge Gaussians.")
    return total


def tile_lists(proj: Projected, ts: int, width: int, height: int,
               cull: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """Each ``ts`` px tile's depth-ordered list of the projected splats that may touch it (their ellipse at
    alpha = 1/255, see ``_tile_runs``; with ``cull`` off, their box). Returns (glist, tile_start, tile_count,
    total): tile t's list is ``glist[tile_start[t]:tile_start[t] + tile_count[t]]`` (indices into ``proj``,
    front first); ``glist`` has ``total`` entries plus a sentinel M (= the number of splats) at the end.
    InputError above ``MAX_INTERSECTIONS`` box intersections. Shared by ``composite_tiles`` and the compiled
    differentiable compositing (``_warp_grad``)."""
    device = proj.uv.device
    M = proj.uv.shape[0]
    TX, TY = -(-width // ts), -(-height // ts)
    n_tiles = TX * TY
    with torch.no_grad():
        check_intersections(proj, ts, width, height)
        g, ty, c_lo, c_hi = _tile_runs(proj, ts, cull)
        counts = (c_hi - c_lo + 1).clamp_min(0)
        total = int(counts.sum())
        run = torch.repeat_interleave(torch.arange(g.numel(), device=device), counts, output_size=total)
        first = (torch.cumsum(counts, 0) - counts).index_select(0, run)
        tx = c_lo.index_select(0, run) + torch.arange(total, device=device) - first
        tile = (ty.index_select(0, run) * TX + tx).to(torch.int32)
        gauss = g.index_select(0, run)  # runs follow the Gaussians' (depth) order
        del g, ty, c_lo, c_hi, counts, run, first, tx
        # Gaussians are already depth-sorted, so a stable sort by tile keeps depth order per tile.
        tile, perm = torch.sort(tile, stable=True)
        glist = torch.cat([gauss.index_select(0, perm), gauss.new_full((1,), M)])  # + sentinel
        tile_count = torch.bincount(tile, minlength=n_tiles)
        del gauss, tile, perm
        tile_start = torch.cumsum(tile_count, 0) - tile_count
    return glist, tile_start, tile_count, total


def composite_tiles(proj: Projected, features: torch.Tensor, width: int, height: int, *,
                    tile_size: int = 8, chunk: int = 16,
                    max_elements: Optional[int] = None, cull: bool = True,
                    pixels: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Front-to-back alpha compositing of the projected Gaussians.

    ``features`` (M, C) are per-Gaussian values in the same (sorted) order as ``proj``. Returns
    (H, W, C + 1): the composited features ``sum_i f_i w_i`` followed by alpha ``sum_i w_i``.
    ``tile_size`` px square tiles, ``chunk`` Gaussians per tile per step, at most ``max_elements``
    (Gaussian, pixel) entries per step (default 2M on CPU, 16M on CUDA). ``cull``: list a Gaussian
    only in the tiles its ellipse reaches (``_tile_runs``), not in every tile of its bounding box; the
    entries dropped are exact zeros, so the result is the same up to the order of float sums.
    ``pixels`` (H, W) bool: composite only these pixels (the others stay 0), to read a few of them: only
    the tiles holding one are visited, and a tile stops once its asked pixels saturate. Each pixel's
    value is the one a whole-frame render gives it, to float round-off (the same splats in the same
    order; only the grouping of the sums differs).
    """
    device, dtype = features.device, features.dtype
    if max_elements is None:
        max_elements = (1 << 21) if device.type == "cpu" else (1 << 24)
    M, C = features.shape
    ts = int(tile_size)
    TX, TY = -(-width // ts), -(-height // ts)
    n_tiles = TX * TY
    P = ts * ts
    out = torch.zeros(n_tiles, C + 1, P, device=device, dtype=dtype)
    if M == 0:
        return _tiles_to_image(out, TX, TY, ts, width, height)

    # ---- (Gaussian, tile) intersections, in (tile, depth) order ------------------------------
    with torch.no_grad():
        glist, tile_start, tile_count, total = tile_lists(proj, ts, width, height, cull)
        wanted = tile_count > 0
        if pixels is not None:
            if tuple(pixels.shape) != (height, width):
                raise InputError(f"composite_tiles: pixels must be a ({height}, {width}) mask; got "
                                 f"{tuple(pixels.shape)}")
            py, px = pixels.to(device=device, dtype=torch.bool).nonzero(as_tuple=True)
            p_tile = torch.div(py, ts, rounding_mode="floor") * TX + torch.div(px, ts, rounding_mode="floor")
            p_slot = (py % ts) * ts + px % ts  # the pixel's place in its tile, row-major
            asked = torch.zeros(n_tiles, P, dtype=torch.bool, device=device)
            asked[p_tile, p_slot] = True
            wanted &= asked.any(1)
        active = wanted.nonzero().squeeze(1)
        # Busy tiles first: batches then hold tiles of similar list lengths.
        active = active[torch.argsort(tile_count[active], descending=True, stable=True)]
        # Constant pixel basis of a tile, in coordinates relative to the tile centre.
        loc = torch.arange(ts, device=device, dtype=dtype) + 0.5 - 0.5 * ts
        ly, lx = torch.meshgrid(loc, loc, indexing="ij")
        lx, ly = lx.reshape(-1), ly.reshape(-1)
        basis = torch.stack([lx * lx, lx * ly, ly * ly, lx, ly, torch.ones_like(lx)], 0) * LOG2_E  # (6, P)
        # Pixels of a border tile that fall outside the image start saturated.
        tcol = active % TX
        trow = torch.div(active, TX, rounding_mode="floor")
        pix_x = tcol[:, None] * ts + torch.arange(ts, device=device).repeat(ts)[None, :]
        pix_y = trow[:, None] * ts + torch.arange(ts, device=device).repeat_interleave(ts)[None, :]
        inside = (pix_x < width) & (pix_y < height)  # (n_active, P)
        if pixels is not None:
            inside &= asked.index_select(0, active)  # pixels not asked start saturated
        inside = inside.to(dtype)
        centres = torch.stack([tcol.to(dtype) * ts + 0.5 * ts, trow.to(dtype) * ts + 0.5 * ts], -1)

    # One per-Gaussian table (u, v, ½a, b, ½c, log o, features..., 1) so each chunk is one gather;
    # row M is a sentinel that never contributes (pads short tile lists).
    table = torch.cat([proj.uv, 0.5 * proj.conic[:, :1], proj.conic[:, 1:2], 0.5 * proj.conic[:, 2:],
                       proj.log_opacity[:, None], features,
                       torch.ones(M, 1, device=device, dtype=dtype)], 1)
    sentinel = torch.zeros(1, table.shape[1], device=device, dtype=dtype)
    sentinel[0, 5] = -1e4
    table = torch.cat([table, sentinel], 0)
    D = table.shape[1]

    grad = torch.is_grad_enabled() and table.requires_grad
    K = max(1, int(chunk))
    batch_tiles = max(1, int(max_elements) // (P * K))
    budget = min(batch_tiles, int(active.numel())) * K * P  # entries per step: the workspace's size
    workspace = _workspace(2, budget, device, dtype, "forward")
    for b0 in range(0, int(active.numel()), batch_tiles):
        tiles = active[b0:b0 + batch_tiles]
        t_run = inside[b0:b0 + batch_tiles]  # transmittance so far; 0 = saturated (or off-image)
        centre = centres[b0:b0 + batch_tiles]
        start, count = tile_start[tiles], tile_count[tiles]
        k0 = 0
        K = max(1, int(chunk))
        while tiles.numel() > 0:
            if not grad:
                # Without gradients the chunk grows as tiles drop out (the few with long lists, at a silhouette,
                # where pixels never saturate, would otherwise take dozens of small steps, each costing more in
                # per-step overhead than in work): the same entries per step, fewer steps. Only the grouping of
                # the float sums changes.
                while 2 * K * int(tiles.numel()) * P <= budget and K < MAX_CHUNK:
                    K *= 2
            ar = torch.arange(K, device=device)
            with torch.no_grad():
                idx = torch.where(ar < (count - k0)[:, None], (start + k0)[:, None] + ar, total)
                gid = glist.index_select(0, idx.view(-1))
            if grad:
                rows = table.index_select(0, gid).view(-1, K, D)
                acc, t_run = _BlendChunk.apply(rows, t_run, centre, basis, workspace)
            else:  # the same gather (embedding is several times faster on CPU) and the same forward
                rows = torch.nn.functional.embedding(gid, table).view(-1, K, D)
                acc, t_run = _BlendChunk.forward(None, rows, t_run, centre, basis, workspace)
            out.index_add_(0, tiles, acc)  # autograd-safe: index_add's backward does not need `out`
            k0 += K
            with torch.no_grad():
                alive = (count > k0) & (t_run > 0).any(dim=1)
                if bool(alive.all()):
                    continue
                sel = alive.nonzero().squeeze(1)
            tiles, start, count, t_run, centre = tiles[sel], start[sel], count[sel], t_run[sel], centre[sel]
    if pixels is not None:  # only the asked pixels: gathered, not the whole tile grid turned into an image
        img = torch.zeros(height, width, C + 1, device=device, dtype=dtype)
        img[py, px] = out[p_tile, :, p_slot]
        return img
    return _tiles_to_image(out, TX, TY, ts, width, height)


def _tiles_to_image(out: torch.Tensor, TX: int, TY: int, ts: int, width: int, height: int) -> torch.Tensor:
    C = out.shape[1]
    img = out.reshape(TY, TX, C, ts, ts).permute(0, 3, 1, 4, 2).reshape(TY * ts, TX * ts, C)
    return img[:height, :width]


def rasterize_torch(means: torch.Tensor, cov3d: torch.Tensor, opacities: torch.Tensor,
                    features: torch.Tensor, w2c: torch.Tensor, *, fx: float, fy: float, cx: float, cy: float,
                    width: int, height: int, near: float, far: float, eps2d: float, depth_mode: str,
                    tile_size: int = 8, chunk: int = 16, max_elements: Optional[int] = None,
                    cull: bool = True, compositor=None, projector=None) -> tuple[torch.Tensor, float]:
    """Render features (N, C) to (H, W, C + 2): features, depth, alpha (all accumulated Σ f w).

    The depth channel is accumulated as an offset from a reference depth (returned too), expected
    depth = ref + Σ (d - ref) w / Σ w, which keeps float32 sums accurate when the scene's depth
    range is small compared with its distance. ``compositor``: a function with ``composite_tiles``'
    signature (projected splats, features, width, height) to composite with instead (the Warp one,
    ``_warp_raster.composite_warp``, for renders without gradients); the tiling options are then unused.
    ``projector``: likewise a function with ``project_gaussians``' signature (``_warp_raster.project_warp``).
    """
    proj, mc = (projector or project_gaussians)(means, cov3d, opacities, w2c, fx, fy, cx, cy, width, height,
                                                near, far, eps2d)
    mcv = mc[proj.index]
    depth = mcv[:, 2] if depth_mode == "z" else torch.linalg.vector_norm(mcv, dim=-1)
    ref = float(depth.detach().mean()) if depth.numel() else 0.0
    feats = torch.cat([features[proj.index], (depth - ref)[:, None]], 1)
    if compositor is not None:
        return compositor(proj, feats, width, height), ref
    img = composite_tiles(proj, feats, width, height, tile_size=tile_size, chunk=chunk,
                          max_elements=max_elements, cull=cull)
    return img, ref
