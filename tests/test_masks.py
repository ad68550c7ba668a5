import torch

from physmotion_core.masks import orient_object_mask


def test_auto_polarity_flips_inverted_alpha_only():
    obj = torch.zeros(20, 30)
    obj[5:15, 10:20] = 1.0
    assert torch.equal(orient_object_mask(obj), obj)
    assert torch.equal(orient_object_mask(1 - obj), obj)  # ComfyUI LoadImage MASK = 1 - alpha
    assert torch.equal(orient_object_mask(obj, "black is object"), 1 - obj)
    assert torch.equal(orient_object_mask(1 - obj, "white is object"), 1 - obj)
