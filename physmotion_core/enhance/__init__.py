"""Generative video enhancement (PhysMotion §3.4): SD 2.1 + depth/canny ControlNets + LoRA;
DDIM+ inversion of the coarse frames, then keyframe-shared sampling with PnP feature / Q-K
injection and TokenFlow propagation. See docs/enhance.md.

Heavy imports (diffusers, transformers, peft) happen inside the functions' modules only when used.
"""

from .invert import Inversion, invert_frames
from .loader import DiffusionModels, load_diffusion
from .lora import LoraResult, LoraSettings, personalize
from .sample import EnhanceResult, SampleSettings, keyframe_shared_sample

__all__ = ["DiffusionModels", "EnhanceResult", "Inversion", "LoraResult", "LoraSettings", "SampleSettings",
           "invert_frames", "keyframe_shared_sample", "load_diffusion", "personalize"]
