"""Types, .ply round trips, mp4 writing, compositing."""

import numpy as np
import pytest
import torch

from physmotion_core.blend import composite
from physmotion_core.errors import InputError
from physmotion_core.ply import read_ply, write_ply
from physmotion_core.types import Camera, Gaussians, quat_to_rotmat, rotmat_to_quat
from physmotion_core.video import read_video, write_mp4


def _random_gaussians(n=200, k=1):
    q = torch.nn.functional.normalize(torch.randn(n, 4), dim=-1)
    q = torch.where(q[:, :1] < 0, -q, q)
    return Gaussians(
        means=torch.randn(n, 3),
        quats=q,
        scales=torch.rand(n, 3) * 0.05 + 1e-3,
        opacities=torch.rand(n) * 0.98 + 0.01,
        sh=torch.randn(n, k, 3),
    )


@pytest.mark.parametrize("k", [1, 4, 16])
def test_ply_round_trip(tmp_path, k):
    g = _random_gaussians(k=k)
    p = write_ply(tmp_path / "a.ply", g)
    h = read_ply(p)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.allclose(getattr(g, name), getattr(h, name), rtol=1e-5, atol=1e-6), name
    # Standard 3DGS header: properties other viewers expect, in order.
    header = p.read_bytes().split(b"end_header")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(props) == 17 + 3 * (k - 1)


def test_ply_stores_logit_opacity_and_log_scale(tmp_path):
    g = _random_gaussians(n=5)
    p = write_ply(tmp_path / "b.ply", g)
    raw = p.read_bytes()
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n"):]
    arr = np.frombuffer(body, dtype="<f4").reshape(5, 17)
    assert np.allclose(arr[:, 10:13], np.log(g.scales.numpy()), atol=1e-5)
    assert np.allclose(1 / (1 + np.exp(-arr[:, 9])), g.opacities.numpy(), atol=1e-5)


def test_ply_round_trip_of_deformed_covariance(tmp_path):
    g = _random_gaussians(n=50)
    F = torch.eye(3) + 0.3 * torch.randn(50, 3, 3)
    cov = F @ g.covariance() @ F.transpose(1, 2)
    deformed = Gaussians(g.means, g.quats, g.scales, g.opacities, g.sh, covars=cov)
    h = read_ply(write_ply(tmp_path / "c.ply", deformed))
    assert torch.allclose(h.covariance(), cov, rtol=1e-3, atol=1e-7)


def test_ply_errors(tmp_path):
    bad = tmp_path / "mesh.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
                    b"property float y\nproperty float z\nend_header\n" + b"\0" * 12)
    with pytest.raises(InputError, match="missing properties"):
        read_ply(bad)
    g = _random_gaussians(n=10)
    p = write_ply(tmp_path / "t.ply", g)
    data = p.read_bytes()
    p.write_bytes(data[:-20])
    with pytest.raises(InputError, match="truncated"):
        read_ply(p)
    with pytest.raises(InputError, match="not a .ply"):
        (tmp_path / "x.ply").write_bytes(b"hello")
        read_ply(tmp_path / "x.ply")


def test_rotation_quaternion_round_trip():
    q = torch.nn.functional.normalize(torch.randn(500, 4, dtype=torch.float64), dim=-1)
    R = quat_to_rotmat(q)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(500, 3, 3), atol=1e-12)
    q2 = rotmat_to_quat(R)
    assert torch.allclose(quat_to_rotmat(q2), R, atol=1e-10)


def test_camera_projection_and_unprojection_are_inverse():
    cam = Camera.look_at((0.3, 0.2, 2.0), (0, 0, 0), width=320, height=240, fov_y_deg=45)
    pts = torch.randn(100, 3) * 0.3
    uv, z = cam.project(pts)
    assert torch.allclose(cam.unproject(uv, z), pts, atol=1e-5)
    # The look-at target projects to the image centre.
    uv0, _ = cam.project(torch.zeros(1, 3))
    assert torch.allclose(uv0, torch.tensor([[160.0, 120.0]]), atol=1e-4)
    # +y world is up in the image (smaller v), +x right.
    cam2 = Camera.look_at((0, 0, 2), (0, 0, 0), width=100, height=100)
    uv, _ = cam2.project(torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]))
    assert uv[0, 0] > 50 and uv[1, 1] < 50


def test_mp4_round_trip(tmp_path):
    t, h, w = 12, 49, 65  # odd sizes are padded to even, never cropped
    frames = torch.zeros(t, h, w, 3)
    for i in range(t):  # a white square moving right
        frames[i, 20:30, 5 + 3 * i:15 + 3 * i] = 1.0
    p = write_mp4(tmp_path / "v.mp4", frames, fps=12)
    video, fps = read_video(p)
    assert video.shape == (t, h + 1, w + 1, 3)
    assert abs(fps - 12) < 1e-6
    xs = [np.nonzero(video[i, 22:28, :, 0].mean(0) > 128)[0].mean() for i in range(t)]
    assert np.allclose(np.diff(xs), 3.0, atol=0.6)
    assert not list(tmp_path.glob("*.tmp*")), "temporary file left behind"


def test_mp4_takes_8_bit_frames_as_they_are(tmp_path):
    """uint8 frames (a tensor or an array) are written as they are, not read as 0..1 floats; the same frames as
    floats rounded to 8 bits give the same file."""
    gen = torch.Generator().manual_seed(0)
    small = torch.rand(6, 4, 5, 3, generator=gen)
    frames = torch.nn.functional.interpolate(small.permute(0, 3, 1, 2), size=(32, 40), mode="bilinear",
                                             align_corners=False).permute(0, 2, 3, 1).contiguous()
    f8 = frames.mul(255.0).add(0.5).to(torch.uint8)
    a = write_mp4(tmp_path / "a.mp4", f8, fps=8, threads=1)
    b = write_mp4(tmp_path / "b.mp4", f8.numpy(), fps=8, threads=1)
    c = write_mp4(tmp_path / "c.mp4", frames, fps=8, threads=1)
    assert a.read_bytes() == b.read_bytes() == c.read_bytes()
    video, _ = read_video(a)
    # Lossy H.264 with 4:2:0 chroma on saturated colours: 5.2 levels of 255 on average (read as floats, the
    # 8-bit values would clip to white: ~130).
    assert float(np.abs(video.astype(np.float64) - f8.numpy()).mean()) < 8.0


def test_mp4_rejects_bad_frames(tmp_path):
    with pytest.raises(InputError):
        write_mp4(tmp_path / "v.mp4", torch.zeros(0, 8, 8, 3))
    with pytest.raises(InputError):
        write_mp4(tmp_path / "v.mp4", torch.full((2, 8, 8, 3), float("nan")))
    assert not (tmp_path / "v.mp4").exists()


def test_composite_formula():
    rgb = torch.tensor([[[[0.4, 0.2, 0.0]]]])  # premultiplied with alpha 0.5
    alpha = torch.tensor([[[0.5]]])
    bg = torch.tensor([[[0.0, 0.0, 1.0]]])
    out = composite(rgb, alpha, bg)
    assert torch.allclose(out, torch.tensor([[[[0.4, 0.2, 0.5]]]]))
    with pytest.raises(InputError):
        composite(rgb, alpha, torch.zeros(2, 2, 3))


def test_mp4_with_a_fixed_thread_count_is_reproducible(tmp_path):
    """threads=N makes the bytes a function of the frames alone (mbtree off, fixed slicing), also
    after other, different encodes ran in the same process (what changed libx264's default output)."""
    rng = np.random.default_rng(3)
    frames = rng.random((6, 64, 80, 3)).astype(np.float32)
    other = rng.random((9, 96, 128, 3)).astype(np.float32)
    first = write_mp4(tmp_path / "a.mp4", frames, fps=12, threads=1).read_bytes()
    for i in range(3):
        write_mp4(tmp_path / f"other{i}.mp4", other[i:], fps=24)
        again = write_mp4(tmp_path / f"b{i}.mp4", frames, fps=12, threads=1).read_bytes()
        assert again == first
    decoded, fps = read_video(tmp_path / "a.mp4")
    assert decoded.shape == (6, 64, 80, 3) and fps == pytest.approx(12)


def test_mp4_preset_is_applied_and_checked(tmp_path):
    """The x264 preset reaches the encoder (ultrafast, which turns CABAC off, writes a larger file for the same
    frames and crf, and decodes to the same motion); an unknown one is refused before anything is written."""
    import av

    t, h, w = 10, 48, 64
    frames = torch.zeros(t, h, w, 3)
    for i in range(t):
        frames[i, 10:30, 4 + 4 * i:20 + 4 * i] = torch.tensor([0.9, 0.5, 0.2])
    frames += 0.1 * torch.rand(t, h, w, 3, generator=torch.Generator().manual_seed(0))  # texture to code
    slow = write_mp4(tmp_path / "medium.mp4", frames, fps=12, crf=28)
    fast = write_mp4(tmp_path / "fast.mp4", frames, fps=12, crf=28, preset="ultrafast")
    assert fast.stat().st_size > slow.stat().st_size
    with av.open(str(fast)) as c:  # ultrafast: no CABAC, x264 records its options in the stream
        sei = bytes(next(iter(c.demux(c.streams.video[0]))))
    assert b"cabac=0" in sei
    video, _ = read_video(fast)
    assert video.shape == (t, h, w, 3)
    with pytest.raises(InputError, match="preset must be one of"):
        write_mp4(tmp_path / "bad.mp4", frames, fps=12, preset="turbo")
    assert not (tmp_path / "bad.mp4").exists()
