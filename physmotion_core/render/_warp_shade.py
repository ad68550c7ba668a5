"""The photo texture's per-pixel passes compiled with Warp (CPU): photo coordinates, stretch, bicubic sampling
and blending, in two loops over the textured pixels instead of some forty whole-image tensor operations.

``photo_texture.shade`` holds the model and a tensor implementation of it (``compiled=False``, the fallback when
Warp is unavailable); this module computes the same values, with the arithmetic in the same precision (photo
coordinates and the stretch in float64, colours in float32), so the two agree to float32 round-off
(tests/test_photo_texture.py compares them to 1e-5).

* ``coords``: one loop over the box of pixels the seen splats reach: the pixel's photo coordinate (the one rigid
  map applied to its surface point, or its ray plus the composited displacement) and whether it has one.
* ``blend``: per pixel, the stretch of the photo coordinates (their Jacobian with respect to the pixel position,
  from the neighbours' coordinates), the photo's share of the pixel (faded where the photo is stretched),
  the photo sampled bicubically (Keys' cubic, a = -0.75, zero outside the photo) and the frame's colour and
  coverage. The splats' interior floor needs a distance transform, which OpenCV computes between the two loops.
"""

# No "from __future__ import annotations": Warp reads the kernels' annotations, which name the local `wp`.

import threading

import numpy as np
import torch

_lock = threading.Lock()
_built = None


def _build():
    global _built
    with _lock:
        if _built is not None:
            return _built
        import warp as wp

        wp.config.quiet = True
        wp.init()
        f64 = wp.float64

        @wp.kernel(enable_backward=False)
        def coords(ext: wp.array(dtype=float), C: int, depth: wp.array(dtype=float), W: int, x0: int, y0: int,
                   bw: int, one: int, A: wp.mat33d, b: wp.vec3d, rfx: f64, rfy: f64, rcx: f64, rcy: f64,
                   pfx: f64, pfy: f64, pcx: f64, pcy: f64, u_out: wp.array(dtype=f64),
                   v_out: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8)):
            # One pixel of the box: its photo coordinate (pixel units, centres at +0.5) and whether it has one
            # (seen splats reach it, and under the one map its surface point lies in front of the photo's camera).
            i = wp.tid()
            x = x0 + i % bw
            y = y0 + i / bw
            p = y * W + x
            S = ext[p * C + C - 1]
            u = f64(0.0)
            v = f64(0.0)
            good = S > 1.0e-6
            rx = (f64(x) + f64(0.5) - rcx) / rfx
            ry = (f64(y) + f64(0.5) - rcy) / rfy
            if good:
                if one != 0:
                    d = f64(depth[p])
                    X = A[0, 0] * rx + A[0, 1] * ry + A[0, 2]
                    Y = A[1, 0] * rx + A[1, 1] * ry + A[1, 2]
                    Z = A[2, 0] * rx + A[2, 1] * ry + A[2, 2]
                    X = d * X + b[0]
                    Y = d * Y + b[1]
                    Z = d * Z + b[2]
                    if Z > f64(1.0e-9):
                        u = pfx * X / Z + pcx
                        v = pfy * Y / Z + pcy
                    else:
                        good = False
                else:
                    s = f64(S)
                    u = pfx * rx + pcx + f64(ext[p * C]) / s
                    v = pfy * ry + pcy + f64(ext[p * C + 1]) / s
            u_out[i] = u
            v_out[i] = v
            if good:
                ok[i] = wp.uint8(1)
            else:
                ok[i] = wp.uint8(0)

        @wp.func
        def deriv(c: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8), i: int, lo: int, hi: int, step: int):
            # d c / d (pixel) along one axis at box index i from its neighbours i -/+ step (lo / hi: whether they
            # are inside the box): central where both have coordinates, one-sided where one has; nan where none.
            has_lo = False
            has_hi = False
            if lo != 0:
                has_lo = ok[i - step] != wp.uint8(0)
            if hi != 0:
                has_hi = ok[i + step] != wp.uint8(0)
            if has_lo and has_hi:
                return (c[i + step] - c[i - step]) * f64(0.5)
            if has_hi:
                return c[i + step] - c[i]
            if has_lo:
                return c[i] - c[i - step]
            return f64(wp.nan)

        @wp.func
        def keys(t: float):
            # Keys' cubic convolution weights (a = -0.75, OpenCV's bicubic) for the taps at -1, 0, 1, 2 of a
            # sample at fraction t in [0, 1).
            a = float(-0.75)
            s = t + 1.0
            w0 = ((a * s - 5.0 * a) * s + 8.0 * a) * s - 4.0 * a
            w1 = ((a + 2.0) * t - (a + 3.0)) * t * t + 1.0
            r = 1.0 - t
            w2 = ((a + 2.0) * r - (a + 3.0)) * r * r + 1.0
            return wp.vec4(w0, w1, w2, 1.0 - w0 - w1 - w2)

        @wp.kernel(enable_backward=False)
        def blend(u_in: wp.array(dtype=f64), v_in: wp.array(dtype=f64), ok: wp.array(dtype=wp.uint8),
                  ext: wp.array(dtype=float), C: int, rgb: wp.array(dtype=float), alpha: wp.array(dtype=float),
                  dist: wp.array(dtype=float), W: int, x0: int, y0: int, bw: int, bh: int,
                  planes: wp.array(dtype=wp.vec4), PW: int, PH: int, min_cov: float, in0: float, in1: float,
                  st0: f64, st1: f64, out_rgb: wp.array(dtype=float), out_a: wp.array(dtype=float)):
            i = wp.tid()
            bx = i % bw
            by = i / bw
            p = (y0 + by) * W + x0 + bx
            a = alpha[p]
            c0 = rgb[3 * p]
            c1 = rgb[3 * p + 1]
            c2 = rgb[3 * p + 2]
            w = float(0.0)
            smp = wp.vec4(0.0, 0.0, 0.0, 0.0)
            if ok[i] != wp.uint8(0):
                S = ext[p * C + C - 1]
                w = wp.clamp(S / wp.max(a, 1.0e-12), 0.0, 1.0) * wp.clamp(a * (1.0 / min_cov), 0.0, 1.0)
                # Stretch: the largest factor by which the frame magnifies the photo along any direction, the
                # inverse of the Jacobian's smallest singular value (photo px per frame px).
                ux = deriv(u_in, ok, i, int(bx > 0), int(bx < bw - 1), 1)
                vx = deriv(v_in, ok, i, int(bx > 0), int(bx < bw - 1), 1)
                uy = deriv(u_in, ok, i, int(by > 0), int(by < bh - 1), bw)
                vy = deriv(v_in, ok, i, int(by > 0), int(by < bh - 1), bw)
                if wp.isnan(ux):
                    ux = f64(1.0)
                    vx = f64(0.0)
                if wp.isnan(uy):
                    uy = f64(0.0)
                    vy = f64(1.0)
                E = ux * ux + vx * vx + uy * uy + vy * vy
                D = wp.abs(ux * vy - uy * vx)
                smin2 = f64(0.5) * (E - wp.sqrt(wp.max(E * E - f64(4.0) * D * D, f64(0.0))))
                fade = f64(1.0)
                if smin2 * st1 * st1 < f64(1.0):
                    fade = f64(0.0)
                elif smin2 * st0 * st0 < f64(1.0):
                    fade = (st1 - f64(1.0) / wp.sqrt(smin2)) / (st1 - st0)
                w = w * float(fade)
                # Bicubic sample of (premultiplied colour, matte) at the photo coordinate; zero outside the photo.
                mx = u_in[i] - f64(0.5)
                my = v_in[i] - f64(0.5)
                fx = wp.floor(mx)
                fy = wp.floor(my)
                if fx > f64(-3.0) and fx < f64(PW + 1) and fy > f64(-3.0) and fy < f64(PH + 1):
                    ix = int(fx)
                    iy = int(fy)
                    wx = keys(float(mx - fx))
                    wy = keys(float(my - fy))
                    for j in range(4):
                        yy = iy - 1 + j
                        if yy >= 0 and yy < PH:
                            row = wp.vec4(0.0, 0.0, 0.0, 0.0)
                            for k in range(4):
                                xx = ix - 1 + k
                                if xx >= 0 and xx < PW:
                                    row = row + wx[k] * planes[yy * PW + xx]
                            smp = smp + wy[j] * row
            m_s = wp.clamp(smp[3], 0.0, 1.0)
            keep = 1.0 - w
            am = w * m_s + keep * a
            floor = a * wp.clamp((dist[i] - in0) / (in1 - in0), 0.0, 1.0)
            ex = wp.max(floor - am, 0.0)
            out_a[p] = am + ex
            g = ex / wp.max(a, 1.0e-6)
            out_rgb[3 * p] = w * wp.min(wp.max(smp[0], 0.0), m_s) + keep * c0 + g * c0
            out_rgb[3 * p + 1] = w * wp.min(wp.max(smp[1], 0.0), m_s) + keep * c1 + g * c1
            out_rgb[3 * p + 2] = w * wp.min(wp.max(smp[2], 0.0), m_s) + keep * c2 + g * c2

        _built = (wp, coords, blend)
        return _built


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
    """The texture's (H,W,4) float32 planes as a Warp array of vec4 (no copy)."""
    wp = _build()[0]
    return wp.array(planes.reshape(-1, 4), dtype=wp.vec4, device="cpu", copy=False)


def photo_coords(ext: torch.Tensor, depth: torch.Tensor, box: tuple, camera, photo_camera, one_map=None):
    """(u, v) float64 (bh*bw) and ok uint8 (bh*bw): the photo coordinates of the box's pixels (``coords``)."""
    wp, coords, _ = _build()
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
    wp.launch(coords, dim=bh * bw, device="cpu",
              inputs=[_arr(wp, ext, float, keep), C, _arr(wp, depth, float, keep), W, x0, y0, bw,
                      int(one_map is not None), Aw, bv, float(camera.fx), float(camera.fy), float(camera.cx),
                      float(camera.cy), float(pc.fx), float(pc.fy), float(pc.cx), float(pc.cy),
                      _arr(wp, u, wp.float64, keep), _arr(wp, v, wp.float64, keep), _arr(wp, ok, wp.uint8, keep)])
    wp.synchronize_device("cpu")
    return u, v, ok


def blend(u, v, ok, ext, rgb, alpha, dist, box, planes, planes_wp, consts, out_rgb, out_a) -> None:
    """The ``blend`` loop over the box, writing ``out_rgb`` (H,W,3) and ``out_a`` (H,W) there (contiguous)."""
    wp, _, kernel = _build()
    y0, y1, x0, x1 = box
    bh, bw = y1 - y0, x1 - x0
    H, W, C = ext.shape
    keep: list = []
    PH, PW = planes.shape[:2]
    min_cov, in0, in1, st0, st1 = consts
    wp.launch(kernel, dim=bh * bw, device="cpu",
              inputs=[_arr(wp, u, wp.float64, keep), _arr(wp, v, wp.float64, keep), _arr(wp, ok, wp.uint8, keep),
                      _arr(wp, ext, float, keep), C, _arr(wp, rgb, float, keep), _arr(wp, alpha, float, keep),
                      _arr(wp, dist, float, keep), W, x0, y0, bw, bh, planes_wp, PW, PH, float(min_cov), float(in0),
                      float(in1), float(st0), float(st1)],
              outputs=[wp.array(out_rgb.numpy().reshape(-1), dtype=float, device="cpu", copy=False),
                       wp.array(out_a.numpy().reshape(-1), dtype=float, device="cpu", copy=False)])
    wp.synchronize_device("cpu")
