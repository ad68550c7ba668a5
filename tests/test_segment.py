"""Model-free segmentation (alpha / mask / GrabCut), background inpainting and image I/O."""


import cv2
import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.image_io import load_image, save_image, to_uint8
from physmotion_core.segment import (
    Segmentation,
    auto_box,
    clean_mask,
    default_dilate_px,
    inpaint_background,
    segment,
)


def _disk(h, w, cx, cy, r):
    yy, xx = np.mgrid[0:h, 0:w]
    return ((xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 <= r * r)


def _gradient_image(h, w):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([0.2 + 0.6 * xx / w, 0.3 + 0.4 * yy / h, 0.8 - 0.5 * xx / w], -1).astype(np.float32)


def _iou(a, b):
    a, b = np.asarray(a) > 0.5, np.asarray(b) > 0.5
    return (a & b).sum() / max(1, (a | b).sum())


# ----------------------------------------------------------------------------------------------
# image I/O
# ----------------------------------------------------------------------------------------------


def test_load_rgba_png_gives_rgb_and_alpha(tmp_path):
    h, w = 40, 50
    disk = _disk(h, w, 25, 20, 12)
    bgra = np.zeros((h, w, 4), np.uint8)
    bgra[..., 0], bgra[..., 1], bgra[..., 2] = 10, 20, 200  # BGR: a red image
    bgra[..., 3] = np.where(disk, 255, 0)
    path = tmp_path / "rgba.png"
    cv2.imwrite(str(path), bgra)
    rgb, alpha = load_image(path)
    assert rgb.shape == (h, w, 3) and rgb.dtype == torch.float32
    assert alpha is not None and alpha.shape == (h, w)
    assert torch.allclose(rgb[0, 0], torch.tensor([200, 20, 10]) / 255.0)
    assert torch.equal(alpha > 0.5, torch.from_numpy(disk))


def test_load_opaque_alpha_gray_and_16bit(tmp_path):
    bgra = np.full((8, 9, 4), 255, np.uint8)
    cv2.imwrite(str(tmp_path / "opaque.png"), bgra)
    rgb, alpha = load_image(tmp_path / "opaque.png")
    assert alpha is None and rgb.shape == (8, 9, 3)

    gray = np.arange(64, dtype=np.uint8).reshape(8, 8) * 4
    cv2.imwrite(str(tmp_path / "gray.png"), gray)
    rgb, alpha = load_image(tmp_path / "gray.png")
    assert alpha is None and rgb.shape == (8, 8, 3)
    assert torch.equal(rgb[..., 0], rgb[..., 2])
    assert abs(float(rgb[7, 7, 1]) - 252 / 255) < 1e-6

    deep = np.full((4, 4, 3), 40000, np.uint16)
    deep[..., 0] = 1000  # blue channel in BGR
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    rgb, _ = load_image(tmp_path / "deep.png")
    assert abs(float(rgb[0, 0, 0]) - 40000 / 65535) < 1e-6
    assert abs(float(rgb[0, 0, 2]) - 1000 / 65535) < 1e-6


def test_load_missing_or_broken_file_names_the_path(tmp_path):
    with pytest.raises(InputError, match="nope.png"):
        load_image(tmp_path / "nope.png")
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not an image at all")
    with pytest.raises(InputError, match="broken.png"):
        load_image(bad)


def test_save_image_roundtrip_is_atomic(tmp_path):
    img = torch.rand(12, 16, 3)
    path = save_image(tmp_path / "sub" / "out.png", img)
    back, alpha = load_image(path)
    assert alpha is None
    assert torch.equal(torch.from_numpy(to_uint8(back)), torch.from_numpy(to_uint8(img)))
    assert sorted(p.name for p in path.parent.iterdir()) == ["out.png"]  # no temp file left
    with pytest.raises(InputError):
        save_image(tmp_path / "x.png", torch.rand(4, 4, 5))


# ----------------------------------------------------------------------------------------------
# segmentation paths
# ----------------------------------------------------------------------------------------------


def test_alpha_path_gives_the_disk_exactly(tmp_path):
    h, w = 64, 80
    disk = _disk(h, w, 40, 30, 18)
    bgra = np.zeros((h, w, 4), np.uint8)
    bgra[..., :3] = (cv2.GaussianBlur(np.random.rand(h, w, 3).astype(np.float32), (0, 0), 2) * 255).astype(np.uint8)
    bgra[..., 3] = np.where(disk, 255, 0)
    cv2.imwrite(str(tmp_path / "obj.png"), bgra)
    rgb, alpha = load_image(tmp_path / "obj.png")
    seg = segment(rgb, alpha=alpha)
    assert isinstance(seg, Segmentation) and seg.method == "alpha"
    assert seg.mask.dtype == torch.float32
    assert torch.equal(seg.mask.bool(), torch.from_numpy(disk))
    assert torch.equal(seg.foreground, rgb * seg.mask[..., None])
    ys, xs = np.nonzero(disk)
    assert seg.box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
    # An all-opaque alpha says nothing: "auto" falls through to the given mask.
    seg2 = segment(rgb, alpha=torch.ones(h, w), mask=torch.from_numpy(disk).float())
    assert seg2.method == "mask"


def test_mask_path_accepts_comfy_shapes():
    h, w = 48, 64
    img = torch.rand(1, h, w, 3)  # a ComfyUI IMAGE batch of one
    disk = _disk(h, w, 30, 24, 10)
    seg = segment(img, mask=torch.from_numpy(disk).float()[None])
    assert seg.method == "mask"
    assert torch.equal(seg.mask.bool(), torch.from_numpy(disk))
    assert seg.image.shape == (h, w, 3)


def _ellipse_scene(h=120, w=160):
    rng = np.random.default_rng(3)
    # A textured greenish-grey background (noise + stripes) and a saturated orange ellipse.
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    bg = np.stack([0.35 + 0.1 * np.sin(xx / 3.0), 0.45 + 0.08 * np.sin(yy / 4.0 + xx / 7.0),
                   0.40 * np.ones_like(xx)], -1)
    bg += 0.05 * rng.standard_normal((h, w, 3)).astype(np.float32)
    ell = np.zeros((h, w), np.uint8)
    cv2.ellipse(ell, (82, 58), (42, 30), 20.0, 0, 360, 1, -1)
    obj = np.stack([0.9 + 0.05 * np.sin(xx / 5.0), 0.45 + 0.1 * np.cos(yy / 6.0), 0.1 * np.ones_like(xx)], -1)
    img = np.where(ell[..., None] > 0, obj, bg)
    return np.clip(img, 0, 1).astype(np.float32), ell > 0


def test_grabcut_without_box_recovers_the_ellipse():
    img, truth = _ellipse_scene()
    seg = segment(torch.from_numpy(img))
    assert seg.method == "grabcut"
    iou = _iou(seg.mask.numpy(), truth)
    assert iou >= 0.9, f"GrabCut IoU {iou:.3f}"
    # The auto box contains the ellipse.
    x0, y0, x1, y1 = auto_box(torch.from_numpy(img))
    ys, xs = np.nonzero(truth)
    assert x0 <= xs.min() and y0 <= ys.min() and x1 > xs.max() and y1 > ys.max()


def test_grabcut_with_a_box_and_with_a_rough_mask():
    img, truth = _ellipse_scene()
    seg = segment(torch.from_numpy(img), box=(30, 15, 135, 105), method="grabcut")
    assert _iou(seg.mask.numpy(), truth) >= 0.9
    rough = cv2.dilate(truth.astype(np.uint8), np.ones((9, 9), np.uint8))
    seg = segment(torch.from_numpy(img), mask=torch.from_numpy(rough).float(), method="grabcut")
    assert _iou(seg.mask.numpy(), truth) >= 0.9


def test_coffee_photo_segments_cup_and_saucer(example_image_path):
    rgb, alpha = load_image(example_image_path)
    assert rgb.shape == (400, 600, 3) and alpha is None
    x0, y0, x1, y1 = auto_box(rgb)
    # The cup (rim ~ x 175..410, y 20..; body down to ~y 300) lies inside the box, and the box is
    # not just the whole image.
    assert x0 <= 175 and y0 <= 25 and x1 >= 410 and y1 >= 300
    assert (x1 - x0) * (y1 - y0) < 0.9 * 600 * 400
    seg = segment(rgb)
    m = seg.mask.numpy() > 0.5
    for x, y in [(290, 150), (290, 60), (230, 265), (120, 250), (440, 250), (365, 290)]:
        assert m[y, x], f"object pixel ({x}, {y}) missed"  # coffee, rim, handle, saucer, spoon
    for x, y in [(20, 20), (560, 40), (570, 350), (20, 200), (530, 200)]:
        assert not m[y, x], f"table pixel ({x}, {y}) taken as object"
    assert 0.35 < m.mean() < 0.65


# ----------------------------------------------------------------------------------------------
# background
# ----------------------------------------------------------------------------------------------


def test_inpainting_changes_only_the_dilated_region_and_matches_a_smooth_background():
    h, w = 120, 160
    bg = _gradient_image(h, w)
    disk = _disk(h, w, 80, 60, 25)
    img = bg.copy()
    img[disk] = (0.95, 0.1, 0.1)  # a red object, whose colour must not leak into the fill
    out = inpaint_background(torch.from_numpy(img), torch.from_numpy(disk).float(), dilate_px=4)
    out = out.numpy()
    grown = cv2.dilate(disk.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))) > 0
    assert np.array_equal(out[~grown], img[~grown])  # bit-identical outside
    err = np.abs(out[grown] - bg[grown])
    # Tolerance: a linear gradient across a 58 px hole is filled to within 0.03 on average and 0.1
    # at worst (of a 0..1 range; the object's red would be an error of ~0.7).
    assert err.mean() < 0.03, err.mean()
    assert err.max() < 0.1, err.max()


def test_segment_background_has_no_object_halo():
    h, w = 100, 120
    bg = _gradient_image(h, w)
    disk = _disk(h, w, 60, 50, 20)
    soft = cv2.GaussianBlur(disk.astype(np.float32), (0, 0), 1.5)  # an anti-aliased edge
    img = bg * (1 - soft[..., None]) + np.array([0.0, 0.9, 0.1], np.float32) * soft[..., None]
    seg = segment(torch.from_numpy(img.astype(np.float32)), mask=torch.from_numpy(disk).float())
    greenish = seg.background.numpy()[..., 1] - bg[..., 1]
    assert greenish.max() < 0.08  # the halo of object colour is gone
    assert default_dilate_px(h, w) >= 3


def test_inpainting_a_4k_image_fills_the_hole_smoothly_and_leaves_the_rest():
    # its time is measured by `python -m benchmarks.bench_fill --large` (docs/benchmarks.md)
    h, w = 2160, 3840
    img = _gradient_image(h, w)
    disk = _disk(h, w, w / 2, h / 2, 700)
    out = inpaint_background(torch.from_numpy(img), torch.from_numpy(disk))
    far = ~(cv2.dilate(disk.astype(np.uint8), np.ones((61, 61), np.uint8)) > 0)
    assert torch.equal(out[torch.from_numpy(far)], torch.from_numpy(img)[torch.from_numpy(far)])
    # The ramp across this 1400 px hole is 0.26; a smooth fill stays within 0.05 of it on average.
    assert float(np.abs(out.numpy()[disk] - img[disk]).mean()) < 0.05


# ----------------------------------------------------------------------------------------------
# clean_mask and errors
# ----------------------------------------------------------------------------------------------


def test_clean_mask_fills_holes_and_drops_specks():
    h, w = 100, 100
    m = _disk(h, w, 50, 50, 30).astype(np.float32)
    m[48:53, 48:53] = 0  # a small hole
    m[5:7, 5:7] = 1  # a speck
    m[90, 90] = 1  # a single-pixel speck
    out = clean_mask(torch.from_numpy(m)).numpy()
    assert out.dtype == np.float32
    assert out[50, 50] == 1 and out[48:53, 48:53].all()
    assert out[5:7, 5:7].sum() == 0 and out[90, 90] == 0
    assert _iou(out, _disk(h, w, 50, 50, 30)) > 0.97
    # A big opening (a ring) is a real hole and stays; a second large part is kept.
    ring = _disk(h, w, 35, 50, 25) & ~_disk(h, w, 35, 50, 14)
    two = ring | _disk(h, w, 82, 50, 12)
    out = clean_mask(torch.from_numpy(two.astype(np.float32))).numpy()
    assert out[50, 35] == 0 and out[50, 82] == 1


def test_bad_inputs_raise_input_error():
    img = torch.rand(32, 40, 3)
    with pytest.raises(InputError, match="empty"):
        segment(img, mask=torch.zeros(32, 40))
    with pytest.raises(InputError, match="whole image"):
        segment(img, mask=torch.ones(32, 40))
    with pytest.raises(InputError, match="does not match"):
        segment(img, mask=torch.ones(30, 40))
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        segment(torch.rand(32, 40))
    with pytest.raises(InputError, match="alpha"):
        segment(torch.rand(32, 40, 4))
    with pytest.raises(InputError, match="alpha"):
        segment(img, method="alpha")
    with pytest.raises(InputError, match="mask"):
        segment(img, method="mask")
    with pytest.raises(InputError, match="method"):
        segment(img, method="sam")
    with pytest.raises(InputError, match="box"):
        segment(img, box=(50, 50, 60, 60))
    with pytest.raises(InputError, match="whole image"):
        inpaint_background(img, torch.ones(32, 40))
