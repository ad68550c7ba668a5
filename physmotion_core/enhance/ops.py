"""The model calls every enhancement stage shares: prompts, VAE encode/decode, UNet + ControlNets."""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from .loader import DiffusionModels


@torch.no_grad()
def encode_prompts(models: DiffusionModels, prompts: Sequence[str]) -> torch.Tensor:
    """CLIP text embeddings (len(prompts), 77, D) in the UNet dtype, on ``models.device``."""
    tok = models.tokenizer(list(prompts), padding="max_length", max_length=models.tokenizer.model_max_length,
                           truncation=True, return_tensors="pt")
    models.place("text_encoder")
    try:
        out = models.text_encoder(tok.input_ids.to(models.device))[0]
    finally:
        models.release("text_encoder")
    return out.to(models.dtype)


@torch.no_grad()
def encode_images(models: DiffusionModels, images: torch.Tensor, batch: int = 4,
                  generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Latents (F,4,h,w) float32 of images (F,3,H,W) in [0,1]: the posterior mean (or a sample
    with ``generator``), times the VAE scaling factor."""
    models.place("vae")
    sf = float(models.vae.config.scaling_factor)
    out = []
    try:
        for s in range(0, images.shape[0], batch):
            x = images[s:s + batch].to(models.device, models.vae_dtype) * 2 - 1
            dist = models.vae.encode(x).latent_dist
            if generator is None:
                z = dist.mean
            else:
                z = dist.mean + dist.std * torch.randn(dist.mean.shape, generator=generator).to(dist.mean)
            out.append((z * sf).float())
    finally:
        models.release("vae")
    return torch.cat(out)


@torch.no_grad()
def decode_latents(models: DiffusionModels, latents: torch.Tensor, batch: int = 1, progress=None) -> torch.Tensor:
    """Images (F,3,H,W) in [0,1] (float32, CPU) from latents (F,4,h,w)."""
    from ..progress import report

    models.place("vae")
    sf = float(models.vae.config.scaling_factor)
    out = []
    try:
        for s in range(0, latents.shape[0], batch):
            z = latents[s:s + batch].to(models.device, models.vae_dtype) / sf
            out.append(((models.vae.decode(z).sample.float() + 1) / 2).clamp(0, 1).cpu())
            report(progress, min(s + batch, latents.shape[0]), latents.shape[0])
    finally:
        models.release("vae")
    return torch.cat(out)


def predict(models: DiffusionModels, x: torch.Tensor, t: int, text: torch.Tensor,
            controls: Sequence[torch.Tensor] = (), scales: Sequence[float] = ()) -> torch.Tensor:
    """The UNet's output (float32) for latents ``x`` (B,4,h,w) at timestep ``t`` with text
    embeddings ``text`` (B,77,D) and ControlNet images ``controls`` (one (B,3,H,W) tensor per
    ControlNet in ``models.controlnets`` order, in [0,1]), summed through MultiControlNet."""
    dev, dt = models.device, models.dtype
    xs = x.to(dev, dt)
    ts = torch.full((x.shape[0],), int(t), device=dev, dtype=torch.long)
    emb = text.to(dev, dt)
    down = mid = None
    if models.controlnets and controls:
        from diffusers import MultiControlNetModel

        multi = MultiControlNetModel(list(models.controlnets.values()))
        down, mid = multi(xs, ts, encoder_hidden_states=emb, controlnet_cond=[c.to(dev, dt) for c in controls],
                          conditioning_scale=[float(s) for s in scales], return_dict=False)
    out = models.unet(xs, ts, encoder_hidden_states=emb, down_block_additional_residuals=down,
                      mid_block_additional_residual=mid, return_dict=False)[0]
    return out.float()
