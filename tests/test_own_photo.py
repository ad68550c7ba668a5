"""Issue 33 through generate(): the mask is checked before anything is simulated, a preview stops
before the simulation, prompts reach the segmentation, and the user is told what was decided."""

import logging

import numpy as np
import pytest
import torch

import physmotion_core.pipeline as pipeline
from physmotion_core.errors import InputError
from physmotion_core.pipeline import generate
from physmotion_core.types import Conditions, Force, Ground, Region, SimSettings

H, W = 96, 128
FAST = SimSettings(frames=4, fps=24.0, grid_res=8, device="cpu")


def photo():
    """A red disk on a grey, slightly textured table (float (H, W, 3) in 0..1)."""
    rng = np.random.default_rng(0)
    img = 0.5 + 0.03 * rng.standard_normal((H, W, 3))
    yy, xx = np.mgrid[:H, :W]
    disk = (xx - 64) ** 2 + (yy - 50) ** 2 <= 22 ** 2
    img[disk] = (0.85, 0.1, 0.1)
    return np.clip(img, 0, 1).astype(np.float32), disk


def _no_simulation(monkeypatch):
    import physmotion_core.sim as sim_pkg

    def boom(*a, **k):
        raise AssertionError("the preview must stop before simulating")

    monkeypatch.setattr(sim_pkg, "simulate", boom)


def test_preview_stops_before_simulating_and_tells_mass_support_and_forecast(monkeypatch, tmp_path):
    _no_simulation(monkeypatch)
    img, disk = photo()
    said = []
    prep = generate(img, material="jelly", conditions=Conditions([Force((5.0, 0.0, 0.0))]), settings=FAST,
                    preview=True, report=said.append, overlay=tmp_path / "ov.png")
    assert prep.mass_kg is not None and prep.mass_kg > 0
    assert said == prep.lines
    text = "\n".join(said)
    assert "mask (grabcut)" in text
    assert "picked automatically" in text and str(tmp_path / "ov.png") in text
    assert "ground: under the object's lowest visible point" in text
    assert "object height: 0.3 m (assumed)" in text
    assert "force 1: 5 N" in text and "Δv" in text and "static friction" in text
    assert (tmp_path / "ov.png").is_file()
    iou = (prep.segmentation.mask.numpy() > 0.5)[disk].sum() / ((prep.segmentation.mask.numpy() > 0.5) | disk).sum()
    assert iou > 0.8


def _implausible_segmentation(monkeypatch):
    """GrabCut's automatic pass replaced by one that returns the table: it touches all four edges."""
    from physmotion_core.segment import segment

    def fake(rgb, **kw):
        m = np.ones((H, W), np.float32)
        m[30:70, 40:90] = 0
        return segment(rgb, mask=torch.from_numpy(m)), "grabcut"

    monkeypatch.setattr(pipeline, "segment_photo", fake)


def test_an_implausible_automatic_mask_is_refused_naming_the_overlay(monkeypatch, tmp_path):
    _no_simulation(monkeypatch)
    _implausible_segmentation(monkeypatch)
    img, _ = photo()
    out = tmp_path / "clip.mp4"
    with pytest.raises(InputError) as exc:
        generate(img, settings=FAST, output=out)
    msg = str(exc.value)
    assert str(tmp_path / "clip.mask.png") in msg and (tmp_path / "clip.mask.png").is_file()
    assert "--object-point" in msg and "--box" in msg and "--mask" in msg
    assert not out.exists()


def test_the_same_mask_with_a_prompt_only_warns(monkeypatch, tmp_path, caplog):
    _no_simulation(monkeypatch)
    _implausible_segmentation(monkeypatch)
    img, _ = photo()
    with caplog.at_level(logging.WARNING, logger="physmotion"):
        prep = generate(img, settings=FAST, preview=True, box=(0, 0, W, H), report=lambda s: None)
    assert not prep.mask_report.ok
    assert caplog.records, "a prompted implausible mask must be warned about"
    assert not any("picked automatically" in r.getMessage() for r in caplog.records)
    hint = [r.getMessage() for r in caplog.records if "If the outline is not the object" in r.getMessage()]
    assert len(hint) == 1 and "move the --box sides" in hint[0] and "--background-point" in hint[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="physmotion"):  # a click: the advice is a box
        generate(img, settings=FAST, preview=True, object_points=[(20, 20)], output=tmp_path / "c.mp4",
                 report=lambda s: None)
    hint = [r.getMessage() for r in caplog.records if "If the outline is not the object" in r.getMessage()]
    assert len(hint) == 1 and "--box X0,Y0,X1,Y1" in hint[0] and str(tmp_path / "c.mask.png") in hint[0]


def test_the_segment_command_writes_the_overlay_and_says_what_generate_would_do(monkeypatch, tmp_path, capsys):
    import cv2

    from physmotion_core.cli import main

    img, disk = photo()
    path = tmp_path / "disk.png"
    cv2.imwrite(str(path), cv2.cvtColor((img * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    # the real segmentation, clicked on the disk: plausible, the overlay beside the fill
    assert main(["segment", str(path), "--object-point", "64,50", "-o", str(tmp_path / "ok.png"),
                 "--models", "none"]) == 0
    cap = capsys.readouterr()
    assert "looks plausible" in cap.out and "generate would" not in cap.out
    # GrabCut's progress on stderr; not a terminal here, so a line at the start, each quarter and the end
    bar = cap.err.strip().split("\n")
    assert "\r" not in cap.err and 3 <= len(bar) <= 6 and all(b.startswith("segment") for b in bar)
    assert "100.0%" in bar[-1] and "100.0%" not in bar[-2]
    ov = cv2.imread(str(tmp_path / "ok.png"))
    assert ov.shape[:2] == (H, 2 * W)  # the photo with the outline | the filled background
    # a wrong mask: unprompted it would be refused, prompted only warned, with what to change
    _implausible_segmentation(monkeypatch)
    assert main(["segment", str(path), "-o", str(tmp_path / "a.png")]) == 0
    out = capsys.readouterr().out
    assert "generate would refuse this mask" in out and "If the outline" not in out
    # the picture says so too: a dark caption bar above the overlay, with light text
    auto = cv2.imread(str(tmp_path / "a.png"))
    bar = auto[: auto.shape[0] - H]
    assert auto.shape[1] == 2 * W and auto.shape[0] - H >= 20 and np.median(bar) < 40 and (bar > 200).any()
    assert main(["segment", str(path), "--object-point", "64,50", "-o", str(tmp_path / "c.png")]) == 0
    out = capsys.readouterr().out
    assert "generate would warn about this mask" in out and "draw a box around the whole object with --box" in out
    assert main(["segment", str(path), "--box", "30,20,100,80", "-o", str(tmp_path / "b.png"), "-q"]) == 0
    cap = capsys.readouterr()
    assert "move the --box sides" in cap.out and "segment" not in cap.err  # -q: no bar


def test_prompts_reach_grabcut_in_the_scaled_photo(monkeypatch):
    _no_simulation(monkeypatch)
    seen = {}
    real = pipeline.segment_photo

    def spy(rgb, **kw):
        seen.update(kw)
        seen["size"] = tuple(rgb.shape[:2])
        return real(rgb, **kw)

    monkeypatch.setattr(pipeline, "segment_photo", spy)
    img, _ = photo()
    big = np.kron(img, np.ones((2, 2, 1), np.float32))  # 256 x 192, scaled back to 128 x 96 by max_side
    generate(big, settings=FAST, preview=True, max_side=128, object_points=[(128, 100)],
             background_points=[(10, 10)], box=(60, 40, 200, 160), report=lambda s: None)
    assert seen["size"] == (H, W)
    assert seen["object_points"] == [(64.0, 50.0)] and seen["background_points"] == [(5.0, 5.0)]
    assert seen["box"] == (30.0, 20.0, 100.0, 80.0)


@pytest.mark.parametrize("kw, words", [
    ({"object_points": [(500, 10)]}, "outside the 128x96 photo"),
    ({"box": (50, 50, 40, 60)}, "empty"),
    ({"background_points": [(5, 5)]}, "only background points"),
    ({"object_points": [(float("nan"), 3)]}, "not finite"),
])
def test_bad_prompts_are_refused_before_any_work(monkeypatch, kw, words):
    _no_simulation(monkeypatch)
    img, _ = photo()
    with pytest.raises(InputError, match=words):
        generate(img, settings=FAST, preview=True, **kw)


def test_a_push_off_the_object_is_refused_at_once_with_where_the_object_is(monkeypatch):
    _no_simulation(monkeypatch)
    img, disk = photo()
    conds = Conditions([Force((5.0, 0.0, 0.0), Region.at_pixel(5, 5, 10))])
    with pytest.raises(InputError) as exc:
        generate(img, mask=torch.from_numpy(disk.astype(np.float32)), conditions=conds, settings=FAST, preview=True)
    msg = str(exc.value)
    assert "(5, 5)" in msg and "does not touch the object" in msg
    ys, xs = np.nonzero(disk)
    assert f"x {xs.min()}..{xs.max() + 1}" in msg and f"y {ys.min()}..{ys.max() + 1}" in msg


def test_a_cut_off_object_is_held_and_the_run_says_so(monkeypatch):
    _no_simulation(monkeypatch)
    img, _ = photo()
    yy, xx = np.mgrid[:H, :W]
    cut = ((xx - 64) / 30.0) ** 2 + ((yy - 70) / 40.0) ** 2 <= 1  # runs off the bottom edge
    prep = generate(img, mask=torch.from_numpy(cut.astype(np.float32)), settings=FAST, preview=True,
                    report=lambda s: None)
    assert prep.support.hold and prep.support.edges == ("bottom",)
    assert any("Anchor" == type(c).__name__ for c in prep.conditions)
    assert prep.conditions.ground().height == pytest.approx(-0.3)
    off = generate(img, mask=torch.from_numpy(cut.astype(np.float32)), settings=FAST, preview=True,
                   hold_edges=False, report=lambda s: None)
    assert not any("Anchor" == type(c).__name__ for c in off.conditions)


def test_the_same_prompts_go_to_sam_when_its_weights_are_present(monkeypatch):
    """With SAM in the models folder, the object/background points and the box become SAM's prompt
    (in the scaled photo's pixels); the automatic mode asks SAM for its most salient object."""
    from types import SimpleNamespace

    import physmotion_core.segment.sam as sam_mod
    from physmotion_core.segment import segment

    _no_simulation(monkeypatch)
    img, disk = photo()
    seen = []
    monkeypatch.setattr(pipeline, "available_models", lambda: {"sam": "sam_vit_b_01ec64.pth", "lgm": None,
                                                               "imagedream": None})
    monkeypatch.setattr(sam_mod, "load_sam", lambda name, device=None: SimpleNamespace(name=name))

    def fake_sam(sam, rgb, prompts, **kw):
        seen.append(list(prompts))
        return SimpleNamespace(segmentation=segment(rgb, mask=torch.from_numpy(disk.astype(np.float32))))

    monkeypatch.setattr(sam_mod, "sam_segment", fake_sam)
    prep = generate(img, settings=FAST, preview=True, object_points=[(64, 50)], background_points=[(5, 90)],
                    box=(30, 20, 100, 80), report=lambda s: None)
    assert prep.stages["segment"] == "sam"
    (p,) = seen[-1]
    assert p.points == [(64.0, 50.0), (5.0, 90.0)] and p.labels == [1, 0] and p.box == (30.0, 20.0, 100.0, 80.0)
    generate(img, settings=FAST, preview=True, report=lambda s: None)
    assert seen[-1] == []  # no prompt: SAM's automatic mode


def test_texture_photo_shows_the_photo_and_splat_the_gaussians_colours():
    img, disk = photo()
    rng = np.random.default_rng(3)
    img = img.copy()
    img[disk] = np.clip(img[disk] + 0.15 * rng.standard_normal((int(disk.sum()), 3)), 0, 1)  # detail to keep
    m = torch.from_numpy(disk.astype(np.float32))
    inner = torch.from_numpy(np.asarray(__import__("cv2").erode(disk.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0))

    def psnr(a, b):
        return float(10 * torch.log10(1.0 / ((a - b) ** 2).mean()))

    ref = torch.from_numpy(img)[inner]
    photo_f0 = generate(img, mask=m, settings=FAST, report=lambda s: None).frames[0][inner]
    splat_f0 = generate(img, mask=m, settings=FAST, texture="splat", report=lambda s: None).frames[0][inner]
    assert psnr(photo_f0, ref) > 40.0
    assert psnr(splat_f0, ref) < psnr(photo_f0, ref) - 10.0
    with pytest.raises(InputError, match="texture"):
        generate(img, mask=m, settings=FAST, texture="paint")


def test_a_mask_in_two_pieces_is_told_before_and_after_the_run(tmp_path):
    """A head the mask holds apart from its body (a gap of a few pixels): the forecast pushes the head's
    own mass, and after the run the head that the push threw out of the frame is reported, while the
    body stayed (so "the object left the frame" is not what happened)."""
    rng = np.random.default_rng(0)
    img = 0.5 + 0.03 * rng.standard_normal((H, W, 3))
    yy, xx = np.mgrid[:H, :W]
    body = (abs(xx - 64) <= 30) & (yy >= 55)  # cut by the frame's bottom edge: held there
    head = (xx - 64) ** 2 + (yy - 16) ** 2 <= 11 ** 2  # rows 5..27: 28 px (more than two grid cells) above
    mask = body | head
    img[mask] = (0.85, 0.5, 0.2)
    said = []
    res = generate(np.clip(img, 0, 1).astype(np.float32), mask=torch.from_numpy(mask.astype(np.float32)),
                   material="jelly", conditions=Conditions([Force((20.0, 0.0, 0.0), region=Region(
                       kind="image", points=((64.0, 16.0),), radius_px=8.0), t_start=0.0, t_end=0.25),
                       Ground(0.0, "friction", 0.5)]),
                   settings=SimSettings(frames=12, fps=24.0, grid_res=12, device="cpu"), report=said.append)
    text = "\n".join(said)
    assert "2 separate pieces" in text and "the piece it pushes" in text, text
    (push,) = [s for s in said if s.startswith("force 1")]
    head_share = float(push.split("(the piece it pushes, ")[1].split("%")[0]) / 100
    assert 0.05 < head_share < 0.3  # the head's share of the volume, not the whole object's mass
    (loose,) = [s for s in said if "neither held nor standing on anything" in s]
    box = [int(v) for v in loose.split(" at x ")[1].split(" px")[0].replace("..", " ").replace(", y", "").split()]
    assert np.allclose(box, [53, 75, 5, 27], atol=4), box  # x0, x1, y0, y1: where the head is in the photo
    assert any("separate piece" in s and "left the frame" in s for s in said), text
    assert not any("the object left the frame" in s for s in said)
    piece = res.sim.particle_piece
    assert piece is not None and int(piece.max()) == 1


def test_prompts_that_the_alpha_channel_overrides_are_named_not_silently_dropped(monkeypatch, tmp_path, capsys):
    """A transparent PNG's alpha is the object's mask; a box or points given with it do not cut anything, and
    the run says so (and how to segment by them instead). Without prompts, or on an opaque photo, no note."""
    import cv2

    from physmotion_core.cli import main

    _no_simulation(monkeypatch)
    img, disk = photo()
    rgba = np.dstack([(img * 255).round().astype(np.uint8)[:, :, ::-1], (disk * 255).astype(np.uint8)])
    path = tmp_path / "disk.png"
    cv2.imwrite(str(path), rgba)
    assert main(["segment", str(path), "--box", "30,20,100,80", "-o", str(tmp_path / "a.png"), "-q"]) == 0
    out = capsys.readouterr().out
    assert "(alpha," in out
    assert "note: --box was not used to cut the mask: the photo's transparency" in out
    assert "give the photo without transparency" in out
    said = []
    generate(path, material="jelly", settings=FAST, preview=True, report=said.append, overlay=tmp_path / "o.png",
             object_points=[(64, 50)], background_points=[(5, 5)])
    notes = [s for s in said if s.startswith("note:")]
    assert notes == ["note: --object-point and --background-point were not used to cut the mask: the photo's "
                     "transparency (its alpha channel) is the object's mask. To segment by them instead, give the "
                     "photo without transparency (a JPEG, or the PNG flattened)."]
    said.clear()
    generate(path, material="jelly", settings=FAST, preview=True, report=said.append, overlay=tmp_path / "o.png")
    assert not [s for s in said if s.startswith("note:")]
    opaque = tmp_path / "opaque.png"
    cv2.imwrite(str(opaque), rgba[:, :, :3])
    assert main(["segment", str(opaque), "--box", "30,20,100,80", "-o", str(tmp_path / "b.png"), "-q",
                 "--models", "none"]) == 0
    assert "note:" not in capsys.readouterr().out
    # a --mask file wins the same way
    assert pipeline.unused_prompts_line("mask", box=(1, 2, 3, 4)).endswith("To segment by it instead, leave out --mask.")
    assert pipeline.unused_prompts_line("grabcut", box=(1, 2, 3, 4)) is None


def test_a_box_reaching_past_the_photo_is_cut_to_it_and_named(monkeypatch, tmp_path, capsys):
    """A box larger than the photo (a template's box kept after loading a smaller photo, or typed wrong) is cut
    to the photo and used, and the run says by how much it reached past, in the photo's own pixels."""
    import cv2

    from physmotion_core.cli import main
    from physmotion_core.segment.check import box_past_photo

    _no_simulation(monkeypatch)
    img, disk = photo()
    path = tmp_path / "disk.png"
    cv2.imwrite(str(path), cv2.cvtColor((img * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    assert main(["segment", str(path), "--box", "30,20,190,80", "-o", str(tmp_path / "a.png"), "-q",
                 "--models", "none"]) == 0
    out = capsys.readouterr().out
    assert f"note: the box (30, 20, 190, 80) reaches past the {W}x{H} photo (right by {190 - W} px)" in out
    said = []
    generate(img, material="jelly", settings=FAST, preview=True, report=said.append, overlay=tmp_path / "o.png",
             box=(-10, 20, 100, 80), models="none")
    assert [s for s in said if "reaches past" in s] == [
        f"note: the box (-10, 20, 100, 80) reaches past the {W}x{H} photo (left by 10 px) and was cut to it: was it "
        "drawn on another photo?"]
    said.clear()
    generate(img, material="jelly", settings=FAST, preview=True, report=said.append, overlay=tmp_path / "o.png",
             box=(30, 20, 100, 80), models="none")
    assert not [s for s in said if "reaches past" in s]
    # within a hand-drawn box's slack of the edge: nothing to say; and each side is named
    assert box_past_photo((-2, 0, W + 2, H), W, H) is None and box_past_photo(None, W, H) is None
    assert "left by 5 px, top by 4 px, right by 6 px, bottom by 7 px" in box_past_photo((-5, -4, W + 6, H + 7), W, H)
