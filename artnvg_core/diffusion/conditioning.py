"""Conditioning inputs: SDXL prompt embeddings and CSGO image tokens.

* :func:`encode_prompt` follows diffusers' SDXL ``encode_prompt`` for one prompt with
  classifier-free guidance: both text encoders' penultimate hidden states concatenated
  ([1, 77, 768 + 1280] for SDXL), the pooled projection of the second encoder ([1, 1280]);
  a ``None`` negative prompt gives zeros when the model asks for it
  (``force_zeros_for_empty_prompt``), else the empty prompt is encoded.
* :func:`image_features`: the image encoder's penultimate hidden states [B, 257, 1664]
  (what CSGO's resamplers read), after CLIP preprocessing at the encoder's image size.
* :func:`prepare_conditioning`: everything shared by all groups of a scene (prompt and
  style tokens), computed once.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .csgo import ImageTokens
from .images import check_images, clip_preprocess
from .memory import visiting
from .models import DiffusionModels, SDXLBase


@dataclass
class PromptEmbeddings:
    """text [1, 77, D], pooled [1, P] and their negative (unconditional) counterparts."""

    text: torch.Tensor
    pooled: torch.Tensor
    negative_text: torch.Tensor
    negative_pooled: torch.Tensor


def _encode_text(base: SDXLBase, prompt: str) -> tuple[torch.Tensor, torch.Tensor]:
    hidden, pooled = [], None
    for tokenizer, encoder in ((base.tokenizer, base.text_encoder), (base.tokenizer_2, base.text_encoder_2)):
        ids = tokenizer(
            [prompt], padding="max_length", max_length=tokenizer.model_max_length, truncation=True, return_tensors="pt"
        ).input_ids
        output = encoder(ids.to(encoder.device), output_hidden_states=True)
        hidden.append(output.hidden_states[-2])
        if output[0].ndim == 2:  # CLIPTextModelWithProjection: text_embeds
            pooled = output[0]
    dtype = base.text_encoder_2.dtype
    return torch.cat(hidden, dim=-1).to(dtype), pooled.to(dtype)


@torch.no_grad()
def encode_prompt(base: SDXLBase, prompt: str, negative_prompt: str | None = None) -> PromptEmbeddings:
    """SDXL prompt embeddings (see the module docstring)."""
    if not isinstance(prompt, str) or not (negative_prompt is None or isinstance(negative_prompt, str)):
        raise ValueError(
            f"encode_prompt: prompt and negative_prompt must be strings, got {prompt!r}, {negative_prompt!r}"
        )
    device = base.unet.device
    with visiting(base.text_encoder, device), visiting(base.text_encoder_2, device):
        text, pooled = _encode_text(base, prompt)
        if negative_prompt is None and base.force_zeros_for_empty_prompt:
            negative_text, negative_pooled = torch.zeros_like(text), torch.zeros_like(pooled)
        else:
            negative_text, negative_pooled = _encode_text(base, negative_prompt or "")
    return PromptEmbeddings(text, pooled, negative_text, negative_pooled)


@torch.no_grad()
def image_features(encoder, images: torch.Tensor) -> torch.Tensor:
    """Penultimate hidden states [B, T, hidden] of ``encoder`` for IMAGE batch ``images`` [B, H, W, 3]."""
    pixels = clip_preprocess(check_images(images, "image_features: images"), encoder.config.image_size)
    pixels = pixels.to(device=encoder.device, dtype=encoder.dtype)
    return encoder(pixels, output_hidden_states=True).hidden_states[-2]


def image_tokens(models: DiffusionModels, kind: str, images: torch.Tensor) -> ImageTokens:
    """CSGO tokens of ``kind`` ("content" or "style") of each image of ``images`` [B, H, W, 3];
    the image encoder runs on the UNet's device."""
    with visiting(models.image_encoder, models.base.unet.device):
        features = image_features(models.image_encoder, images)
    return models.csgo.tokens(kind, features)


def content_tokens(models: DiffusionModels, content_images: torch.Tensor) -> ImageTokens | None:
    """CSGO content tokens of each view [B, 4, D] (None without CSGO)."""
    if models.csgo is None:
        return None
    return image_tokens(models, "content", content_images)


@dataclass
class StyleConditioning:
    """What every group of a scene shares: the prompt and the style tokens [1, Q, D] (None without CSGO)."""

    prompt: PromptEmbeddings
    style: ImageTokens | None


def prepare_conditioning(
    models: DiffusionModels,
    style_image: torch.Tensor | None,
    prompt: str,
    negative_prompt: str | None = None,
) -> StyleConditioning:
    """Encode the prompt and, when CSGO is loaded, the style image ([1, H, W, 3] or [H, W, 3])."""
    embeddings = encode_prompt(models.base, prompt, negative_prompt)
    if models.csgo is None:
        return StyleConditioning(embeddings, None)
    if style_image is None:
        raise ValueError("prepare_conditioning: style_image is required when CSGO weights are loaded")
    if isinstance(style_image, torch.Tensor) and style_image.ndim == 3:
        style_image = style_image.unsqueeze(0)
    style_image = check_images(style_image, "prepare_conditioning: style_image")
    if style_image.shape[0] != 1:
        raise ValueError(
            f"prepare_conditioning: style_image must hold one image, got a batch of {style_image.shape[0]}"
        )
    style = image_tokens(models, "style", style_image)
    return StyleConditioning(embeddings, style)
