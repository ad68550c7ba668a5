"""Posing a frame's Gaussians from its particles, compiled with Warp (the CPU path of SimResult.gaussians_at),
and the splats' stretch clamp (``clamp_stretch``, the CPU path of types.results.splat_deformation).

Each Gaussian g follows a weighted blend of its K nearest particles' local affine maps (see SimResult):

    x_g = Σ_k w_k (x_k + F_k (X_g − X_k)),   Σ_g = F̄ Σ⁰_g F̄ᵀ,   F̄ = Σ_k w_k F_k,

with a neighbour's weight dropped once it is torn away from the Gaussian's own particle (more than twice
its rest distance plus one spacing) and the weights renormalised. In PyTorch this is a gather of K
matrices per Gaussian and a dozen whole-array passes (about 0.1 s per frame for 56k Gaussians and K = 8
on one core, as much as rasterizing the frame); one compiled loop per Gaussian costs a fraction of
that. Same arithmetic as the PyTorch formula it replaces (kept in ``SimResult._pose_torch``, which the
tests compare against): F̄ in float32, the means in float64 about the rest centre c, written in float32.

One thread by default: a frame takes ~13 ms for 56k Gaussians on one core of the 2-core test machine and
two threads measured no faster (it is memory-bound), while a thread pool launched between torch's
rendering calls competed with torch's spinning OpenMP workers (87 ms a frame inside render_clip). ``threads``
splits the Gaussians between that many threads (Warp releases the GIL while a CPU kernel runs).
"""

# No "from __future__ import annotations": Warp reads the kernel's annotations, which name the local `wp`.

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from ..warp_build import built_once


@built_once
def _build(wp):
    @wp.func
    def weight(x: wp.array(dtype=wp.vec3), nb: wp.array2d(dtype=int), w: wp.array2d(dtype=float),
               rest_d: wp.array2d(dtype=float), spacing: float, crack: int, xo: wp.vec3, n: int, k: int):
        # Neighbour k's weight before normalising: 0 once torn away from the Gaussian's own particle
        # (NaN counts as torn); the own particle's never below 1e-6.
        wk = w[n, k]
        if crack != 0:
            d = wp.length(x[nb[n, k]] - xo)
            if not (d <= 2.0 * rest_d[n, k] + spacing):
                wk = 0.0
        if k == 0:
            wk = wp.max(wk, 1.0e-6)
        return wk

    @wp.kernel(enable_backward=False)
    def pose(x: wp.array(dtype=wp.vec3), X: wp.array(dtype=wp.vec3), F: wp.array(dtype=wp.mat33),
             nb: wp.array2d(dtype=int), w: wp.array2d(dtype=float), rest_d: wp.array2d(dtype=float),
             spacing: float, crack: int, centre: wp.vec3d, Xg: wp.array(dtype=wp.vec3),
             cov: wp.array(dtype=wp.mat33), offset: int,
             means: wp.array(dtype=wp.vec3), covars: wp.array(dtype=wp.mat33)):
        n = wp.tid() + offset
        K = nb.shape[1]
        xo = x[nb[n, 0]]
        # One pass over the neighbours (each weight, with its tearing test, computed once), normalised at the end.
        total = float(0.0)
        Fg = wp.mat33(0.0)
        m = wp.vec3d(0.0, 0.0, 0.0)
        for k in range(K):
            wk = weight(x, nb, w, rest_d, spacing, crack, xo, n, k)
            p = nb[n, k]
            Fp = F[p]
            total += wk
            Fg += wk * Fp
            b = wp.vec3d(x[p]) - wp.mat33d(Fp) * (wp.vec3d(X[p]) - centre)
            m += wp.float64(wk) * b
        Fg = Fg * (1.0 / total)
        m = m / wp.float64(total)
        means[n] = wp.vec3(m + wp.mat33d(Fg) * (wp.vec3d(Xg[n]) - centre))
        covars[n] = Fg * cov[n] * wp.transpose(Fg)

    @wp.kernel(enable_backward=False)
    def clamp_stretch(F: wp.array(dtype=wp.mat33d), limit: wp.float64, rotation_free: wp.array(dtype=wp.uint8),
                      out: wp.array(dtype=wp.mat33d)):
        # F = U S Vᵀ with S clamped to [1/limit, limit]; where rotation_free, V S Vᵀ. Warp's svd3 keeps U and V
        # rotations and puts an inversion's sign on the last singular value (the smallest in magnitude): that
        # sign moves into U's last column, so S is non-negative as in the usual SVD. The products are unique
        # (equal singular values clamp to equal values), so they equal those of any other SVD of F.
        i = wp.tid()
        U = wp.mat33d()
        S = wp.vec3d()
        V = wp.mat33d()
        wp.svd3(F[i], U, S, V)
        lo = wp.float64(1.0) / limit
        s = wp.vec3d(wp.clamp(wp.abs(S[0]), lo, limit), wp.clamp(wp.abs(S[1]), lo, limit),
                     wp.clamp(wp.abs(S[2]), lo, limit))
        if rotation_free[i] != wp.uint8(0):
            out[i] = V * wp.diag(s) * wp.transpose(V)
        else:
            one = wp.float64(1.0)
            sg = wp.vec3d(wp.where(S[0] < wp.float64(0.0), -one, one), wp.where(S[1] < wp.float64(0.0), -one, one),
                          wp.where(S[2] < wp.float64(0.0), -one, one))
            out[i] = U * wp.diag(wp.cw_mul(sg, s)) * wp.transpose(V)

    return (wp, pose, clamp_stretch)


def clamp_stretch(F: torch.Tensor, limit: float, rotation_free: torch.Tensor) -> torch.Tensor:
    """(N,3,3) float64 on the CPU: U clamp(S, 1/limit, limit) Vᵀ of each F = U S Vᵀ, or V clamp(S) Vᵀ where
    ``rotation_free`` (N,) is true (``splat_deformation``'s rule), compiled: a 3x3 SVD per matrix in a loop
    instead of LAPACK's batched one (on sand's 5.4k particles 33 ms -> a few ms a frame, one core)."""
    wp, _, kernel = _build()
    N = int(F.shape[0])
    out = torch.empty(N, 3, 3, dtype=torch.float64)
    if N == 0:
        return out
    keep = []

    def view(t, dtype):
        a, t = _wp_view(wp, t, dtype)
        keep.append(t)
        return a

    wp.launch(kernel, dim=N, device="cpu",
              inputs=[view(F.to(torch.float64), wp.mat33d), float(limit), view(rotation_free.to(torch.uint8), wp.uint8),
                      view(out, wp.mat33d)])
    wp.synchronize_device("cpu")
    return out


def _wp_view(wp, t: torch.Tensor, dtype):
    """A Warp array on the tensor's memory (CPU, contiguous), no copy; and the tensor, to keep alive."""
    t = t.detach().contiguous()
    return wp.array(t.numpy(), dtype=dtype, device="cpu", copy=False), t


def pose_gaussians(x: torch.Tensor, X: torch.Tensor, F: torch.Tensor, neighbours: torch.Tensor,
                   weights: torch.Tensor, rest_d, spacing: float, centre: torch.Tensor, Xg: torch.Tensor,
                   rest_cov: torch.Tensor, threads: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Means (N,3) and covariances (N,3,3), float32, of the Gaussians posed by the particles' positions ``x``
    (P,3) and splat deformations ``F`` (P,3,3); ``X`` (P,3) the particles' rest positions, ``neighbours``
    (N,K) and ``weights`` (N,K) each Gaussian's particles, ``rest_d`` (N,K) their rest distances to its own
    particle (None: no tearing test), ``centre`` (3,) float64, ``Xg`` (N,3) and ``rest_cov`` (N,3,3) the
    Gaussians at rest."""
    wp, kernel, _ = _build()
    f32 = torch.float32
    N = int(Xg.shape[0])
    keep = []  # the tensors the Warp views read from stay alive until the launches end

    def view(t, dtype):
        a, t = _wp_view(wp, t, dtype)
        keep.append(t)
        return a

    xa, Xa = view(x.to(f32), wp.vec3), view(X.to(f32), wp.vec3)
    Fa = view(F.to(f32), wp.mat33)
    nba = view(neighbours.to(torch.int32), int)
    wa = view(weights.to(f32), float)
    crack = rest_d is not None
    rda = view(rest_d.to(f32), float) if crack else wa
    Xga, cova = view(Xg.to(f32), wp.vec3), view(rest_cov.to(f32), wp.mat33)
    means = torch.empty(N, 3, dtype=f32)
    covars = torch.empty(N, 3, 3, dtype=f32)
    ma, ca = view(means, wp.vec3), view(covars, wp.mat33)
    c = wp.vec3d(*[float(v) for v in centre.double().tolist()])
    n_threads = max(1, min(int(threads), N // 4096 or 1))
    bounds = np.linspace(0, N, n_threads + 1).astype(int)

    def launch(i: int) -> None:
        lo, hi = int(bounds[i]), int(bounds[i + 1])
        if hi > lo:
            wp.launch(kernel, dim=hi - lo, device="cpu",
                      inputs=[xa, Xa, Fa, nba, wa, rda, float(spacing), int(crack), c, Xga, cova, lo, ma, ca])

    if n_threads == 1:
        launch(0)
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            for job in [pool.submit(launch, i) for i in range(n_threads)]:
                job.result()
    wp.synchronize_device("cpu")
    return means, covars
