"""Controls for the Wan video models (physmotion_core/controls.py, nodes/video_control.py), checked on an
analytic scene: a textured rigid cube translating at a known velocity and spinning about the vertical
axis at a known rate, whose SimResult is built directly (every particle's position is known in closed
form at any time), rendered through a pinhole camera."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from physmotion_core import controls as C
from physmotion_core.errors import InputError
from physmotion_core.render.frames import render_frames
from physmotion_core.types import Camera, Gaussians, Material, SimResult

SIDE = 0.3
GRID = 13  # particles (= Gaussians) per cube edge: spacing 0.025 m
SPACING = SIDE / (GRID - 1)


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    # The renders here are small; on a busy 2-core machine two torch threads spin against each other.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def rot_y(a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)


CENTRE = torch.tensor([0.0, SIDE / 2, 0.0], dtype=torch.float64)


def rest_points() -> torch.Tensor:
    lin = torch.linspace(-SIDE / 2, SIDE / 2, GRID, dtype=torch.float64)
    return torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3) + CENTRE


def analytic(X: torch.Tensor, t: float, v, omega: float) -> torch.Tensor:
    """Positions at time t of rest points X of the cube: x = c + v t + R_y(omega t) (X - c)."""
    return CENTRE + torch.tensor(v, dtype=torch.float64) * t + (X.double() - CENTRE) @ rot_y(omega * t).T


def cube_sim(v=(0.15, 0.05, 0.0), omega=1.0, frames=48, fps=24.0, scale=0.45, seed=0) -> SimResult:
    X = rest_points()
    n = X.shape[0]
    rgb = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed))
    rest = Gaussians.from_rgb(X.float(), rgb, torch.full((n, 3), scale * SPACING), torch.full((n,), 0.95))
    t = torch.arange(frames, dtype=torch.float64) / fps
    x = torch.stack([analytic(X, float(tt), v, omega) for tt in t]).float()
    F = torch.stack([rot_y(omega * float(tt)) for tt in t]).float()[:, None].expand(-1, n, -1, -1).contiguous()
    return SimResult(rest=rest, times=t, x=x, F=F, binding=torch.arange(n), rest_particles=X.float(),
                     material=Material(), stats={"particle_spacing": SPACING})


def camera(width=192, height=128) -> Camera:
    return Camera.look_at((0.0, 0.35, 1.3), (0.0, 0.15, 0.0), width=width, height=height, fov_y_deg=40)


V, OMEGA = (0.15, 0.05, 0.0), 1.0


@pytest.fixture(scope="module")
def clip():
    """48 frames at 24 fps resampled to Wan's 16 fps x 33 frames, rendered, tracked."""
    sim = cube_sim(V, OMEGA)
    cam = camera()
    rs = C.resample_simulation(sim, C.WAN_FPS)
    frames = render_frames(rs, cam)
    tracks = C.point_tracks(rs, frames, cam, 48, background_points=4)
    return sim, rs, cam, frames, tracks


# ---------------------------------------------------------------------------------------------
# The upstream parser, re-derived from ComfyUI 0.3.64's comfy_extras/nodes_wan.py (commit
# 637221995f7424a561bd825de3e61ea117dfe1e3): pad_pts pads/truncates each track to 121 samples with
# visibility 1 for the listed points and 0 for the padding; process_tracks keeps sample 0 and, of
# the other 120, repeat_interleave(b)[1::a] with a = 120/gcd(120, F), b = F/gcd(120, F), F = length-1.
# ---------------------------------------------------------------------------------------------


def upstream_frames(tracks_json: str, length: int) -> tuple[np.ndarray, np.ndarray]:
    """(length, N, 2) positions and (length, N) visibility the Wan node's model sees per output frame."""
    data = json.loads(tracks_json.replace("'", '"'))
    pts = np.zeros((len(data), 121, 3), np.float32)
    for n, tr in enumerate(data):
        arr = np.array([[p["x"], p["y"], 1] for p in tr], np.float32)[:121]
        pts[n, :len(arr)] = arr
    samples = torch.from_numpy(pts).permute(1, 0, 2)  # (121, N, 3)
    F = length - 1
    g = math.gcd(120, F)
    a, b = 120 // g, F // g
    rest = torch.repeat_interleave(samples[1:], b, dim=0)[1::a]
    out = torch.cat([samples[:1], rest]).numpy()
    assert out.shape[0] == length
    return out[..., :2], out[..., 2] > 0.5


def test_sample_rule_matches_the_upstream_index_selection():
    for length in (5, 9, 33, 49, 81, 125, 161):
        frame_of, read = C.wan_sample_frames(length)
        # Put the sample index in x and read back which sample each output frame gets.
        probe = json.dumps([[{"x": float(s), "y": 0.0} for s in range(121)]])
        got, _ = upstream_frames(probe, length)
        used = got[:, 0, 0].round().astype(int)
        assert set(used) == set(np.nonzero(read)[0]), length
        for s in set(used.tolist()):  # a sample stands for the middle of the frames that read it
            frames = np.nonzero(used == s)[0]
            assert frame_of[s] == pytest.approx(0.5 * (frames[0] + frames[-1])), (length, s, frames)
        shared, lag = C.wan_shared_samples(length)
        assert (shared, lag) == ((0, 0.0) if length <= 121 else (shared, lag))
        if length > 121:  # more frames than samples: some share, none is more than half its span off
            assert shared > 0 and 0 < lag <= 0.5 * (np.bincount(used).max() - 1) + 1e-9, (length, shared, lag)
        assert np.all(np.diff(frame_of) >= -1e-12)  # monotone in time
    # length - 1 a multiple of 120: a = 1 and [1::1] drops a frame upstream; refused here.
    probe = json.dumps([[{"x": float(s), "y": 0.0} for s in range(121)]])
    with pytest.raises(AssertionError):
        upstream_frames(probe, 121)
    with pytest.raises(InputError, match="one frame too few"):
        C.wan_sample_frames(121)


def test_center_crop_box_matches_common_upscale_rounding():
    # comfy.utils.common_upscale(crop="center"): 600x400 (1.5) to 832x480 (1.733) crops rows:
    # y = round((400 - 400 * (1.5 / 1.7333)) / 2) = round(26.92) = 27.
    assert C.center_crop_box(600, 400, 832, 480) == (0, 27, 600, 346)
    assert C.center_crop_box(400, 600, 832, 480) == (0, 185, 400, 230)
    assert C.center_crop_box(832, 480, 416, 240) == (0, 0, 832, 480)
    assert C.center_crop_box(1000, 400, 832, 480) == (153, 0, 694, 400)


def test_fit_camera_renders_what_the_cropped_photo_shows():
    sim = cube_sim(frames=1)
    cam = camera(300, 200)
    full = render_frames(sim, cam)
    fitted = render_frames(sim, C.fit_camera(cam, 160, 80))
    cropped = C.fit_images(full.alpha, 160, 80)
    a, b = fitted.alpha[0] > 0.5, cropped[0] > 0.5
    iou = float((a & b).sum()) / float((a | b).sum())
    assert iou > 0.95, iou
    # The camera as the crop: its principal point moved by the crop offset and scaled.
    x, y, w, h = C.center_crop_box(300, 200, 160, 80)
    fc = C.fit_camera(cam, 160, 80)
    assert fc.cy == pytest.approx((cam.cy - y) * 80 / h) and fc.fx == pytest.approx(cam.fx * 160 / w)


# ---------------------------------------------------------------------------------------------
# Time
# ---------------------------------------------------------------------------------------------


def test_resampling_24fps_48_frames_to_16fps_33_frames_keeps_the_trajectory():
    assert C.wan_length(48, 24.0, 16.0) == 33
    t_in = np.arange(48) / 24.0

    def curve(t):  # a swing and a fall: x'' bounded by (pi)^2 * 0.2 and 2 * 0.5
        t = np.asarray(t, np.float64)
        return np.stack([0.2 * np.sin(np.pi * t), 0.5 * t ** 2 - 0.3 * t, 0.1 * t], -1)

    values = torch.from_numpy(curve(t_in))
    out = C.resample_points(values, 24.0, 16.0, 33).numpy()
    t_out = np.arange(33) / 16.0
    assert out.shape == (33, 3)
    h = 1 / 24.0
    acc = np.array([0.2 * np.pi ** 2, 1.0, 0.0])
    err = np.abs(out - curve(t_out))
    inside = t_out <= t_in[-1]
    # Linear interpolation: |error| <= h^2/8 max|x''| between samples; the last frame (t = 2 s) lies one
    # input frame past the simulation (47/24 s) and is extrapolated: |error| <= h^2 max|x''|.
    assert np.all(err[inside] <= h ** 2 / 8 * acc + 1e-12), err[inside].max(0)
    assert np.all(err[~inside] <= h ** 2 * acc + 1e-12)
    # Frames that fall on simulated times are those exactly (every other one at 24 -> 16 fps).
    assert np.allclose(out[:32:2], values.numpy()[::3], atol=1e-12)
    # Holding the nearest frame instead would be ~10x further off: the bound is not loose.
    nearest = values.numpy()[np.minimum(np.round(t_out * 24).astype(int), 47)]
    assert np.abs(nearest - curve(t_out)).max() > 10 * err.max()


def test_resampled_simulation_is_at_the_model_clock(clip):
    sim, rs, *_ = clip
    assert rs.num_frames == 33 and float(rs.times[1]) == pytest.approx(1 / 16)
    X = sim.rest_particles
    r_omega2 = math.sqrt(2) * SIDE / 2 * OMEGA ** 2  # the largest centripetal acceleration, m/s^2
    h = 1 / 24.0
    for j in (0, 7, 16, 31, 32):
        exact = analytic(X, j / 16, V, OMEGA)
        # Linear interpolation between simulated frames: h^2/8 |a|; frame 32 (2.0 s) is one frame past the
        # last simulated one (47/24 s), extrapolated: h^2 |a|. Both well under 0.1 px here.
        bound = (h ** 2 if j == 32 else h ** 2 / 8) * r_omega2 + 2e-6
        assert float((rs.x[j].double() - exact).norm(dim=-1).max()) <= bound, j
    with pytest.raises(InputError, match="4k\\+1"):
        C.check_length(32)


# ---------------------------------------------------------------------------------------------
# Point tracks
# ---------------------------------------------------------------------------------------------


def test_tracks_are_the_projected_particle_positions(clip):
    _, rs, cam, frames, tracks = clip
    obj = tracks.particle >= 0
    assert int(obj.sum()) >= 40 and int((~obj).sum()) == 4
    X = rs.rest_particles[tracks.particle[obj]]
    worst = 0.0
    for j in range(tracks.num_frames):
        uv, _ = cam.project(analytic(X, j / 16, V, OMEGA))
        worst = max(worst, float((tracks.uv[j, obj].double() - uv).norm(dim=-1).max()))
    assert worst < 0.5, worst
    # The same through the JSON, read the way WanTrackToVideo reads it, at every output frame.
    text = C.wan_tracks_json(tracks, occlusion="keep")
    pos, vis = upstream_frames(text, 33)
    assert vis.all() and pos.shape == (33, tracks.num_points, 2)
    for j in range(33):
        uv, _ = cam.project(analytic(X, j / 16, V, OMEGA))
        assert float(np.abs(pos[j, obj.numpy()] - uv.numpy()).max()) < 0.5
    # Background anchors stay where they are and are never on the object.
    assert torch.equal(tracks.uv[:, ~obj], tracks.uv[:1, ~obj].expand(33, -1, -1))
    bx, by = tracks.uv[0, ~obj, 0].long(), tracks.uv[0, ~obj, 1].long()
    assert float(frames.alpha[:, by, bx].max()) < 0.05


def test_track_points_are_spread_evenly_over_the_silhouette(clip):
    _, _, _, frames, tracks = clip
    obj = tracks.particle >= 0
    uv0 = tracks.uv[0, obj]
    mask = frames.alpha[0] > 0.5
    assert bool(mask[uv0[:, 1].long(), uv0[:, 0].long()].all())
    d = torch.cdist(uv0, uv0) + torch.eye(len(uv0)) * 1e9
    nearest = d.min(1).values
    cell = math.sqrt(float(mask.sum()) / len(uv0))  # the spacing of an even grid of that many points
    # Farthest-point sampling: no two points closer than half a grid cell, none stranded far away.
    assert float(nearest.min()) > 0.5 * cell and float(nearest.max()) < 2.0 * cell, (nearest.min(), nearest.max(), cell)


def test_points_behind_the_object_are_invisible_and_their_tracks_end(clip):
    _, rs, cam, frames, tracks = clip
    X = rs.rest_particles.double()
    checked = {"front": 0, "back": 0}
    for n in torch.nonzero(tracks.particle >= 0)[:, 0].tolist():
        rel = (X[tracks.particle[n]] - CENTRE) / (SIDE / 2)
        on = rel.abs() > 0.99
        # Points within 1.5 particle spacings of an edge are at the particles' resolution; skip them.
        if int(on.sum()) != 1 or float(rel.abs()[~on].max()) > 1 - 1.5 * SPACING / (SIDE / 2):
            continue
        axis = int(on.nonzero()[0])
        normal0 = torch.zeros(3, dtype=torch.float64)
        normal0[axis] = float(torch.sign(rel[axis]))
        for j in range(tracks.num_frames):
            p = analytic(X[tracks.particle[n]][None], j / 16, V, OMEGA)[0]
            to_cam = cam.position.double() - p
            facing = float(rot_y(OMEGA * j / 16) @ normal0 @ to_cam / to_cam.norm())
            if facing > 0.3:
                checked["front"] += 1
                assert bool(tracks.visible[j, n]), (n, j, facing)
            elif facing < -0.1:  # its face turned away: the cube is between it and the camera
                checked["back"] += 1
                assert not bool(tracks.visible[j, n]), (n, j, facing)
    assert checked["front"] > 100 and checked["back"] > 50, checked
    # A point on the back face, directly: hidden; the front face centre: visible.
    back, front = CENTRE + torch.tensor([0, 0, -SIDE / 2]), CENTRE + torch.tensor([0, 0, SIDE / 2])
    uv, z = cam.project(torch.stack([back, front]))
    vis = C.visibility(uv[None], z[None], dataclasses.replace(frames, alpha=frames.alpha[:1], depth=frames.depth[:1]),
                       1.5 * SPACING)
    assert vis.tolist() == [[False, True]]
    # In the JSON a point ends its track at the first sample that shows it hidden.
    text = C.wan_tracks_json(tracks, occlusion="end")
    data = json.loads(text)
    frame_of, _ = C.wan_sample_frames(33)
    kept = [n for n in range(tracks.num_points) if bool(tracks.visible[0, n])]
    assert len(data) == len(kept)
    for tr, n in zip(data, kept):
        hidden = [j for j in range(33) if not bool(tracks.visible[j, n])]
        if not hidden:
            assert len(tr) == 121
        else:
            assert frame_of[len(tr) - 1] < hidden[0] <= math.ceil(frame_of[min(len(tr), 120)])
    _, vis_up = upstream_frames(text, 33)
    assert not vis_up.all()  # some points disappear behind the turning cube, as the parser reads it


def test_tracks_refuse_an_empty_first_frame():
    sim = cube_sim(frames=2)
    cam = Camera.look_at((0.0, 0.35, -1.3), (0.0, 0.35, -3.0), width=64, height=48)  # looking away
    frames = render_frames(sim, cam)
    with pytest.raises(InputError, match="not visible in the first frame"):
        C.point_tracks(sim, frames, cam, 8)


def test_draw_tracks_marks_the_points(clip):
    _, _, _, frames, tracks = clip
    img = C.draw_tracks(frames.rgb, tracks)
    assert img.shape == frames.rgb.shape
    changed = (img - frames.rgb.clamp(0, 1)).abs().sum(-1) > 0.05
    u, v = tracks.uv[0, 0].long()
    assert bool(changed[0, v - 1:v + 2, u - 1:u + 2].any())


# ---------------------------------------------------------------------------------------------
# Exact flow
# ---------------------------------------------------------------------------------------------


def test_exact_flow_warps_better_than_zero_flow_and_farneback():
    import cv2

    v, omega = (0.9, 0.3, 0.0), 6.0  # 4-10 px per frame and 14 degrees of spin: a real test for an estimator
    sim = cube_sim(v, omega, frames=6, scale=0.7)
    j = 4
    pair = dataclasses.replace(sim, times=sim.times[j:j + 2] - sim.times[j], x=sim.x[j:j + 2], F=sim.F[j:j + 2])
    cam = camera()
    frames = render_frames(pair, cam)
    fwd = C.exact_flow(pair, cam)
    bwd = C.exact_flow(pair, cam, direction="backward")
    assert fwd.flow.shape == (1, 128, 192, 2) and bool(fwd.valid.any())
    I0, I1 = frames.rgb[0].numpy(), frames.rgb[1].numpy()
    H, W = I0.shape[:2]
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))

    def sample(img, f):  # img at p + f(p), bilinear
        return cv2.remap(img, gx + f[..., 0], gy + f[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def inside(alpha):
        return cv2.erode((alpha > 0.5).numpy().astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)

    def gray(img):
        return cv2.cvtColor((np.clip(img, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)

    # Frame t warped by the exact flow reproduces frame t+1 (backward flow: frame t sampled at p + flow).
    m1 = inside(frames.alpha[1])
    err = {"exact": np.abs(sample(I0, bwd.flow[0].numpy()) - I1)[m1].mean(),
           "zero": np.abs(I0 - I1)[m1].mean(),
           "farneback": np.abs(sample(I0, cv2.calcOpticalFlowFarneback(gray(I1), gray(I0), None, 0.5, 3, 15, 3, 5,
                                                                        1.2, 0)) - I1)[m1].mean()}
    assert err["exact"] < 0.8 * err["farneback"] and err["exact"] < 0.2 * err["zero"], err
    # And the forward flow the other way round (frame t+1 sampled along it reproduces frame t).
    m0 = inside(frames.alpha[0])
    e_fwd = np.abs(sample(I1, fwd.flow[0].numpy()) - I0)[m0].mean()
    fb = cv2.calcOpticalFlowFarneback(gray(I0), gray(I1), None, 0.5, 3, 15, 3, 5, 1.2, 0)
    assert e_fwd < 0.8 * np.abs(sample(I1, fb) - I0)[m0].mean()
    # The flow is the rigid motion's: each visible pixel's surface point moved and projected again.
    ok = fwd.valid[0]
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    p = torch.stack([xs, ys], -1)[ok].double()
    X = cam.unproject(p, frames.depth[0][ok].double())
    t0, t1 = j / 24.0, (j + 1) / 24.0
    Xn = CENTRE + torch.tensor(v, dtype=torch.float64) * t1 + \
        (X - CENTRE - torch.tensor(v, dtype=torch.float64) * t0) @ rot_y(omega * (t1 - t0)).T
    uv, _ = cam.project(Xn)
    assert float((fwd.flow[0][ok].double() - (uv - p)).norm(dim=-1).max()) < 1e-3
    assert float(fwd.flow[0][~ok].abs().max()) == 0.0
    # The backward flow likewise, from frame t+1's pixels back to frame t.
    ok = bwd.valid[0]
    assert torch.equal(ok, frames.alpha[1] > 0.5)
    p = torch.stack([xs, ys], -1)[ok].double()
    X = cam.unproject(p, frames.depth[1][ok].double())
    Xp = CENTRE + torch.tensor(v, dtype=torch.float64) * t0 + \
        (X - CENTRE - torch.tensor(v, dtype=torch.float64) * t1) @ rot_y(omega * (t0 - t1)).T
    uv, _ = cam.project(Xp)
    assert float((bwd.flow[0][ok].double() - (uv - p)).norm(dim=-1).max()) < 1e-3


def test_one_render_gives_the_frames_and_the_flow(clip):
    """render_clip renders each frame once, with the flow's channels: its frames are render_frames' frames
    (to float round-off) and its flow is exact_flow's."""
    _, rs, cam, frames, _ = clip
    short = dataclasses.replace(rs, times=rs.times[:6], x=rs.x[:6], F=rs.F[:6])
    got, flow = C.render_clip(short, cam, flow="forward")
    for a, b in ((got.rgb, frames.rgb[:6]), (got.alpha, frames.alpha[:6]), (got.depth, frames.depth[:6])):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=0)
    assert got.fps == pytest.approx(16.0) and flow.flow.shape == (5, 128, 192, 2)
    alone = C.exact_flow(short, cam)
    assert torch.equal(alone.flow, flow.flow) and torch.equal(alone.valid, flow.valid)
    assert torch.equal(flow.valid, got.alpha[:5] > 0.5)
    plain, none = C.render_clip(short, cam)
    assert none is None and torch.allclose(plain.rgb, got.rgb, atol=2e-6)


def test_visibility_reads_only_the_pixels_around_the_points(clip):
    """The same answer as pooling the whole frames (3x3 farthest covered depth, any covered pixel), for
    points inside, on the border of and outside the frame."""
    _, _, cam, frames, _ = clip
    T, H, W = frames.alpha.shape
    gen = torch.Generator().manual_seed(0)
    uv = torch.stack([torch.rand(T, 300, generator=gen) * (W + 8) - 4, torch.rand(T, 300, generator=gen) * (H + 8) - 4], -1)
    uv[:, :4] = torch.tensor([[0.2, 0.3], [W - 0.1, H - 0.2], [0.5, H - 0.5], [W - 0.5, 0.5]])
    z = frames.depth.amax() * torch.rand(T, 300, generator=gen) * 1.2 - 0.05
    got = C.visibility(uv.double(), z.double(), frames, 0.02)
    covered = frames.alpha > 0.5
    near = torch.where(covered, frames.depth, torch.full_like(frames.depth, -float("inf")))
    near = torch.nn.functional.max_pool2d(near[:, None], 3, stride=1, padding=1)[:, 0]
    cov = torch.nn.functional.max_pool2d(covered.float()[:, None], 3, stride=1, padding=1)[:, 0] > 0
    ix, iy = torch.floor(uv[..., 0]).long(), torch.floor(uv[..., 1]).long()
    inside = (ix >= 0) & (ix < W) & (iy >= 0) & (iy < H) & (z > 0)
    cx, cy = ix.clamp(0, W - 1), iy.clamp(0, H - 1)
    t = torch.arange(T)[:, None].expand_as(cx)
    want = inside & cov[t, cy, cx] & (z.double() <= near[t, cy, cx] + 0.02)
    assert torch.equal(got, want) and 0 < int(got.sum()) < got.numel()


def test_splat_linear_part_is_the_clamped_deformation():
    from physmotion_core.types import MAX_SPLAT_STRETCH

    gen = torch.Generator().manual_seed(1)
    P = 400
    F = torch.linalg.matrix_exp(0.3 * torch.randn(P, 3, 3, generator=gen))
    F[:50] *= 4.0  # stretched past the clamp
    F[50:100] *= 0.2  # squashed past it
    F[100:110, 0] *= -1.0  # inverted
    F = F.float()
    sim = cube_sim(frames=2)
    sim = dataclasses.replace(sim, F=F[None].expand(2, -1, -1, -1).contiguous(),
                              rotation_free=torch.arange(P) % 7 == 0)
    # Against the clamp written out (every F through the SVD), not the shared shortcut both now use.
    U, S, Vh = torch.linalg.svd(F.double())
    S = torch.diag_embed(S.clamp(1.0 / MAX_SPLAT_STRETCH, MAX_SPLAT_STRETCH))
    want = torch.where(sim.rotation_free[:, None, None], Vh.transpose(-1, -2) @ S @ Vh, U @ S @ Vh)
    torch.testing.assert_close(C._splat_linear_part(sim, 1), want, atol=1e-6, rtol=1e-6)


def test_flow_colours_and_npz(tmp_path):
    f = torch.zeros(1, 4, 4, 2)
    f[0, 0, 0] = torch.tensor([3.0, 0.0])  # right: red
    f[0, 0, 1] = torch.tensor([0.0, -3.0])  # up (y down in images)
    col = C.flow_to_color(f)
    assert col[0, 1, 1].tolist() == [1.0, 1.0, 1.0]  # still = white
    assert col[0, 0, 0, 0] > 0.9 and col[0, 0, 0, 1] < 0.2 and col[0, 0, 0, 2] < 0.2
    assert not torch.allclose(col[0, 0, 0], col[0, 0, 1])
    assert torch.equal(C.flow_to_color(torch.zeros(2, 3, 5, 2)), torch.ones(2, 3, 5, 3))  # nothing moves: white
    # Converting only the moving pixels gives what converting every pixel gives (OpenCV's HSV wheel, here whole).
    import cv2

    g = torch.Generator().manual_seed(2)
    big = torch.randn(3, 20, 30, 2, generator=g) * 4
    big[torch.rand(3, 20, 30, generator=g) < 0.7] = 0.0  # a still background
    for top in (0.0, 2.5):
        fx, fy = big[..., 0].reshape(-1, 30).numpy(), big[..., 1].reshape(-1, 30).numpy()
        mag, ang = cv2.cartToPolar(fx, fy, angleInDegrees=True)
        peak = top if top > 0 else float(mag.max())
        hsv = np.stack([(ang * 0.5).astype(np.uint8), (np.minimum(mag * (1.0 / peak), 1.0) * 255.0).astype(np.uint8),
                        np.full(mag.shape, 255, np.uint8)], -1)
        whole = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).reshape(3, 20, 30, 3)
        assert torch.equal(C.flow_to_color(big, top), torch.from_numpy(whole).float() / 255.0)
    flow = C.Flow(flow=f, valid=f.norm(dim=-1) > 0, fps=16.0)
    path = C.save_flow_npz(tmp_path / "f.npz", flow, camera(8, 8))
    data = np.load(path)
    assert np.array_equal(data["flow"], f.numpy()) and data["valid"].sum() == 2 and float(data["fps"]) == 16.0
    assert data["K"].shape == (3, 3) and str(data["direction"]) == "forward"


# ---------------------------------------------------------------------------------------------
# Control videos
# ---------------------------------------------------------------------------------------------


def test_control_videos(clip):
    _, _, _, frames, _ = clip
    bg = torch.full((128, 192, 3), 0.25)
    v = C.control_videos(frames, bg, grow_mask=3)
    T = frames.alpha.shape[0]
    for t in (v.depth, v.render, v.blended, v.vace):
        assert t.shape == (T, 128, 192, 3) and float(t.min()) >= 0 and float(t.max()) <= 1
    obj = frames.alpha > 0.5
    assert bool(v.mask.bool()[obj].all()) and float(v.mask.sum()) > float(obj.sum())  # grown
    assert float(v.depth[~C._dilate(frames.alpha > 0.0039, 1)].max()) == 0.0  # no object: black
    # Near is bright: the front face's top edge is nearer than its bottom edge seen from above? use z order.
    inside = frames.alpha[0] > 0.99
    d, g = frames.depth[0][inside], v.depth[0][..., 0][inside]
    assert float(torch.corrcoef(torch.stack([d, g]))[0, 1]) < -0.9
    assert torch.allclose(v.vace[v.mask.bool()], v.depth[v.mask.bool()])
    assert torch.allclose(v.vace[~v.mask.bool()], v.blended[~v.mask.bool()])
    assert torch.allclose(v.blended[~C._dilate(frames.alpha > 0.0039, 1)], torch.tensor(0.25))
    with pytest.raises(InputError, match="multiple of 16"):
        C.check_size(100, 64)


# ---------------------------------------------------------------------------------------------
# Nodes
# ---------------------------------------------------------------------------------------------


def test_flow_node_saves_beside_the_preview_and_reports_a_failed_save(tmp_path, monkeypatch):
    """The Exact Flow node compresses its .npz on a second thread while it makes the preview: the file is
    complete when the node returns, and a failed save is the node's error, not lost in the thread."""
    from comfy_harness import node_classes

    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path / "temp"))
    node = node_classes()["PhysMotionExactFlow"]()
    common = dict(simulation=cube_sim(frames=12), camera=camera(300, 200), width=160, height=96, fps=16.0, length=9)
    flow, preview, path = node.run(**common, direction="forward", max_flow=0.0, filename_prefix="ok/f")["result"]
    with np.load(path) as z:
        assert np.array_equal(z["flow"], flow.flow.numpy()) and np.array_equal(z["valid"], flow.valid.numpy())

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(C, "save_flow_npz", full_disk)
    with pytest.raises(OSError, match="No space left"):
        node.run(**common, direction="forward", max_flow=0.0, filename_prefix="full/f")


def test_nodes_run_report_progress_and_cancel(tmp_path, monkeypatch):
    from comfy_harness import node_classes
    from fake_comfy import InterruptProcessingException, install_fake_comfy

    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path / "temp"))
    state = install_fake_comfy(monkeypatch)
    classes = node_classes()
    sim, cam = cube_sim(frames=12), camera(300, 200)
    common = dict(simulation=sim, camera=cam, width=160, height=96, fps=16.0, length=9)
    out = classes["PhysMotionPointTracks"]().run(**common, num_points=16, background_points=2, occlusion="end track",
                                                 background=torch.full((1, 200, 300, 3), 0.5))
    text, preview, w, h, n = out["result"]
    assert (w, h, n) == (160, 96, 9) and preview.shape == (9, 96, 160, 3)
    data = json.loads(text)
    assert 10 <= len(data) <= 18 and all(set(p) == {"x", "y"} for p in data[0])
    assert all(0 <= p["x"] < 160 and 0 <= p["y"] < 96 for p in data[0])
    assert state.updates and state.updates[-1] == (9, 9)  # the render's progress bar
    out = classes["PhysMotionControlVideos"]().run(**common, grow_mask=2)
    depth, render, mask, blended, vace, w, h, n = out["result"]
    assert depth.shape == (9, 96, 160, 3) and mask.shape == (9, 96, 160) and (w, h, n) == (160, 96, 9)
    rendered = len(state.updates)
    classes["PhysMotionControlVideos"]().run(**common, grow_mask=0)
    assert len(state.updates) == rendered  # the same simulation, clock and size: the render is reused
    classes["PhysMotionControlVideos"]().run(**{**common, "width": 176}, grow_mask=2)
    assert len(state.updates) > rendered  # another size renders again
    out = classes["PhysMotionExactFlow"]().run(**common, direction="forward", max_flow=0.0,
                                              filename_prefix="flows/cube")
    flow, preview, path = out["result"]
    assert flow.flow.shape == (8, 96, 160, 2) and preview.shape == (8, 96, 160, 3)
    assert np.load(path)["flow"].shape == (8, 96, 160, 2) and str(tmp_path / "flows") in path
    with pytest.raises(InputError, match="4k\\+1"):
        classes["PhysMotionControlVideos"]().run(**{**common, "length": 10}, grow_mask=0)
    # The flow of the clip just rendered comes from that render; two clips are kept (the tracks' half-size
    # preview clip beside the controls' full-size one).
    rendered = len(state.updates)
    out = classes["PhysMotionExactFlow"]().run(**common, direction="forward", max_flow=0.0, filename_prefix="x")
    assert torch.equal(out["result"][0].flow, flow.flow)
    assert len(state.updates) == rendered
    classes["PhysMotionPointTracks"]().run(**common, num_points=16, background_points=2, occlusion="keep",
                                           preview="coarse video")
    rendered = len(state.updates)
    classes["PhysMotionPointTracks"]().run(**common, num_points=8, background_points=0, occlusion="keep",
                                           preview="coarse video")
    assert len(state.updates) == rendered + 9  # the tracks' own progress (one step a frame); the clip is kept
    rendered = len(state.updates)
    classes["PhysMotionExactFlow"]().run(**common, direction="forward", max_flow=0.0, filename_prefix="y")
    assert len(state.updates) == rendered
    # A backward flow renders again, and Cancel stops that render at the next frame (a new simulation object
    # here, so nothing is reused).
    back = classes["PhysMotionExactFlow"]().run(**common, direction="backward", max_flow=0.0, filename_prefix="b")
    assert len(state.updates) > rendered and back["result"][0].direction == "backward"
    state.cancel_after = state.checks + 3
    with pytest.raises(InterruptProcessingException):
        classes["PhysMotionExactFlow"]().run(**{**common, "simulation": cube_sim(frames=12)}, direction="forward",
                                            max_flow=0.0, filename_prefix="x")
    assert state.checks == state.cancel_after + 1


def test_the_flow_channels_are_rendered_only_when_a_flow_node_follows(tmp_path, monkeypatch):
    """Run as ComfyUI runs it (hidden PROMPT and UNIQUE_ID), the controls node renders the exact flow's nine
    channels with the clip only when a PhysMotion Exact Flow node of the same prompt asks for the same clip
    (same simulation and camera links, size, clock and length), in the direction it asks; then the flow node
    renders nothing. Alone (the Wan VACE template), it renders colour and depth only. The tracks node renders
    no clip (``probe_tracks``), whatever else the prompt holds."""
    import sys

    from comfy_harness import node_classes
    from fake_comfy import install_fake_comfy

    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path / "temp"))
    install_fake_comfy(monkeypatch)
    classes = node_classes()
    VC = sys.modules[classes["PhysMotionPointTracks"].__module__]
    calls = []
    real = C.render_clip
    monkeypatch.setattr(C, "render_clip", lambda s, cam, **k: calls.append((cam.width, k.get("flow"))) or real(s, cam, **k))
    sim, cam = cube_sim(frames=12), camera(300, 200)
    clip = dict(width=160, height=96, fps=16.0, length=9)
    links = {"simulation": ["7", 0], "camera": ["3", 1]}
    prompt = {"20": {"class_type": "PhysMotionPointTracks", "inputs": {**links, **clip, "num_points": 8}},
              "21": {"class_type": "PhysMotionControlVideos", "inputs": {**links, **clip, "grow_mask": 0}}}
    tracks = dict(simulation=sim, camera=cam, **clip, num_points=8, background_points=0, occlusion="keep")
    classes["PhysMotionPointTracks"]().run(**tracks)
    classes["PhysMotionControlVideos"]().run(simulation=sim, camera=cam, **clip, grow_mask=0, prompt=prompt,
                                             unique_id="21")
    assert calls == [(160, None)]  # no clip for the tracks; the controls' without flow channels
    flow_node = {"class_type": "PhysMotionExactFlow", "inputs": {**links, **clip, "direction": "backward"}}
    assert VC._flow_follows({**prompt, "22": flow_node}, "21") == "backward"
    other_size = {**flow_node, "inputs": {**flow_node["inputs"], "width": 176}}
    assert VC._flow_follows({**prompt, "22": other_size}, "21") is None
    other_sim = {**flow_node, "inputs": {**flow_node["inputs"], "simulation": ["8", 0]}}
    assert VC._flow_follows({**prompt, "22": other_sim}, "21") is None
    linked = {**flow_node, "inputs": {**flow_node["inputs"], "width": ["5", 0]}}
    assert VC._flow_follows({**prompt, "22": linked}, "21") == "backward"  # may match at run time
    assert VC._flow_follows(None, None) == "forward"  # called without a prompt: as before
    sim2 = cube_sim(frames=12)
    out_c = classes["PhysMotionControlVideos"]().run(simulation=sim2, camera=cam, **clip, grow_mask=0,
                                                     prompt={**prompt, "22": flow_node}, unique_id="21")
    out = classes["PhysMotionExactFlow"]().run(simulation=sim2, camera=cam, **clip, direction="backward",
                                              max_flow=0.0, filename_prefix="f")
    assert calls[1:] == [(160, "backward")]  # the flow came with the controls' render
    assert out["result"][0].direction == "backward"
    # The flow's channels change none of the control videos.
    plain = classes["PhysMotionControlVideos"]().run(simulation=cube_sim(frames=12), camera=cam, **clip, grow_mask=0,
                                                     prompt=prompt, unique_id="21")
    for a, b in zip(out_c["result"][:5], plain["result"][:5]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_tracks_node_renders_no_clip_and_stays_exact(tmp_path, monkeypatch):
    """The tracks node renders no clip (``probe_tracks``: frame 0, then only the pixels around the points):
    the tracks are the particles projected through the camera (to the JSON's 2 decimals), and the points
    and their visibility are exactly those of ``point_tracks`` on a full-size render of the clip. The
    preview is full size; "coarse video" renders a half-size clip for it."""
    import json as _json

    from comfy_harness import node_classes
    from fake_comfy import install_fake_comfy

    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path / "temp"))
    install_fake_comfy(monkeypatch)
    classes = node_classes()
    sizes = []
    real = C.render_clip
    monkeypatch.setattr(C, "render_clip", lambda s, cam, **k: sizes.append((cam.width, cam.height)) or real(s, cam, **k))
    sim, cam = cube_sim(frames=12), camera(300, 200)
    clip = dict(width=160, height=96, fps=16.0, length=9)
    args = dict(simulation=sim, camera=cam, **clip, num_points=24, background_points=0, occlusion="keep")
    text, preview, w, h, n = classes["PhysMotionPointTracks"]().run(**args)["result"]
    assert sizes == [] and preview.shape == (9, 96, 160, 3) and (w, h) == (160, 96)
    data = np.array([[[p["x"], p["y"]] for p in track] for track in _json.loads(text)])
    rs = C.resample_simulation(sim, 16.0, 9)
    full_cam = C.fit_camera(cam, 160, 96)
    frames = real(rs, full_cam)[0]
    ref = C.point_tracks(rs, frames, full_cam, 24)
    uv, _ = full_cam.project(rs.x[:, ref.particle].reshape(-1, 3).double())
    uv = uv.reshape(9, -1, 2).numpy()
    assert data.shape[0] == ref.num_points
    assert np.abs(data[:, 0] - uv[0]).max() < 0.01 and np.abs(data[:, -1] - uv[-1]).max() < 0.01  # 2 decimals
    got, first = C.probe_tracks(rs, full_cam, 24)
    assert torch.equal(got.particle, ref.particle) and torch.equal(got.visible, ref.visible)
    assert torch.equal(got.uv, ref.uv)
    torch.testing.assert_close(first.rgb[0], frames.rgb[0], atol=1e-6, rtol=0)
    # The first frame of the preview is the first frame's render, the tracks drawn on it.
    assert float((preview[0] - C.draw_tracks(frames.rgb[:1].clamp(0, 1), dataclasses.replace(
        ref, uv=ref.uv[:1], visible=ref.visible[:1]))[0]).abs().max()) < 1e-5
    classes["PhysMotionPointTracks"]().run(**args, preview="coarse video")
    assert sizes == [(80, 48)]
    with pytest.raises(InputError, match="preview"):
        classes["PhysMotionPointTracks"]().run(**args, preview="video")


def test_probe_reads_the_pixels_a_whole_render_shows(clip):
    """``probe`` gives the alpha and depth of ``rasterize`` at the asked pixels (to float round-off), 0 at the
    others, and a footprint that holds every pixel the render reaches."""
    from physmotion_core.render.rasterize import probe, rasterize

    _, rs, cam, _, _ = clip
    gen = torch.Generator().manual_seed(1)
    for t in (0, 16, 32):
        g = rs.gaussians_at(t)
        full = rasterize(g, cam)
        asked = torch.rand(cam.height, cam.width, generator=gen) < 0.03
        asked[60:70, 90:100] = True  # a block on the cube, beside scattered pixels on and off it
        p = probe(g, cam, asked)
        assert float((p.alpha - full.alpha)[asked].abs().max()) < 1e-5
        assert float((p.depth - full.depth)[asked].abs().max()) < 1e-5
        assert float(p.alpha[~asked].abs().max()) == 0.0 and bool((full.alpha[asked] > 0.5).any())
        assert bool(p.footprint[full.alpha > 0].all()) and not bool(p.footprint.all())
    with pytest.raises(InputError, match="mask"):
        probe(g, cam, asked[:-1])


def test_track_points_match_point_tracks_on_the_rendered_clip(clip):
    """The library's render-free tracks: the same points, positions and visibility as ``point_tracks`` on the
    rendered clip; background anchors only where no splat ever reaches."""
    _, rs, cam, frames, tracks = clip
    got, first = C.probe_tracks(rs, cam, 48, background_points=4)
    obj = tracks.particle >= 0
    assert torch.equal(got.particle[:int(obj.sum())], tracks.particle[obj])
    assert torch.equal(got.uv[:, :int(obj.sum())], tracks.uv[:, obj])
    assert torch.equal(got.visible[:, :int(obj.sum())], tracks.visible[:, obj])
    bg = got.particle < 0
    assert int(bg.sum()) == 4 and bool(got.visible[:, bg].all())
    bx, by = got.uv[0, bg, 0].long(), got.uv[0, bg, 1].long()
    assert float(frames.alpha[:, by, bx].max()) == 0.0



def _coming_to_rest(rs: SimResult, stop: int) -> SimResult:
    """``rs`` with every frame from ``stop`` on posed as frame ``stop`` (the object at rest), and one frame in the
    middle of the motion repeated (a pause)."""
    x, F = rs.x.clone(), rs.F.clone()
    x[stop:], F[stop:] = x[stop], F[stop]
    x[5], F[5] = x[4], F[4]
    return dataclasses.replace(rs, x=x, F=F)


def test_frames_at_rest_are_copied_not_drawn_again(clip, monkeypatch):
    """A frame posed bit for bit as the one before it (SimResult.same_pose) gets that frame's render, colour,
    depth, flow and track visibility, exactly what drawing it again gives (checked with the reuse turned off),
    and the rasterizer is not called for it; on several threads too, whose blocks are balanced by the frames
    that need drawing."""
    import importlib

    R = importlib.import_module("physmotion_core.render.rasterize")  # the package exports the function by that name
    _, rs, cam, _, _ = clip
    sim = _coming_to_rest(rs, 20)
    T = sim.num_frames
    assert sim.same_pose(T - 1, 20) and sim.same_pose(5, 4) and not sim.same_pose(4, 3)
    drawn = T - (T - 1 - 20) - 1  # every frame but the repeats (frames 21.. and 5)
    calls = []
    real = R.rasterize
    monkeypatch.setattr(R, "rasterize", lambda *a, **k: calls.append(1) or real(*a, **k))
    results = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("PHYSMOTION_RENDER_THREADS", threads)
        calls.clear()
        frames = render_frames(sim, cam)
        assert len(calls) <= drawn + int(threads) - 1, (threads, len(calls))  # a block starts with a draw
        clips = {d: C.render_clip(sim, cam, flow=d) for d in ("forward", "backward")}
        tracks, _ = C.probe_tracks(sim, cam, 24, background_points=4)
        results[threads] = (frames, clips, tracks)
    monkeypatch.setattr(SimResult, "same_pose", lambda self, a, b: False)
    monkeypatch.delenv("PHYSMOTION_RENDER_THREADS")
    calls.clear()
    ref = render_frames(sim, cam)
    assert len(calls) == T
    ref_clips = {d: C.render_clip(sim, cam, flow=d) for d in ("forward", "backward")}
    ref_tracks, _ = C.probe_tracks(sim, cam, 24, background_points=4)
    for frames, clips, tracks in results.values():
        for k in ("rgb", "alpha", "depth"):
            assert torch.equal(getattr(frames, k), getattr(ref, k)), k
        for d, (cf, fl) in clips.items():
            rf, rfl = ref_clips[d]
            assert torch.equal(cf.rgb, rf.rgb) and torch.equal(cf.depth, rf.depth), d
            assert torch.equal(fl.flow, rfl.flow) and torch.equal(fl.valid, rfl.valid), d
        assert torch.equal(tracks.uv, ref_tracks.uv) and torch.equal(tracks.visible, ref_tracks.visible)
    # At rest nothing moves: the flow there is 0 where the object is (the exact map gives the pixel itself).
    fl = results["1"][1]["forward"][1]
    assert bool(fl.valid[25].any()) and float(fl.flow[25][fl.valid[25]].abs().max()) < 1e-3


def test_frame_blocks_balance_the_frames_that_need_drawing():
    from physmotion_core.render.frames import _block_bounds

    assert _block_bounds(17, 2) == [0, 8, 17]  # by count, as before
    assert _block_bounds(17, 2, [1] * 8 + [0] * 9) == [0, 4, 17]  # the resting tail costs nothing
    assert _block_bounds(33, 2, [1] * 22 + [0] * 11) == [0, 11, 33]
    b = _block_bounds(10, 3, [1, 0, 0, 1, 1, 0, 1, 1, 0, 0])
    assert b[0] == 0 and b[-1] == 10 and b == sorted(b)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_tracks_and_clip_match_the_cpu(clip):
    """On a GPU the tracks node probes and the controls render there (torch on CUDA, or gsplat for the clip):
    the same tracks as on the CPU but where a depth test sits within round-off of its tolerance, and the
    clip's alpha within a 1/255 step."""
    _, rs, cam, frames, _ = clip
    cpu, _ = C.probe_tracks(rs, cam, 48, background_points=4)
    gpu, _ = C.probe_tracks(rs, cam, 48, background_points=4, device="cuda")
    assert torch.equal(gpu.particle, cpu.particle) and torch.equal(gpu.uv, cpu.uv)
    assert float((gpu.visible != cpu.visible).float().mean()) <= 0.01
    got, _ = C.render_clip(rs, cam, device="cuda")
    assert float((got.alpha - frames.alpha).abs().max()) < 1.0 / 255.0


# ---------------------------------------------------------------------------------------------
# Templates
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, control, wan", [("wan_tracks_push_a_jelly", "PhysMotionPointTracks", "WanTrackToVideo"),
                                               ("wan_vace_torque_spin", "PhysMotionControlVideos", "WanVaceToVideo")])
def test_wan_templates_validate_and_are_wired_to_the_model_clock(name, control, wan):
    from comfy_harness import ROOT
    from comfy_schemas import TEMPLATE_MODEL_FILES, all_schemas

    from physmotion_core.comfy.workflow import validate_prompt_against_schemas

    prompt = json.loads((ROOT / "example_workflows" / "api" / f"{name}.json").read_text())
    assert validate_prompt_against_schemas(prompt, all_schemas(), TEMPLATE_MODEL_FILES) == []
    ids = {n["class_type"]: nid for nid, n in prompt.items()}
    ctl, model = prompt[ids[control]]["inputs"], prompt[ids[wan]]["inputs"]
    outs = dict(zip(all_schemas()[control]["output_name"], range(99)))
    for key in ("width", "height", "length"):  # the Wan node takes the size and length the controls were made at
        assert model[key] == [ids[control], outs[key]]
    sim = prompt[ids["PhysMotionMPMSimulate"]]["inputs"]
    # The clip the simulation fills at 16 fps, so no frame repeats the final state.
    assert ctl["fps"] == C.WAN_FPS and ctl["length"] == C.wan_length(sim["frames"], sim["fps"], ctl["fps"])
    C.check_size(ctl["width"], ctl["height"])
    if wan == "WanTrackToVideo":
        assert model["tracks"] == [ids[control], outs["tracks"]]
        C.wan_sample_frames(ctl["length"])  # a length the node's track resampling can take
        assert prompt[ids["CreateVideo"]]["inputs"]["fps"] == C.WAN_FPS
    else:
        assert model["control_video"] == [ids[control], outs["vace_control"]]
        assert model["control_masks"] == [ids[control], outs["mask"]]
        trim = prompt[ids["TrimVideoLatent"]]["inputs"]
        assert trim["trim_amount"] == [ids[wan], 3]  # VACE's reference frame is cut off before decoding


_UPSTREAM_SCRIPT = r"""
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import comfy.options
comfy.options.enable_args_parsing()
sys.argv = [sys.argv[0], "--cpu"]
from comfy_extras import nodes_wan as W
d = json.load(sys.stdin)
tracks = W.parse_json_tracks(d["tracks"])
arrs = np.stack([W.pad_pts(t) for t in tracks], 0)
out = W.process_tracks(arrs, (d["width"], d["height"]), d["length"] - 1).numpy()
xy = out[..., 1:3] * (min(d["width"], d["height"]) / 2) + np.array([d["width"], d["height"]]) / 2
json.dump({"xy": xy.tolist(), "visible": (out[..., 3] > 0).tolist()}, sys.stdout)
"""


@pytest.mark.skipif(not __import__("os").environ.get("COMFYUI_DIR"), reason="set COMFYUI_DIR to a ComfyUI checkout")
def test_real_comfyui_reads_the_tracks_as_the_particles_move(clip):
    """ComfyUI's own parse_json_tracks / pad_pts / process_tracks (in a subprocess, with its Python) read
    the JSON back to the analytic positions, and see each point exactly while it is visible."""
    import os
    import subprocess

    _, rs, cam, _, tracks = clip
    text = C.wan_tracks_json(tracks, occlusion="end")
    py = os.environ.get("COMFYUI_PYTHON", "python")
    res = subprocess.run([py, "-c", _UPSTREAM_SCRIPT, os.environ["COMFYUI_DIR"]], cwd=os.environ["COMFYUI_DIR"],
                         input=json.dumps({"tracks": text, "width": cam.width, "height": cam.height, "length": 33}),
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout.strip().splitlines()[-1])
    xy, vis = np.array(got["xy"]), np.array(got["visible"])
    kept = [n for n in range(tracks.num_points) if bool(tracks.visible[0, n])]
    X = rs.rest_particles[tracks.particle[kept].clamp_min(0)]
    obj = (tracks.particle[kept] >= 0).numpy()
    for j in range(33):
        uv, _ = cam.project(analytic(X, j / 16, V, OMEGA))
        seen = vis[j] & obj
        assert np.abs(xy[j][seen] - uv.numpy()[seen]).max() < 0.5, j
    first_hidden = [next((j for j in range(33) if not bool(tracks.visible[j, n])), 33) for n in kept]
    for i, fh in enumerate(first_hidden):
        assert vis[:fh, i].all() and not vis[fh:, i].any(), (i, fh)


def test_tracks_json_is_the_json_of_the_rounded_samples():
    """The tracks STRING, written without json.dumps (it took 0.15 s of a 1 s node), parses to exactly
    the samples rounded to 2 decimals, track by track, ending where "end" ends them, and stays valid
    JSON when a point crosses the camera's plane (±inf, NaN: written 1e6 px off the frame)."""
    rng = np.random.default_rng(3)
    T, N = 33, 7
    uv = torch.from_numpy(rng.uniform(-50, 900, size=(T, N, 2))).float()
    uv[5, 2] = float("inf")
    uv[6, 2, 1] = float("nan")
    vis = torch.from_numpy(rng.uniform(size=(T, N)) > 0.1)
    vis[:, 0] = True
    vis[0, 3] = False  # hidden from the start: no track under "end"
    vis[5:7, 2] = False
    tracks = C.Tracks(uv=uv, visible=vis, particle=torch.arange(N), width=832, height=480, fps=16.0)
    frame_of, _ = C.wan_sample_frames(T)
    f0 = np.floor(frame_of).astype(int).clip(0, T - 1)
    f1 = np.minimum(f0 + 1, T - 1)
    w = frame_of - f0
    ref = uv.double().numpy()
    ref = np.nan_to_num(ref[f0] * (1 - w)[:, None, None] + ref[f1] * w[:, None, None], nan=-1e6, posinf=1e6,
                        neginf=-1e6).clip(-1e6, 1e6)
    for occlusion in ("keep", "end"):
        data = json.loads(C.wan_tracks_json(tracks, occlusion=occlusion))
        kept = list(range(N)) if occlusion == "keep" else [n for n in range(N) if bool(vis[0, n])]
        assert len(data) == len(kept)
        for tr, n in zip(data, kept):
            assert len(tr) == 121 if occlusion == "keep" else 1 <= len(tr) <= 121
            got = np.array([[p["x"], p["y"]] for p in tr])
            want = ref[:len(tr), n]
            assert np.abs(got - want).max() <= 0.006, (occlusion, n)  # half the last decimal + float32
            assert np.array_equal(got, np.round(got, 2))
        if occlusion == "keep":
            assert max(abs(p["x"]) for p in data[2]) == 1e6
        else:
            assert len(data[0]) == 121 and len(data[kept.index(2)]) < 121


def test_rigid_frames_take_the_flow_from_depth_and_match_the_channels(monkeypatch):
    """A frame whose splats all move by one affine map (a rigid body) renders no flow channels: its flow is the map
    applied to the rendered surface point. It matches the composited channels (which the flag turns back on)
    within 1e-3 px; a deforming body, each splat its own map, still composites them (identical either way)."""
    import importlib

    R = importlib.import_module("physmotion_core.render.rasterize")  # the module (the package re-exports the function)
    seen = []
    real = R.rasterize
    monkeypatch.setattr(R, "rasterize", lambda g, cam, **k: seen.append(k.get("extra_features") is not None)
                        or real(g, cam, **k))
    cam = camera()
    rigid = C.resample_simulation(cube_sim(V, OMEGA, frames=8), C.WAN_FPS)
    flows = {}
    for flag in (True, False):
        monkeypatch.setattr(C, "ONE_MAP_FLOW", flag)
        seen.clear()
        frames, flows[flag] = C.render_clip(rigid, cam, flow="forward")
        assert seen == ([False] * rigid.num_frames if flag else [True] * (rigid.num_frames - 1) + [False])
    assert torch.equal(flows[True].valid, flows[False].valid) and bool(flows[True].valid.any())
    ok = flows[True].valid
    assert float((flows[True].flow - flows[False].flow)[ok].norm(dim=-1).max()) < 1e-3
    assert float(flows[True].flow[~ok].abs().max()) == 0.0
    # A sheared cube: F differs from particle to particle, so every frame composites the channels.
    sim = cube_sim((0.0, 0.0, 0.0), 0.0, frames=8)
    X = sim.rest_particles.double()
    shear = torch.zeros(3, 3, dtype=torch.float64)
    shear[0, 1] = 1.0
    k = (X[:, 0:1, None] - float(X[:, 0].mean())) * 4.0  # the shear rate grows across the cube
    Fs, xs = [], []
    for tt in sim.times.tolist():
        F = torch.eye(3, dtype=torch.float64) + k * tt * shear  # (n,3,3)
        xs.append(CENTRE + ((F @ (X - CENTRE)[..., None])[..., 0]))
        Fs.append(F)
    sheared = dataclasses.replace(sim, x=torch.stack(xs).float(), F=torch.stack(Fs).float())
    out = {}
    for flag in (True, False):
        monkeypatch.setattr(C, "ONE_MAP_FLOW", flag)
        seen.clear()
        out[flag] = C.render_clip(sheared, cam, flow="forward")[1]
        assert seen[:-1] == [True] * (sheared.num_frames - 1)
    assert torch.equal(out[True].flow, out[False].flow) and bool(out[True].valid.any())


def test_one_map_is_read_only_within_its_tolerance():
    cam = camera()
    n = 50
    A = torch.eye(3, dtype=torch.float64).expand(n, 3, 3).clone()
    ms = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) + 0.1 * torch.rand(n, 3, dtype=torch.float64)
    b = torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64).expand(n, 3).clone()
    A0, b0 = C._one_map(A, b, ms, cam)
    assert torch.equal(A0, A[0]) and torch.allclose(b0, b[0])
    b2 = b.clone()
    b2[0, 0] += 1e-3  # one splat moving 1 mm more at ~1 m: about 0.15 px at this focal length
    assert C._one_map(A, b2, ms, cam) is None
    A2 = A.clone()
    A2[3] = A2[3] @ rot_y(1e-3)  # one splat turning a milliradian more
    assert C._one_map(A2, b, ms, cam) is None
    assert C._one_map(A, b + 1e-9, ms, cam) is not None  # round-off is not a second map
