"""Reference architectures (configs only, no weights) of the models ArtNVG runs.

* :data:`SDXL_UNET_CONFIG` / :data:`SDXL_VAE_CONFIG`: stabilityai/stable-diffusion-xl-base-1.0
  (``unet/config.json`` / ``vae/config.json``).
* :data:`SDXL_SCHEDULER_CONFIG`: its noise schedule (``scheduler/scheduler_config.json``),
  for DDIM and the other diffusers schedulers.
* :data:`CLIP_L_TEXT_CONFIG` / :data:`BIGG_TEXT_CONFIG`: SDXL's two text encoders (OpenAI CLIP
  ViT-L/14 text tower, OpenCLIP ViT-bigG/14 text tower with projection), transformers
  ``CLIPTextConfig`` fields; the token ids are CLIP's BPE ids (49406 start, 49407 end).
* :func:`controlnet_config_from_unet`: an SDXL ControlNet of the UNet's architecture (what
  diffusers' ``ControlNetModel.from_unet`` builds; the TTPlanet tile ControlNet has it).
* :data:`VIT_BIGG_IMAGE_ENCODER_CONFIG`: the IP-Adapter SDXL image encoder
  (h94/IP-Adapter ``sdxl_models/image_encoder``: OpenCLIP ViT-bigG/14 vision tower,
  hidden 1664, 48 layers, 16 heads, projection 1280).

Used to build models from single weight files that carry no config, and to build
full-size randomly initialised models for benchmarks.
"""

from __future__ import annotations

from collections.abc import Mapping

SDXL_UNET_CONFIG = dict(
    sample_size=128,
    in_channels=4,
    out_channels=4,
    down_block_types=("DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D"),
    up_block_types=("CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"),
    block_out_channels=(320, 640, 1280),
    layers_per_block=2,
    transformer_layers_per_block=(1, 2, 10),
    attention_head_dim=(5, 10, 20),
    cross_attention_dim=2048,
    norm_num_groups=32,
    use_linear_projection=True,
    addition_embed_type="text_time",
    addition_time_embed_dim=256,
    projection_class_embeddings_input_dim=2816,
)

SDXL_SCHEDULER_CONFIG = dict(
    num_train_timesteps=1000,
    beta_start=0.00085,
    beta_end=0.012,
    beta_schedule="scaled_linear",
    steps_offset=1,
    timestep_spacing="leading",
    clip_sample=False,
    set_alpha_to_one=False,
)

SDXL_VAE_CONFIG = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=("DownEncoderBlock2D",) * 4,
    up_block_types=("UpDecoderBlock2D",) * 4,
    block_out_channels=(128, 256, 512, 512),
    layers_per_block=2,
    latent_channels=4,
    norm_num_groups=32,
    sample_size=1024,
    scaling_factor=0.13025,
    force_upcast=True,
)

CLIP_L_TEXT_CONFIG = dict(
    vocab_size=49408,
    hidden_size=768,
    intermediate_size=3072,
    num_hidden_layers=12,
    num_attention_heads=12,
    max_position_embeddings=77,
    hidden_act="quick_gelu",
    layer_norm_eps=1e-5,
    projection_dim=768,
    bos_token_id=49406,
    eos_token_id=49407,
    pad_token_id=49407,
)

BIGG_TEXT_CONFIG = dict(
    CLIP_L_TEXT_CONFIG,
    hidden_size=1280,
    intermediate_size=5120,
    num_hidden_layers=32,
    num_attention_heads=20,
    hidden_act="gelu",
    projection_dim=1280,
    pad_token_id=0,  # its tokenizer pads with "!"
)

VIT_BIGG_IMAGE_ENCODER_CONFIG = dict(
    hidden_size=1664,
    intermediate_size=8192,
    num_hidden_layers=48,
    num_attention_heads=16,
    image_size=224,
    patch_size=14,
    projection_dim=1280,
    hidden_act="gelu",
    layer_norm_eps=1e-5,
)

_CONTROLNET_FIELDS_FROM_UNET = (
    "in_channels",
    "flip_sin_to_cos",
    "freq_shift",
    "down_block_types",
    "only_cross_attention",
    "block_out_channels",
    "layers_per_block",
    "downsample_padding",
    "mid_block_scale_factor",
    "act_fn",
    "norm_num_groups",
    "norm_eps",
    "cross_attention_dim",
    "transformer_layers_per_block",
    "attention_head_dim",
    "num_attention_heads",
    "use_linear_projection",
    "class_embed_type",
    "num_class_embeds",
    "upcast_attention",
    "resnet_time_scale_shift",
    "projection_class_embeddings_input_dim",
    "addition_embed_type",
    "addition_time_embed_dim",
    "mid_block_type",
)


def controlnet_config_from_unet(unet_config: Mapping) -> dict:
    """ControlNetModel kwargs mirroring ``unet_config`` (fields the UNet config lacks keep their defaults)."""
    config = {key: unet_config[key] for key in _CONTROLNET_FIELDS_FROM_UNET if key in unet_config}
    config.update(conditioning_embedding_out_channels=(16, 32, 96, 256), conditioning_channels=3)
    return config


def transformers_config_kwargs(config: Mapping) -> dict:
    """A transformers ``config.json``'s entries as its config class takes them: without the file's
    ``architectures``, ``model_type`` and dtype entries."""
    return {k: v for k, v in config.items() if k not in ("architectures", "model_type", "torch_dtype", "dtype")}
