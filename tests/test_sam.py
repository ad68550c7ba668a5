"""SAM: architecture read from checkpoints, safe loading, prompts, candidate selection, automatic mode."""

from __future__ import annotations

import pickle
from functools import partial

import numpy as np
import pytest
import torch

pytest.importorskip("segment_anything")

from segment_anything import SamPredictor  # noqa: E402
from segment_anything.build_sam import sam_model_registry  # noqa: E402
from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer  # noqa: E402
from segment_anything.utils.transforms import ResizeLongestSide  # noqa: E402

from physmotion_core.errors import InputError, MissingModelError  # noqa: E402
from physmotion_core.segment.sam import (  # noqa: E402
    ObjectPrompt,
    _automatic,
    best_by_iou,
    load_sam,
    parse_prompts,
    salience_scores,
    sam_architecture,
    sam_segment,
    stability,
)

TINY = dict(embed_dim=64, depth=4, num_heads=2, img_size=256, window_size=4, global_attn_indexes=(1, 3),
            prompt_dim=32, mlp_dim=64)


def tiny_sam(seed: int = 4) -> Sam:
    """The segment-anything architecture with a tiny ViT (random weights; seed 4 gives masks that cover
    about a quarter of the test photo, so the union leaves background to inpaint)."""
    torch.manual_seed(seed)
    emb = TINY["img_size"] // 16
    sam = Sam(
        image_encoder=ImageEncoderViT(depth=TINY["depth"], embed_dim=TINY["embed_dim"], img_size=TINY["img_size"],
                                      mlp_ratio=4, norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
                                      num_heads=TINY["num_heads"], patch_size=16, qkv_bias=True, use_rel_pos=True,
                                      global_attn_indexes=TINY["global_attn_indexes"],
                                      window_size=TINY["window_size"], out_chans=TINY["prompt_dim"]),
        prompt_encoder=PromptEncoder(embed_dim=TINY["prompt_dim"], image_embedding_size=(emb, emb),
                                     input_image_size=(TINY["img_size"],) * 2, mask_in_chans=16),
        mask_decoder=MaskDecoder(num_multimask_outputs=3,
                                 transformer=TwoWayTransformer(depth=2, embedding_dim=TINY["prompt_dim"],
                                                               mlp_dim=TINY["mlp_dim"], num_heads=8),
                                 transformer_dim=TINY["prompt_dim"], iou_head_depth=3, iou_head_hidden_dim=32),
        pixel_mean=[123.675, 116.28, 103.53], pixel_std=[58.395, 57.12, 57.375])
    # Random (not zero-initialised) relative positions, so a wrong table would change the output.
    with torch.no_grad():
        for blk in sam.image_encoder.blocks:
            blk.attn.rel_pos_h.normal_(0, 0.1)
            blk.attn.rel_pos_w.normal_(0, 0.1)
    return sam.eval()


@pytest.fixture(scope="module")
def sam_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    (root / "sams").mkdir()
    torch.save(tiny_sam().state_dict(), root / "sams" / "sam_tiny.pth")  # official style: a plain state dict
    return root


@pytest.fixture(scope="module")
def photo():
    """A 96x128 photo: a red disc on a textured grey background."""
    rng = np.random.default_rng(0)
    H, W = 96, 128
    img = 0.5 + 0.05 * rng.standard_normal((H, W, 3))
    yy, xx = np.mgrid[:H, :W]
    disc = (xx - 70) ** 2 + (yy - 50) ** 2 < 22 ** 2
    img[disc] = [0.9, 0.1, 0.1]
    return np.clip(img, 0, 1).astype(np.float32)


@pytest.mark.parametrize("variant,dim,depth,heads,glob", [
    ("vit_b", 768, 12, 12, (2, 5, 8, 11)),
    ("vit_l", 1024, 24, 16, (5, 11, 17, 23)),
    ("vit_h", 1280, 32, 16, (7, 15, 23, 31)),
])
def test_official_architectures_are_read_from_shapes(variant, dim, depth, heads, glob):
    with torch.device("meta"):
        official = sam_model_registry[variant]()
    arch = sam_architecture(official.state_dict())
    assert (arch["embed_dim"], arch["depth"], arch["num_heads"]) == (dim, depth, heads)
    assert arch["global_attn_indexes"] == glob
    assert (arch["window_size"], arch["img_size"], arch["prompt_dim"]) == (14, 1024, 256)
    assert (arch["decoder_mlp_dim"], arch["iou_hidden"], arch["mask_in_chans"]) == (2048, 256, 16)


def test_tiny_checkpoint_loads_and_matches_the_original_network(sam_root, photo):
    sam = load_sam(root=sam_root, device="cpu")  # the only file in the folder
    assert sam.variant.startswith("custom")
    assert sam.info["global_attn_indexes"] == TINY["global_attn_indexes"]
    assert sam.info["window_size"] == TINY["window_size"] and sam.info["num_heads"] == TINY["num_heads"]
    ref = tiny_sam()
    u8 = (photo * 255).round().astype(np.uint8)
    out = []
    for net in (sam.model, ref):
        p = SamPredictor(net)
        p.set_image(u8)
        out.append(p.predict(point_coords=np.array([[70.0, 50.0]]), point_labels=np.array([1]),
                             return_logits=True))
    np.testing.assert_allclose(out[0][0], out[1][0], atol=1e-5)
    np.testing.assert_allclose(out[0][1], out[1][1], atol=1e-6)


def test_prompts_give_one_mask_per_object_chosen_by_predicted_iou(sam_root, photo):
    sam = load_sam("sam_tiny.pth", root=sam_root, device="cpu")
    H, W = photo.shape[:2]
    prompts = parse_prompts("70,50; 20,20", "", width=W, height=H)
    res = sam_segment(sam, photo, prompts, clean=False)
    assert res.masks.shape == (2, H, W)
    assert set(torch.unique(res.masks).tolist()) <= {0.0, 1.0}
    # Each object's mask is the multimask candidate with the highest predicted IoU.
    p = SamPredictor(sam.model)
    p.set_image((photo * 255).round().astype(np.uint8))
    for k, (x, y) in enumerate([(70, 50), (20, 20)]):
        logits, iou, _ = p.predict(point_coords=np.array([[x, y]], np.float32), point_labels=np.array([1]),
                                   return_logits=True)
        i = int(np.argmax(iou))
        assert res.scores[k] == pytest.approx(float(iou[i]))
        assert torch.equal(res.masks[k] > 0.5, torch.from_numpy(logits[i] > 0))
    # The union is cut out and inpainted.
    union = res.masks.amax(0)
    assert torch.equal(res.segmentation.mask, union)
    assert torch.allclose(res.segmentation.foreground, res.segmentation.image * union[..., None])


def test_best_by_iou_and_stability():
    masks = torch.zeros(3, 4, 4, dtype=torch.bool)
    m, s, i = best_by_iou(masks, torch.tensor([0.2, 0.9, 0.5]))
    assert i == 1 and s == pytest.approx(0.9)
    logits = torch.full((2, 10, 10), -5.0)
    logits[0, 2:8, 2:8] = 5.0  # crisp: the same mask at ±1
    logits[1, 2:8, 2:8] = 0.5  # soft: vanishes at +1
    st = stability(logits)
    assert st[0] == pytest.approx(1.0) and st[1] == pytest.approx(0.0)


def test_salience_prefers_a_centred_object_over_border_tiny_and_huge_regions():
    H, W = 60, 80
    K = 4
    masks = torch.zeros(K, H, W, dtype=torch.bool)
    masks[0, 20:40, 30:50] = True  # the object, centred
    masks[1, 40:, :] = True  # the table: hugs the border
    masks[2, 29:31, 39:41] = True  # a speck
    masks[3, 1:-1, 1:-1] = True  # nearly the whole image
    iou = torch.tensor([0.8, 0.95, 0.99, 0.99])
    s = salience_scores(masks, iou, torch.ones(K))
    assert int(torch.argmax(s)) == 0
    assert s[2] == 0 and s[3] == 0 and s[1] < s[0]
    # An off-centre object scores less than the same object centred.
    off = torch.zeros(1, H, W, dtype=torch.bool)
    off[0, 2:22, 2:22] = True
    assert salience_scores(off, iou[:1], torch.ones(1))[0] < s[0]


class _FakePredictor:
    """Stands in for SamPredictor: every point prompt returns a disc around the point whose radius
    depends on where it is, so which candidate is most salient is known in advance."""

    def __init__(self, H, W):
        self.transform = ResizeLongestSide(256)
        self.input_size = self.transform.get_preprocess_shape(H, W, 256)
        self.model = type("M", (), {"image_encoder": type("E", (), {"img_size": 256})()})()
        self.device = torch.device("cpu")
        self.H, self.W = H, W

    def _disc(self, x, y, r, size_hw, scale):
        h, w = size_hw
        yy, xx = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        return 4.0 * (1 - ((xx - x * scale) ** 2 + (yy - y * scale) ** 2).sqrt() / (r * scale))

    def predict_torch(self, coords, labels, boxes=None, multimask_output=True, return_logits=False):
        # The low-res logits here are 64x64 over the padded 256 input: original px x 64 / max(H, W).
        if coords is None:
            n = boxes.shape[0]
            low = torch.full((n, 3, 64, 64), -4.0)
            return None, torch.full((n, 3), 0.5), low
        pts = coords[:, 0, :] / (256 / max(self.H, self.W))
        low, iou = [], []
        for x, y in pts.tolist():
            r = 12.0 if abs(x - self.W / 2) < 20 and abs(y - self.H / 2) < 20 else 3.0
            d = self._disc(x, y, r, (64, 64), 64 / max(self.H, self.W))
            low.append(torch.stack([d, d, d]))
            iou.append(torch.tensor([0.7, 0.8, 0.75]))
        return None, torch.stack(iou), torch.stack(low)

    def predict(self, point_coords=None, point_labels=None, box=None, multimask_output=True, return_logits=False):
        x, y = point_coords[0]
        r = 12.0 if abs(x - self.W / 2) < 20 and abs(y - self.H / 2) < 20 else 3.0
        d = self._disc(x, y, r, (self.H, self.W), 1.0)
        return torch.stack([d, d, d]).numpy(), np.array([0.7, 0.8, 0.75], np.float32), None


def test_automatic_mode_picks_the_salient_candidate():
    H, W = 96, 128
    img = np.full((H, W, 3), 0.5, np.float32)
    pred = _FakePredictor(H, W)
    mask, iou = _automatic(pred, img, grid=8)
    assert mask.shape == (H, W)
    assert iou == pytest.approx(0.8)  # the candidate with the best predicted IoU among equals
    ys, xs = torch.nonzero(mask, as_tuple=True)
    # The winner is one of the big central discs (radius 12), not a small off-centre one.
    assert len(ys) > 0.5 * np.pi * 12 ** 2
    assert abs(xs.float().mean() - W / 2) < 20 and abs(ys.float().mean() - H / 2) < 20


def test_automatic_mode_runs_the_real_network(sam_root, photo):
    sam = load_sam(root=sam_root, device="cpu")
    try:
        res = sam_segment(sam, photo, [], grid=4)
    except InputError as exc:  # a random network may find nothing object-like: that is the clear error
        assert "no object-sized region" in str(exc)
        return
    assert res.masks.shape == (1,) + photo.shape[:2]
    assert 0.005 <= float(res.masks.mean()) <= 0.8


def test_prompt_parsing_groups_points_and_boxes():
    objs = parse_prompts("15,15; 90,60; 5,5,0", "10,10,30,30", width=100, height=80)
    assert len(objs) == 2
    assert objs[0].box == (10, 10, 30, 30) and objs[0].points[0] == (15, 15)
    assert objs[1].box is None and objs[1].points[0] == (90, 60)
    for o in objs:  # the background point applies to every object
        assert (5, 5) in o.points and o.labels[o.points.index((5, 5))] == 0
    frac = parse_prompts("0.5, 0.5", "", width=200, height=100, fraction=True)
    assert frac[0].points == [(100.0, 50.0)]
    explicit = parse_prompts("1,1,1,1; 2,2,1,0", "", width=10, height=10)
    assert explicit[0].points == [(2, 2)] and explicit[1].points == [(1, 1)]


@pytest.mark.parametrize("points,boxes,msg", [
    ("1,2,3", "", "label"),
    ("500,5", "", "outside the image"),
    ("a,b", "", "Could not read"),
    ("", "1,2,3", "4 numbers"),
    ("", "5,5,5,9", "empty"),
    ("5,5,0", "", "Only background points"),
    ("1,1,0,0", "", "only background points"),
])
def test_bad_prompts_are_refused_with_a_fix(points, boxes, msg):
    with pytest.raises(InputError, match=msg):
        parse_prompts(points, boxes, width=100, height=80)


def test_missing_and_wrong_checkpoints_give_clear_errors(tmp_path):
    (tmp_path / "sams").mkdir()
    with pytest.raises(MissingModelError) as e:
        load_sam(root=tmp_path)
    assert str(tmp_path / "sams") in str(e.value) and "sam_vit_h_4b8939.pth" in str(e.value)
    assert "empty" in str(e.value)
    with pytest.raises(MissingModelError, match="notes.txt"):
        (tmp_path / "sams" / "notes.txt").write_text("x")
        load_sam("sam_vit_b_01ec64.pth", root=tmp_path)
    torch.save({"conv.weight": torch.zeros(3, 3)}, tmp_path / "sams" / "other.pth")
    with pytest.raises(InputError, match="not a SAM checkpoint"):
        load_sam("other.pth", root=tmp_path)
    # A pickle carrying arbitrary objects is refused by weights_only loading, with a clear message.
    with open(tmp_path / "sams" / "evil.pth", "wb") as f:
        pickle.dump({"x": ObjectPrompt()}, f)
    with pytest.raises(InputError, match="Could not read weights"):
        load_sam("evil.pth", root=tmp_path)
    (tmp_path / "sams" / "cut.pth").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(InputError, match="truncated"):
        load_sam("cut.pth", root=tmp_path)


def test_sam_nodes_list_load_and_segment(sam_root, photo, monkeypatch):
    from comfy_harness import load_pack

    monkeypatch.setenv("PHYSMOTION_MODELS", str(sam_root))
    nodes = load_pack().NODE_CLASS_MAPPINGS
    loader, seg = nodes["PhysMotionSAMLoader"], nodes["PhysMotionSAMSegment"]
    assert loader.INPUT_TYPES()["required"]["sam_name"][0] == ["sam_tiny.pth"]
    (sam,) = loader().run("sam_tiny.pth")
    image = torch.from_numpy(photo)[None]
    out = seg().run(sam, image, "0.55, 0.52", "", "fraction", True)
    fg, mask, bg, objs, overlay = out["result"]
    assert len(out["ui"]["images"]) == 1  # the overlay shown in the node
    assert overlay.shape == (1, photo.shape[0], 2 * photo.shape[1], 3)
    H, W = photo.shape[:2]
    assert fg.shape == (1, H, W, 3) and mask.shape == (1, H, W) and bg.shape == (1, H, W, 3)
    assert objs.shape == (1, H, W) and torch.equal(objs.amax(0), mask[0])
    assert sam.device.type == "cpu"  # offloaded after the node
    # A MASK from any other node is used instead of running SAM (and checked the same way).
    given = torch.zeros(1, H, W)
    given[:, H // 4:H // 2, W // 4:W // 2] = 1.0
    import physmotion_core.segment.sam as sam_mod

    monkeypatch.setattr(sam_mod, "sam_segment", lambda *a, **k: (_ for _ in ()).throw(AssertionError("SAM ran")))
    fg2, mask2, _, objs2, _ = seg().run(sam, image, "", "", "pixels", True, mask=given)["result"]
    assert torch.equal(mask2, given) and torch.equal(objs2, given)
    with pytest.raises(MissingModelError, match="sam_vit_h_4b8939.pth"):
        loader().run("(none found)")
