"""Anchors hold the region asked for and add no energy; damping keeps positions and F consistent
(issue 22). Everything runs through ``simulate()``, the user's path.

Hanging bar: a bar hanging from an Anchor (ν = 0, E = 1e5 Pa, ρ = 1000 kg/m³: c = 10 m/s),
released from rest under gravity, oscillates about its static stretch with the fixed-free period
4 L / c, L the free length from the held material's lower face down to the bar's bottom face, both
faces measured from the particles. (The anchor's box ends at y = 1.0, inside the fill's voxel row
0.99-1.045 m, whose particles all lie above 1.0 and are all held: the held material ends at 0.99 m.
An anchor selects particles, so its edge is known to a particle spacing, here 2.6 % of L; the bottom
face is measured from the particles the same way.)

Both are released stress-free (``preload=False``): the textbook answers are for a release from rest, and
since 2026-12-06 a body held still from the start is otherwise started in equilibrium (the gravity preload).

Cantilever: a horizontal beam (L/h = 4, ν = 0) clamped by an Anchor over one thickness, sagging
under its own weight (E sets the Euler–Bernoulli sag of the nominal beam, ≤ 2 % of L); a slender one
(L/h = 6 as filled) for the issue's Euler–Bernoulli check, where shear adds only 2 %.
"""

import functools
import math

import numpy as np

from physmotion_core.sim.simulate import simulate
from physmotion_core.types import Anchor, Conditions, Gravity, Material, Region, SimSettings
from physmotion_core.validate.stress import gaussian_box

G = 9.81

# -- hanging bar -------------------------------------------------------------------------------

BAR_L, BAR_H, BAR_E, BAR_RHO = 1.0, 0.2, 1e5, 1000.0
BAR_OMEGA1 = math.pi * math.sqrt(BAR_E / BAR_RHO) / (2 * BAR_L)
# Ten offsets of the grid against the bar, a tenth of a cell apart: domain_margin moves the grid's
# origin by (margin step) · (object size) = 0.01 · 1.1 m = 0.1 dx at grid_res 10 (dx = 0.11 m).
OFFSETS = tuple(0.30 + 0.01 * k for k in range(10))


def _crossings(t, u):
    s = np.sign(u)
    i = np.nonzero(s[:-1] * s[1:] < 0)[0]
    return t[i] - u[i] * (t[i + 1] - t[i]) / (u[i + 1] - u[i])


@functools.lru_cache(maxsize=None)
def _hanging_bar(margin: float, damping: float = 0.0):
    """Positions and F of the hanging bar, every frame (damping: in units of ω1; damped runs last 1 s
    at 24 fps, undamped ones 100 frames at 120 fps); the free length; the bottom layer."""
    g = gaussian_box((-BAR_H / 2, 0.0, -BAR_H / 2), (BAR_H / 2, BAR_L + 0.1, BAR_H / 2), (9, 45, 9))
    mat = Material(name="elastic", model="fixed_corotated", E=BAR_E, nu=0.0, density=BAR_RHO,
                   damping=damping * BAR_OMEGA1)
    top = Region("box", lo=(-1.0, BAR_L, -1.0), hi=(1.0, 5.0, 1.0))  # holds the top 10 cm
    fps, frames = (24.0, 24) if damping > 0 else (120.0, 100)
    res = simulate(g, mat, Conditions([Anchor(top), Gravity((0.0, -G, 0.0))]),
                   SimSettings(frames=frames, fps=fps, grid_res=10, domain_margin=margin, device="cpu",
                               rest_speed=0.0, preload=False), record_all=True)
    x, F = res.x.numpy().astype(np.float64), res.F.numpy().astype(np.float64)
    y0 = x[0, :, 1]
    s = res.stats["particle_spacing"]
    bottom = y0 < y0.min() + 0.5 * s  # the bottom layer of particles (they are jittered in their cells)
    bottom_face = y0[bottom].mean() - 0.5 * s
    top_face = y0[y0 > y0.max() - 0.5 * s].mean() + 0.5 * s
    held = y0 > BAR_L  # the particles the anchor's box selects
    held_face = y0[held & (y0 < y0[held].min() + 0.5 * s)].mean() - 0.5 * s  # their lowest layer's lower face
    return x, F, fps, held_face - bottom_face, top_face - bottom_face, bottom


def _period_error(margin: float) -> float:
    x, _, fps, L_free, _, bottom = _hanging_bar(margin)
    u = x[:, bottom, 1].mean(1) - x[0, bottom, 1].mean()
    c = _crossings(np.arange(len(u)) / fps, u - u.mean())
    assert len(c) >= 3
    period = 2.0 * np.polyfit(np.arange(len(c)), c, 1)[0]
    return period / (4.0 * L_free / math.sqrt(BAR_E / BAR_RHO)) - 1.0


def test_hanging_bar_period_at_10_cells():
    """The period at 10 cells, with the anchor's edge swept across a cell (10 grid offsets, ~10 s).

    Every grid node an anchored particle touched used to be held, 1.5 cells past the region, with
    stress-free held particles: the period came out −14 … −4 % (mean −8 %, from the box's edge) over
    these offsets. Then a node was held when the anchored particles carried ≥ 15 % of its mass: the
    clamp sat on a node and jumped by most of a cell as the grid slid past the edge, −3.2 … +4.5 %
    (mean +1.0 %) from the held face. Now the anchor puts the clamp on the edge between the nodes
    (kernels.anchor_update): measured −1.76, −1.85, −1.88, −1.71, −1.01, +0.29, +0.63, −0.40, −1.25,
    −1.69 % (mean −1.1 %, spread 2.5 %; 2-core AMD EPYC CPU, one thread; with the fill's earlier ±¼
    jitter −2.07 … +0.49 %, mean −1.2 %). The ringing never grows: its second
    half's peak-to-peak is 0.92-0.97 of its first's."""
    errs = np.array([_period_error(m) for m in OFFSETS])
    assert abs(errs.mean()) < 0.015, errs
    assert errs.max() - errs.min() < 0.035, errs
    for m in OFFSETS:
        x, _, _, _, _, bottom = _hanging_bar(m)
        u = x[:, bottom, 1].mean(1)
        half = len(u) // 2
        assert np.ptp(u[half:]) <= np.ptp(u[:half]), m


def test_hanging_bar_period_within_3_percent_at_every_grid_offset():
    """The issue's tolerance at every offset of the grid (the runs are shared with the test above):
    measured at most 1.88 % (the node rule: 4.5 %, 4 of 10 offsets beyond 3 %)."""
    errs = np.array([_period_error(m) for m in OFFSETS])
    assert np.abs(errs).max() < 0.03, errs


def test_damped_hanging_bar_settles_at_the_static_stretch():
    """Damped (c = ω1, 1 s), the bar settles with its bottom lowered by ρ g L² / (2 E), exact for this
    model (ν = 0: the Cauchy stress is E (λ − 1) on an unchanged cross-section), L from the held face.
    The static stretch goes as L², so it shows where the clamp is more plainly than the period:
    measured −4.5, −4.7, −4.6, −2.3, −1.7, +1.9, +1.0, −1.4, −3.3, −4.3 % over the ten offsets (~5 s;
    one thread). With the fill's earlier ±¼ jitter −3.9 … +3.5 %: the positions then stretched 2.2 %
    more than F (the test below), which hid part of the clamp's offset from the held face (the
    kernel's docstring: a fraction of a cell, depending on where the edge cuts the links).
    The old anchor: +13.6 … −5.4 %; before the links across the anchor's edge were weighted
    (kernels.link_weight), +21 % at the offset where the edge runs through a layer of nodes."""
    errs = []
    for m in OFFSETS:
        x, _, _, L_free, _, bottom = _hanging_bar(m, 1.0)
        u = -(x[-1, bottom, 1].mean() - x[0, bottom, 1].mean())
        errs.append(u / (BAR_RHO * G * L_free**2 / (2 * BAR_E)) - 1.0)
    errs = np.array(errs)
    assert np.abs(errs).max() < 0.05, errs


def _strain_ratio(x, F, dx, frame):
    """Strain from F over strain from the positions, away from the clamp (y0 < L − 1.5 dx): the mean
    of F_yy − 1 against the mean of du/dy0, u(y0) fitted by a cubic through every particle's
    displacement. Local, so it needs no estimate of where the bar's faces are."""
    y0 = x[0, :, 1]
    sel = y0 < BAR_L - 1.5 * dx
    p = np.polyfit(y0[sel], x[frame, sel, 1] - y0[sel], 3)
    return float((F[frame, sel, 1, 1] - 1.0).mean() / np.polyval(np.polyder(p), y0[sel]).mean())


def test_damping_does_not_move_the_static_answer():
    """Mass-proportional damping scales the velocity gradient that updates F as it scales the
    velocities, so it only takes energy out: the settled bar is the same whatever the damping, hence
    the undamped static answer (the limit of vanishing damping). With c = ω1 and c = 2 ω1 (ζ ≈ 0.5
    and 1 on the fundamental, 1 s; ~2 s of CPU for three grid offsets), the bottom's displacement
    agrees within 1 % (measured 0.15-0.31 %, what c = 2 ω1 has still to creep) and so does the strain
    from F relative to the positions' (measured 0.06-0.15 %). Damping only the velocities, as before
    issue 22, made F and the positions differ by 12 %."""
    dx = 1.1 / 10
    for margin in OFFSETS[::4]:
        settled = []
        for damping in (1.0, 2.0):
            x, F, _, _, _, bottom = _hanging_bar(margin, damping)
            settled.append((-(x[-1, bottom, 1].mean() - x[0, bottom, 1].mean()), _strain_ratio(x, F, dx, -1)))
        (u1, r1), (u2, r2) = settled
        assert abs(u2 / u1 - 1.0) < 0.01, (margin, u1, u2)
        assert abs(r2 / r1 - 1.0) < 0.01, (margin, r1, r2)


def test_damped_strain_from_positions_and_from_F_agree_within_1_percent():
    """The issue's 1 % between the strain from the positions and from F, damped (c = ω1) and settled
    (``_strain_ratio``: away from the clamp, no estimate of the faces needed), at three grid offsets.

    Measured (2-core AMD EPYC CPU, one thread) over all ten offsets: 0.9928-0.9954 (0.9954, 0.9949,
    0.9928 at the three tested here). It was 0.9748-0.9789 while the fill jittered each particle by up
    to ¼ spacing in its voxel and gave every particle the same volume: where particles lay farther
    apart the material was represented more thinly, strained more, and counted once in F's mean while
    it spanned more of the length the positions measure. The gap goes as the jitter squared (±0.15:
    0.989-0.991, ±0.125: 0.991-0.994, ±0.1: 0.993-0.995, none: 0.996-1.000); the fill now jitters by
    ±0.1 spacing. A 1-D model of the bar (quadratic B-splines, the kernels' anchor and transfers)
    showed the same: 0.975-0.983 at ±¼, 0.997-1.001 unjittered, a particle's strain correlating with
    its Voronoi length at r = +0.68. What it was not: the cubic fit (the stretch between neighbouring
    layers' mean positions gave 0.979 at ±¼), APIC's C against the true grid gradient Σ v ∇w, the free
    bottom's light nodes, damping (the same undamped) or the clamp region (left out here)."""
    for margin in OFFSETS[::4]:
        x, F, _, _, _, _ = _hanging_bar(margin, 1.0)
        ratio = _strain_ratio(x, F, 1.1 / 10, -1)
        assert abs(ratio - 1.0) < 0.01, (margin, ratio)


# -- cantilever --------------------------------------------------------------------------------


def _cantilever(cells: int, periods: float, frames_per_period: int, damping: float, sag: float,
                length: float = 4.0, margin: float = 0.2):
    """Tip deflection (m) every frame of the anchored cantilever, with its Euler–Bernoulli and
    Timoshenko static deflections for the beam the particles make (the fill sets the faces: its
    thickness, width and free length are measured from the particle layers, the free length from
    the anchor's edge x = 0). The Gaussians span a free length ``length`` · h, h = 0.05 m, and
    ``cells`` grid cells through h (the fill adds about a particle layer on each face: 4 cells of
    Gaussians fill 5); ``margin`` is the domain's. E is set so that the nominal beam's EB tip
    deflection is ``sag`` · L."""
    h, rho = 0.05, 1000.0
    L = length * h
    W = 0.5 * h  # width along z: with ν = 0 it scales the load and the stiffness together
    E = 3 * rho * G * L**3 / (2 * sag * h**2)
    clamp = h  # the anchored length
    dx = (L + clamp) / round((L + clamp) / (h / cells))

    def n(extent):  # Gaussians a quarter cell apart
        return max(2, round(extent / (dx / 4)) + 1)

    g = gaussian_box((-clamp, 0.0, 0.0), (L, h, W), (n(L + clamp), n(h), n(W)))
    T1 = 2 * math.pi / (1.875**2 * math.sqrt(E * h**2 / 12 / rho) / L**2)  # nominal EB first period
    mat = Material(name="beam", model="fixed_corotated", E=E, nu=0.0, density=rho, damping=damping * 2 * math.pi / T1)
    held = Region("box", lo=(-10.0, -10.0, -10.0), hi=(0.0, 10.0, 10.0))  # everything left of x = 0
    fps = frames_per_period / T1
    res = simulate(g, mat, Conditions([Anchor(held), Gravity((0.0, -G, 0.0))]),
                   SimSettings(frames=int(periods * frames_per_period) + 1, fps=fps, grid_res=round((L + clamp) / dx),
                               domain_margin=margin, device="cpu", rest_speed=0.0, preload=False), record_all=True)
    x = res.x.numpy().astype(np.float64)
    s = res.stats["particle_spacing"]

    def faces(a):
        v = x[0, :, a]
        return v[v < v.min() + 0.5 * s].mean() - 0.5 * s, v[v > v.max() - 0.5 * s].mean() + 0.5 * s

    (_, L), (y_lo, y_hi), (z_lo, z_hi) = faces(0), faces(1), faces(2)
    h, W = y_hi - y_lo, z_hi - z_lo
    tip = x[0, :, 0] > x[0, :, 0].max() - s
    d = -(x[:, tip, 1].mean(1) - x[0, tip, 1].mean())
    q, I = rho * G * h * W, W * h**3 / 12
    eb = q * L**4 / (8 * E * I)
    timoshenko = eb + q * L**2 / (2 * (5 / 6) * (E / 2) * h * W)  # shear: κ = 5/6, G = E/2 (ν = 0)
    return d, fps, eb, timoshenko


def _period_means(d, fps):
    """The mean of d over each whole period of its oscillation (between alternate crossings of its mean)."""
    t = np.arange(len(d)) / fps
    c = _crossings(t, d - d.mean())
    means = []
    for k in range(0, len(c) - 2, 2):
        m = (t >= c[k]) & (t < c[k + 2])
        means.append(np.trapezoid(d[m], t[m]) / (t[m][-1] - t[m][0]))
    return np.array(means)


def test_anchored_cantilever_does_not_creep():
    """Undamped, 4 cells through the thickness, tip sag 2 % of L, 6 bending periods (~10 s): the
    mean tip deflection over each whole period stays within 2 % of the first period's (measured
    +0.07, +0.38, +0.33, +0.52, +0.43 %; with the anchor that held whole nodes +0.5, +1.0, +0.7, +0.2,
    +0.5 %: it rises and falls, a slow beat, not a creep). What used to creep was not the anchor (the
    anchors crept alike) but F's float32 update, worse the smaller the strain: see the next test. The
    first period's mean is 0.991 of Timoshenko (within 5 %, asserted; 0.957 with the clamp on a node)."""
    d, fps, eb, timoshenko = _cantilever(cells=4, periods=6, frames_per_period=24, damping=0.0, sag=0.02)
    means = _period_means(d, fps)
    assert len(means) >= 5
    drift = means / means[0] - 1.0
    assert np.abs(drift).max() < 0.02, drift
    assert abs(means[0] / timoshenko - 1.0) < 0.05, (means[0], timoshenko, eb)


def test_anchored_cantilever_does_not_creep_at_small_strain():
    """The same beam with a 0.2 % sag (~10 s): within 2 % over 6 periods (measured −0.02, +0.26, +0.11,
    +0.31, +0.12 %; with the anchor that held whole nodes +0.6, +0.3, -0.0, +0.4, +0.2 %). With F updated as (I + dt C) F it crept
    +9.6 % here (+2.2 % at 1 %): forming I + dt C in float32 rounds dt C, a few 1e-7 per substep at this
    strain, to float32's step of 1.2e-7 at 1 (doubled at half the CFL, the same with neo-Hookean and with
    the old anchor). g2p now forms F + dt (C F)."""
    d, fps, _, _ = _cantilever(cells=4, periods=6, frames_per_period=24, damping=0.0, sag=0.002)
    means = _period_means(d, fps)
    drift = means / means[0] - 1.0
    assert np.abs(drift).max() < 0.02, drift


def test_damped_anchored_cantilever_settles_at_the_static_deflection():
    """Damped (mass-proportional, c = ω1), 4 cells through the thickness, tip sag 1 % of L, settled
    over 2 bending periods (~5 s): measured 0.981 of Timoshenko, the reference that counts here (the
    filled beam is 0.0625 m thick, L/h = 3.3, and shear adds 7.4 % to Euler–Bernoulli), and 1.054 of
    Euler–Bernoulli, which omits shear and so bounds the deflection from below. (With the clamp on a
    node, inside the held material, it settled stiffer: 0.956 of Timoshenko, 1.027 of EB, and this test
    also asked for EB within 5 %, which a beam this short within 5 % of Timoshenko cannot meet; the
    issue's EB check is the slender beam's, below.) Over five grid offsets spanning about half a cell
    (domain_margin 0.2 … 0.2229): 0.981, 1.002, 1.023, 1.013, 1.036 of Timoshenko (1.054 … 1.113 of EB).
    Measured against the beam the particles make: the fill makes it thicker than the Gaussians
    (0.0625 m for 0.05 m, 0.037 m wide for 0.025 m, 0.206 m free for 0.2 m), which read as 0.75 of EB,
    "locking", against the nominal beam."""
    d, _, eb, timoshenko = _cantilever(cells=4, periods=2, frames_per_period=12, damping=1.0, sag=0.01)
    assert d[-1] > eb, (d[-1], eb)
    assert abs(d[-1] / timoshenko - 1.0) < 0.05, (d[-1], timoshenko)


def test_damped_slender_cantilever_settles_within_5_percent_of_euler_bernoulli():
    """The issue's check with a beam slender enough for Euler–Bernoulli to be the reference: L/h = 6.09
    as filled (Gaussians 0.369 m free by 0.05 m, 4 cells through them, 5 as filled), where shear adds
    2.2 % (0.8 (h/L)², ν = 0, κ = 5/6). Damped (c = ω1 of the nominal beam), tip sag 5 % of L,
    2 bending periods (19-22 s on a 2-core AMD EPYC CPU, one thread): settles at 1.042 of EB and 1.020 of
    Timoshenko (its last quarter period moved 0.16 %). The large-deflection elastica is 0.998 of EB's
    linear sag at 5 %.

    Not a tight result; what was measured (2-core AMD EPYC CPU):
    * Grid offset: over five offsets a fifth of a cell apart (domain_margin 0.2, 0.2058, 0.2116, 0.2174,
      0.2232) 1.042, 1.040, 1.070, 1.056, 1.035 of EB (1.020, 1.018, 1.048, 1.034, 1.013 of Timoshenko):
      EB within 5 % at 3 of 5 offsets, Timoshenko at all 5. At 6 cells through the filled thickness
      (L/h 5.93, ~45 s) 1.014 and 1.047 of EB at two of them (0.2, 0.2116).
    * Thinner: L/h 8.09 with 4 cells through the filled thickness (~20 s) gives 1.034, 1.108, 1.078,
      1.077, 1.040, 1.053, 1.052 of EB over seven offsets (margins 0.2, 0.2057, 0.21, 0.2114, 0.2171,
      0.22, 0.2229): EB within 5 % at 2 of 7.
    * Small strain (the next test): before F's update was compensated (g2p's F_err), this beam at 1 %
      sag settled at 1.070 of EB (margin 0.2); the L/h 8 beam at 1 % was 1.124 after 2 periods and
      1.151 after 4, still rising, and at 0.2 % it overshot, then rose back above its unloaded position
      at a steady speed: the root's per-substep strain increment, below float32's step at 1, was
      rounded away when stored into F's diagonal. Compensated: 1.049 at 1 % and 1.044 at 5 % (this
      beam), 1.020 after 4 periods (the L/h 8 beam at 1 %)."""
    d, _, eb, timoshenko = _cantilever(cells=4, periods=2, frames_per_period=12, damping=1.0, sag=0.05,
                                       length=7.375)
    assert timoshenko / eb - 1.0 < 0.025, (timoshenko, eb)  # slender: EB is a meaningful reference
    assert abs(d[-1] / d[-4] - 1.0) < 0.005, d[-4:]  # settled
    assert abs(d[-1] / eb - 1.0) < 0.05, (d[-1], eb, timoshenko)
    assert abs(d[-1] / timoshenko - 1.0) < 0.05, (d[-1], timoshenko, eb)


def test_damped_slender_cantilever_at_small_strain_settles_as_at_large():
    """The same beam at 0.2 % sag (~20 s): linear elasticity, so the settled deflection over EB's does not
    depend on the load. Measured 1.049 of EB and 1.027 of Timoshenko (1.044 and 1.022 at 5 % sag), settled.
    Before g2p compensated F's float32 update (F_err) the strain increments near the clamp, below float32's
    resolution at 1, were rounded away: the beam overshot and then rose steadily back above its unloaded
    position (-0.035 of EB after 2 periods)."""
    d, _, eb, timoshenko = _cantilever(cells=4, periods=2, frames_per_period=12, damping=1.0, sag=0.002,
                                       length=7.375)
    assert abs(d[-1] / d[-4] - 1.0) < 0.005, d[-4:]
    assert abs(d[-1] / eb - 1.0) < 0.05, (d[-1], eb, timoshenko)
    assert abs(d[-1] / timoshenko - 1.0) < 0.05, (d[-1], timoshenko, eb)
