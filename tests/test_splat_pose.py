"""Posing the Gaussians of a frame (SimResult.gaussians_at) against the rule written out plainly.

The fast path runs the SVD only where the stretch clamp can change F and reassociates the blend of
the neighbours' affine maps; these tests hold it to the direct formula: every F through the SVD,
x_g = Σ w_k (x_k + F_k (X_g − X_k)), Σ_g = F̄ Σ⁰ F̄ᵀ, torn neighbours dropped, liquid splats round."""

import pickle

import torch

from physmotion_core.types.gaussians import Gaussians
from physmotion_core.types.material import Material
from physmotion_core.types.results import MAX_SPLAT_STRETCH, SimResult, splat_deformation


def _reference_deformation(F, limit, rotation_free):
    U, S, Vh = torch.linalg.svd(F.double())
    S = torch.diag_embed(S.clamp(1.0 / limit, limit))
    out = torch.where(rotation_free[:, None, None], Vh.transpose(-1, -2) @ S @ Vh, U @ S @ Vh)
    return out.to(F.dtype)


def _random_F(n, gen):
    F = torch.eye(3) + 0.3 * torch.randn(n, 3, 3, generator=gen)
    F[: n // 8] *= 5.0  # stretched past the clamp
    F[n // 8: n // 4] *= 0.1  # squashed past it
    F[n // 4: n // 4 + 5, :, 0] *= -1.0  # inverted
    return F


def test_splat_deformation_matches_the_svd_clamp_everywhere():
    gen = torch.Generator().manual_seed(1)
    F = _random_F(4000, gen)
    rf = torch.rand(4000, generator=gen) < 0.3
    got = splat_deformation(F, MAX_SPLAT_STRETCH, rf)
    want = _reference_deformation(F, MAX_SPLAT_STRETCH, rf)
    torch.testing.assert_close(got, want, atol=2e-6, rtol=2e-6)
    # Inside the bound, F comes back unchanged without the SVD's round trip.
    small = torch.eye(3) + 0.05 * torch.randn(100, 3, 3, generator=gen)
    assert torch.equal(splat_deformation(small, MAX_SPLAT_STRETCH), small)


def test_compiled_stretch_clamp_matches_lapack_on_hard_matrices():
    """sim/pose.clamp_stretch (Warp's svd3 per matrix, the CPU path of splat_deformation) against LAPACK's SVD in
    float64, on the matrices where an SVD's sign and order conventions matter: inversions (a negative determinant),
    rank-deficient and zero matrices, repeated singular values, rotations, reflections, and stretches past the
    clamp both ways; with and without the rotation-free rule."""
    from physmotion_core.sim.pose import clamp_stretch

    gen = torch.Generator().manual_seed(7)
    F = _random_F(3000, gen).double()
    R = torch.linalg.qr(torch.randn(40, 3, 3, generator=gen, dtype=torch.float64)).Q
    special = [torch.eye(3), -torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, -1.0])),
               torch.diag(torch.tensor([2.0, 2.0, 0.0])), torch.diag(torch.tensor([5.0, 0.1, 0.1])),
               torch.diag(torch.tensor([1e-9, 1.0, 1e9]))]
    F = torch.cat([F, R, R * 4.0, R * torch.tensor([1.0, 1.0, -0.05], dtype=torch.float64),
                   torch.stack(special).double()])
    for rf in (torch.zeros(len(F), dtype=torch.bool), torch.ones(len(F), dtype=torch.bool),
               torch.rand(len(F), generator=gen) < 0.5):
        got = clamp_stretch(F, MAX_SPLAT_STRETCH, rf)
        want = _reference_deformation(F, MAX_SPLAT_STRETCH, rf)
        assert (got - want).abs().max() < 1e-9, (got - want).abs().amax((1, 2)).argmax()
    assert clamp_stretch(F[:0], MAX_SPLAT_STRETCH, rf[:0]).shape == (0, 3, 3)
    # Rank 0 or 1: U and V of the repeated zero singular values are each free, so U clamp(S) Vᵀ is not unique
    # (any SVD's is as right); its singular values are: the clamp's. V clamp(S) Vᵀ is unique again.
    low = torch.stack([torch.zeros(3, 3), torch.ones(3, 3), torch.outer(torch.tensor([1.0, 2, 3]),
                                                                         torch.tensor([0.5, -1, 2]))]).double()
    for rfv in (False, True):
        rf = torch.full((3,), rfv)
        got = clamp_stretch(low, MAX_SPLAT_STRETCH, rf)
        want = torch.linalg.svdvals(low).clamp(1 / MAX_SPLAT_STRETCH, MAX_SPLAT_STRETCH)
        assert (torch.linalg.svdvals(got) - want).abs().max() < 1e-12
        if rfv:
            assert (got - _reference_deformation(low, MAX_SPLAT_STRETCH, rf)).abs().max() < 1e-12


def _sim(gen, N=3000, P=1500, K=8, T=2):
    means = torch.rand(N, 3, generator=gen) + torch.tensor([2.0, 1.0, -3.0])  # metres from the origin
    g = Gaussians.from_rgb(means, torch.rand(N, 3, generator=gen), 0.01 * torch.rand(N, 3, generator=gen) + 1e-3,
                           torch.rand(N, generator=gen))
    X = means[torch.randint(0, N, (P,), generator=gen)] + 0.01 * torch.randn(P, 3, generator=gen)
    F = torch.stack([_random_F(P, gen) for _ in range(T)])
    x = X[None] + 0.02 * torch.randn(T, P, 3, generator=gen)
    x[1, :50] += 1.0  # torn far away
    nb = torch.randint(0, P, (N, K), generator=gen)
    w = torch.rand(N, K, generator=gen)
    w = w / w.sum(1, keepdim=True)
    rf = torch.rand(P, generator=gen) < 0.2
    liquid = torch.rand(P, generator=gen) < 0.1
    return SimResult(rest=g, times=torch.arange(T).float(), x=x, F=F, binding=nb[:, 0], rest_particles=X,
                     material=Material(), stats={"particle_spacing": 0.01}, rotation_free=rf, liquid=liquid,
                     neighbours=nb, weights=w)


def _reference_pose(sim, frame):
    F = _reference_deformation(sim.F[frame], MAX_SPLAT_STRETCH, sim.rotation_free).double()
    x, X, Xg = sim.x[frame].double(), sim.rest_particles.double(), sim.rest.means.double()
    nb, w = sim.neighbours, sim.weights.double()
    rest_d = (X[nb] - X[nb[:, :1]]).norm(dim=-1)
    now_d = (x[nb] - x[nb[:, :1]]).norm(dim=-1)
    w = torch.where(now_d <= 2.0 * rest_d + sim.stats["particle_spacing"], w, torch.zeros_like(w))
    w[:, 0] = w[:, 0].clamp_min(1e-6)
    w = w / w.sum(1, keepdim=True)
    means = (w[..., None] * (x[nb] + (F[nb] @ (Xg[:, None, :] - X[nb])[..., None])[..., 0])).sum(1)
    Fg = (w[..., None, None] * F[nb]).sum(1)
    cov = sim.rest.covariance().double()
    own = sim.liquid[nb[:, 0]]
    s = torch.linalg.eigvalsh(cov[own]).clamp_min(0).sqrt()
    cov[own] = (s[:, 1] * s[:, 2])[:, None, None] * torch.eye(3, dtype=torch.float64)
    return means, Fg @ cov @ Fg.transpose(-1, -2)


def test_gaussians_at_matches_the_direct_formula():
    sim = _sim(torch.Generator().manual_seed(2))
    for frame in range(sim.num_frames):
        g = sim.gaussians_at(frame)
        means, covars = _reference_pose(sim, frame)
        # float32 outputs: positions to a micron at metres from the origin, covariances to 1e-5 relative.
        assert (g.means.double() - means).abs().max() < 1e-6
        assert (g.covars.double() - covars).abs().max() < 1e-5 * covars.abs().max()


def test_the_cached_rest_state_is_not_pickled_and_is_rebuilt():
    sim = _sim(torch.Generator().manual_seed(3))
    first = sim.gaussians_at(1)
    assert "_rest_cache" in sim.__dict__
    copy = pickle.loads(pickle.dumps(sim))
    assert "_rest_cache" not in copy.__dict__
    again = copy.gaussians_at(1)
    assert torch.equal(first.means, again.means) and torch.equal(first.covars, again.covars)


def test_compiled_and_pytorch_posing_agree_and_threads_do_not_matter():
    """gaussians_at poses float32 CPU frames with the compiled kernel (sim/pose.py); the PyTorch formula
    (``_pose_torch``) serves every other device and dtype. Both meet the direct formula (above for the
    compiled one), on a scene with neighbours and on one where each Gaussian follows its own particle only;
    the kernel's result is the same for any number of threads (each Gaussian is one thread's work)."""
    from physmotion_core.sim.pose import pose_gaussians
    from physmotion_core.types.results import pose_on_cpu

    sim = _sim(torch.Generator().manual_seed(4), N=9000)
    assert pose_on_cpu(sim.x[0], sim.F[0], sim.rest.means, sim.rest.means.dtype)
    for frame in range(sim.num_frames):
        F = splat_deformation(sim.F[frame], MAX_SPLAT_STRETCH, sim.rotation_free)
        rest = sim._rest_state()
        m_t, c_t = sim._pose_torch(sim.x[frame], F, rest)
        means, covars = _reference_pose(sim, frame)
        assert (m_t.double() - means).abs().max() < 1e-6
        assert (c_t.double() - covars).abs().max() < 1e-5 * covars.abs().max()
        args = (sim.x[frame], sim.rest_particles, F, sim.neighbours, sim.weights, rest["rest_d"], 0.01,
                rest["centre"], sim.rest.means, rest["cov"])
        one, three = pose_gaussians(*args, threads=1), pose_gaussians(*args, threads=3)
        assert torch.equal(one[0], three[0]) and torch.equal(one[1], three[1])
    solo = _sim(torch.Generator().manual_seed(5))
    solo.neighbours, solo.weights = None, None
    g = solo.gaussians_at(1)
    F = splat_deformation(solo.F[1], MAX_SPLAT_STRETCH, solo.rotation_free)
    m_t, c_t = solo._pose_torch(solo.x[1], F, solo._rest_state())
    assert (g.means - m_t).abs().max() < 1e-6
    assert (g.covars - c_t).abs().max() <= 1e-5 * c_t.abs().max()
    # x_g = x_k + F_k (X_g - X_k) for the Gaussian's own particle k, written out.
    k = solo.binding
    direct = solo.x[1][k].double() + (F[k].double() @ (solo.rest.means.double() - solo.rest_particles[k].double())[..., None])[..., 0]
    assert (g.means.double() - direct).abs().max() < 1e-6
