"""Tiny randomly initialised models with SDXL's architecture, for the diffusion tests.

Same model classes and wiring as SDXL (dual CLIP text encoders, text_time additional
embeddings, CrossAttn down/up blocks with several transformer layers, a ControlNet built
from the UNet, an 8x VAE, a CLIP vision encoder with projection): the library's reference
configs (:mod:`artnvg_core.diffusion.architectures`) with widths of a few channels, so a whole
sampling run takes a fraction of a second on a CPU.

Test modules import the autouse fixture ``one_cpu_thread``.
``write_csgo_file`` writes a CSGO weight file in the released key layout, enumerating the
processors itself (independently of artnvg_core's key layout code).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from diffusers import (
    AutoencoderKL,
    ControlNetModel,
    DDIMScheduler,
    UNet2DConditionModel,
)
from transformers import (
    CLIPTextConfig,
    CLIPTextModel,
    CLIPTextModelWithProjection,
    CLIPTokenizer,
    CLIPVisionConfig,
    CLIPVisionModelWithProjection,
)
from transformers.convert_slow_tokenizer import bytes_to_unicode

from artnvg_core.diffusion.architectures import (
    CLIP_L_TEXT_CONFIG,
    SDXL_SCHEDULER_CONFIG,
    SDXL_UNET_CONFIG,
    SDXL_VAE_CONFIG,
    VIT_BIGG_IMAGE_ENCODER_CONFIG,
)
from artnvg_core.diffusion.resampler import PerceiverResampler, ResamplerConfig

TEXT_WIDTH = 8  # each text encoder; the UNet's cross-attention width is 2 * TEXT_WIDTH
CROSS_DIM = 2 * TEXT_WIDTH
TIME_EMBED_DIM = 4
ENCODER_WIDTH = 16
RESAMPLER_HEAD_WIDTH = 64


@pytest.fixture(autouse=True, scope="module")
def one_cpu_thread():
    """Run a test module with one intra-op thread (tiny models spend their time in threading overhead,
    badly so on a loaded CPU); imported by each diffusion test module, restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_unet(seed: int = 0) -> UNet2DConditionModel:
    torch.manual_seed(seed)
    return UNet2DConditionModel(**dict(
        SDXL_UNET_CONFIG,
        sample_size=8,
        block_out_channels=(8, 16, 32),
        transformer_layers_per_block=(1, 1, 2),
        attention_head_dim=(2, 4, 8),
        cross_attention_dim=CROSS_DIM,
        norm_num_groups=4,
        addition_time_embed_dim=TIME_EMBED_DIM,
        projection_class_embeddings_input_dim=6 * TIME_EMBED_DIM + TEXT_WIDTH,
    )).eval()


def tiny_controlnet(unet: UNet2DConditionModel, seed: int = 1,
                    hint_channels: tuple[int, ...] = (4, 8, 8, 16)) -> ControlNetModel:
    """A ControlNet of the UNet's architecture (its hint encoder's widths ``hint_channels``); its
    zero-initialised convolutions are made random."""
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=hint_channels)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in controlnet.parameters():
            if not param.any():
                param.copy_(0.05 * torch.randn(param.shape, generator=generator))
    return controlnet.eval()


def tiny_vae(seed: int = 2) -> AutoencoderKL:
    torch.manual_seed(seed)
    return AutoencoderKL(**dict(
        SDXL_VAE_CONFIG, block_out_channels=(4, 4, 8, 8), layers_per_block=1, norm_num_groups=2, sample_size=64
    )).eval()


def tiny_tokenizer(pad_token: str = "<|endoftext|>") -> CLIPTokenizer:
    """A CLIP BPE tokenizer without merges: one token per byte (vocab 514)."""
    chars = list(bytes_to_unicode().values())
    vocab = {c: i for i, c in enumerate(chars)}
    vocab.update({c + "</w>": len(chars) + i for i, c in enumerate(chars)})
    vocab.update({"<|startoftext|>": 512, "<|endoftext|>": 513})
    return CLIPTokenizer(vocab=vocab, merges=[], pad_token=pad_token, model_max_length=77)


def _text_config() -> CLIPTextConfig:
    """CLIP ViT-L/14's text tower (both tiny encoders use it), over the byte vocabulary of :func:`tiny_tokenizer`."""
    return CLIPTextConfig(**dict(
        CLIP_L_TEXT_CONFIG,
        vocab_size=514,
        hidden_size=TEXT_WIDTH,
        intermediate_size=16,
        num_hidden_layers=2,
        num_attention_heads=2,
        projection_dim=TEXT_WIDTH,
        bos_token_id=512,
        eos_token_id=513,
        pad_token_id=513,
    ))


def tiny_text_encoders(seed: int = 3) -> tuple[CLIPTextModel, CLIPTextModelWithProjection]:
    torch.manual_seed(seed)
    return CLIPTextModel(_text_config()).eval(), CLIPTextModelWithProjection(_text_config()).eval()


def tiny_image_encoder(seed: int = 4) -> CLIPVisionModelWithProjection:
    torch.manual_seed(seed)
    config = CLIPVisionConfig(**dict(
        VIT_BIGG_IMAGE_ENCODER_CONFIG,
        hidden_size=ENCODER_WIDTH,
        intermediate_size=32,
        num_hidden_layers=3,
        num_attention_heads=2,
        projection_dim=8,
    ))
    return CLIPVisionModelWithProjection(config).eval()


def tiny_scheduler() -> DDIMScheduler:
    return DDIMScheduler(**SDXL_SCHEDULER_CONFIG)


def tiny_resampler(num_queries: int, seed: int = 5) -> PerceiverResampler:
    torch.manual_seed(seed)
    config = ResamplerConfig(
        num_queries=num_queries,
        embedding_dim=ENCODER_WIDTH,
        dim=CROSS_DIM,
        output_dim=CROSS_DIM,
        depth=2,
        heads=2,
        dim_head=RESAMPLER_HEAD_WIDTH,
        ff_mult=2,
    )
    return PerceiverResampler(config).eval()


def _image_branch_keys(model, routed_blocks: tuple[str, ...], by_index: bool, seed: int) -> dict[str, torch.Tensor]:
    """Random to_k_ip / to_v_ip tensors for every attn2 in ``routed_blocks``, in the released layout."""
    generator = torch.Generator().manual_seed(seed)
    keys = {}
    for index, name in enumerate(model.attn_processors):
        if name.endswith("attn2.processor") and name.startswith(routed_blocks):
            layer = model.get_submodule(name[: -len(".processor")])
            prefix = str(index) if by_index else name
            for proj in ("to_k_ip", "to_v_ip"):
                shape = (layer.to_k.out_features, layer.to_k.in_features)
                keys[f"{prefix}.{proj}.weight"] = 0.3 * torch.randn(shape, generator=generator)
    return keys


def csgo_state(
    unet: UNet2DConditionModel,
    controlnet: ControlNetModel,
    num_content_tokens: int = 4,
    num_style_tokens: int = 8,
    controlnet_by_index: bool = True,
    unet_content: bool = True,
) -> dict[str, dict[str, torch.Tensor]]:
    """A CSGO weight dict in the released layout with random tensors; ``unet_content=False`` leaves out
    the UNet down blocks' content entries, as a file saved from the released class does."""
    return {
        "content_image_proj": tiny_resampler(num_content_tokens, seed=6).state_dict(),
        "style_image_proj": tiny_resampler(num_style_tokens, seed=7).state_dict(),
        "ip_adapter": _image_branch_keys(unet, ("down_blocks", "up_blocks") if unet_content else ("up_blocks",), True,
                                         seed=8),
        "controlnet_adapter_modules": _image_branch_keys(controlnet, ("down_blocks",), controlnet_by_index, seed=9),
    }


def write_csgo_file(path: Path, state: dict[str, dict[str, torch.Tensor]]) -> Path:
    torch.save(state, path)
    return path


def tiny_base():
    """An SDXLBase of tiny models (DDIM scheduler config as SDXL's)."""
    from artnvg_core.diffusion.models import SDXLBase

    unet = tiny_unet()
    text_encoder, text_encoder_2 = tiny_text_encoders()
    return SDXLBase(
        unet=unet,
        vae=tiny_vae(),
        text_encoder=text_encoder,
        text_encoder_2=text_encoder_2,
        tokenizer=tiny_tokenizer(),
        tokenizer_2=tiny_tokenizer(pad_token="!"),
        scheduler_config=dict(tiny_scheduler().config),
    )


def tiny_models(tmp_path: Path | None = None, num_style_tokens: int = 8, unet_content: bool = True):
    """DiffusionModels of tiny models; with ``tmp_path``, CSGO weights are written there and loaded
    (``unet_content``: see :func:`csgo_state`)."""
    from artnvg_core.diffusion.csgo import (
        CONTROLNET_ROUTES,
        UNET_ROUTES,
        install_processors,
    )
    from artnvg_core.diffusion.csgo_weights import load_csgo
    from artnvg_core.diffusion.models import DiffusionModels

    base = tiny_base()
    controlnet = tiny_controlnet(base.unet)
    if tmp_path is None:
        install_processors(base.unet, UNET_ROUTES, image_branches=False)
        install_processors(controlnet, CONTROLNET_ROUTES, image_branches=False)
        return DiffusionModels(base=base, controlnet=controlnet)
    state = csgo_state(base.unet, controlnet, num_style_tokens=num_style_tokens, unet_content=unet_content)
    path = write_csgo_file(tmp_path / "csgo.bin", state)
    csgo = load_csgo(path, base.unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    return DiffusionModels(base=base, controlnet=controlnet, image_encoder=tiny_image_encoder(), csgo=csgo)


def diffusers_pipeline(base, scheduler, controlnet: ControlNetModel | None = None):
    """diffusers' own SDXL pipeline over ``base``'s models (an SDXLBase; the ControlNet pipeline with
    ``controlnet``), without watermarker or progress bar: the reference the tests compare with."""
    from diffusers import StableDiffusionXLControlNetPipeline, StableDiffusionXLPipeline

    parts = dict(vae=base.vae, text_encoder=base.text_encoder, text_encoder_2=base.text_encoder_2,
                 tokenizer=base.tokenizer, tokenizer_2=base.tokenizer_2, unet=base.unet, scheduler=scheduler,
                 add_watermarker=False)
    pipe = (StableDiffusionXLPipeline(**parts) if controlnet is None
            else StableDiffusionXLControlNetPipeline(controlnet=controlnet, **parts))
    pipe.set_progress_bar_config(disable=True)
    return pipe


def write_model_files(root: Path) -> dict[str, Path]:
    """Tiny model files in the layouts the loaders read: a diffusers SDXL folder, a ControlNet folder,
    a transformers image encoder folder and a CSGO ``.bin``; returns their paths by role."""
    base = tiny_base()
    diffusers_pipeline(base, tiny_scheduler()).save_pretrained(root / "sdxl")
    controlnet = tiny_controlnet(base.unet)
    controlnet.save_pretrained(root / "controlnet")
    tiny_image_encoder().save_pretrained(root / "image_encoder")
    write_csgo_file(root / "csgo.bin", csgo_state(base.unet, controlnet))
    return {"sdxl": root / "sdxl", "controlnet": root / "controlnet", "image_encoder": root / "image_encoder",
            "csgo": root / "csgo.bin"}


def _ldm_unet_keys(unet: UNet2DConditionModel) -> dict[str, str]:
    """diffusers UNet key -> key in an original (SGM) SDXL checkpoint, under ``model.diffusion_model.``."""
    per_block = unet.config.layers_per_block + 1
    resnet = {"norm1": "in_layers.0", "conv1": "in_layers.2", "norm2": "out_layers.0", "conv2": "out_layers.3",
              "time_emb_proj": "emb_layers.1", "conv_shortcut": "skip_connection"}
    top = {"time_embedding.linear_1": "time_embed.0", "time_embedding.linear_2": "time_embed.2",
           "add_embedding.linear_1": "label_emb.0.0", "add_embedding.linear_2": "label_emb.0.2",
           "conv_in": "input_blocks.0.0", "conv_norm_out": "out.0", "conv_out": "out.2"}
    mapping = {}
    for key in unet.state_dict():
        parts = key.split(".")
        head = key.rsplit(".", 1)[0]
        if head in top:
            new = f"{top[head]}.{parts[-1]}"
        elif parts[0] == "down_blocks":
            block, kind = int(parts[1]), parts[2]
            if kind == "downsamplers":
                new = f"input_blocks.{1 + block * per_block + per_block - 1}.0.op.{parts[-1]}"
            else:
                index = 1 + block * per_block + int(parts[3])
                rest = parts[4:] if kind == "attentions" else [resnet.get(parts[4], parts[4]), *parts[5:]]
                new = ".".join([f"input_blocks.{index}.{1 if kind == 'attentions' else 0}", *rest])
        elif parts[0] == "mid_block":
            index = {"resnets.0": 0, "attentions.0": 1, "resnets.1": 2}[".".join(parts[1:3])]
            rest = parts[3:] if parts[1] == "attentions" else [resnet.get(parts[3], parts[3]), *parts[4:]]
            new = ".".join([f"middle_block.{index}", *rest])
        else:  # up_blocks
            block, kind = int(parts[1]), parts[2]
            if kind == "upsamplers":
                has_attention = "attentions" in dict(unet.up_blocks[block].named_children())
                new = f"output_blocks.{block * per_block + per_block - 1}.{2 if has_attention else 1}.conv.{parts[-1]}"
            else:
                index = block * per_block + int(parts[3])
                rest = parts[4:] if kind == "attentions" else [resnet.get(parts[4], parts[4]), *parts[5:]]
                new = ".".join([f"output_blocks.{index}.{1 if kind == 'attentions' else 0}", *rest])
        mapping[key] = new
    return mapping


def _ldm_vae_state(vae: AutoencoderKL) -> dict[str, torch.Tensor]:
    """The VAE's weights in the original layout (under ``first_stage_model.``; attention as 1x1 convolutions)."""
    ups = len(vae.config.up_block_types)
    attention = {"group_norm": "norm", "to_q": "q", "to_k": "k", "to_v": "v", "to_out.0": "proj_out"}
    state = {}
    for key, tensor in vae.state_dict().items():
        new = key.replace("conv_norm_out", "norm_out").replace("conv_shortcut", "nin_shortcut")
        new = new.replace("mid_block.resnets.0", "mid.block_1").replace("mid_block.resnets.1", "mid.block_2")
        if "mid_block.attentions.0" in new:
            new = new.replace("mid_block.attentions.0", "mid.attn_1")
            for old, short in attention.items():
                new = new.replace(f".{old}.", f".{short}.")
            tensor = tensor[:, :, None, None] if tensor.ndim == 2 else tensor
        parts = new.split(".")
        if parts[1] == "down_blocks":
            new = ".".join([parts[0], "down", parts[2], *(["block", *parts[4:]] if parts[3] == "resnets"
                                                          else ["downsample", "conv", parts[-1]])])
        elif parts[1] == "up_blocks":
            new = ".".join([parts[0], "up", str(ups - 1 - int(parts[2])),
                            *(["block", *parts[4:]] if parts[3] == "resnets" else ["upsample", "conv", parts[-1]])])
        state[new] = tensor
    return state


def _open_clip_state(encoder: CLIPTextModelWithProjection) -> dict[str, torch.Tensor]:
    """The projected text encoder's weights in OpenCLIP's layout (fused q/k/v, transposed projection)."""
    text = {k.removeprefix("text_model."): v for k, v in encoder.state_dict().items()}
    state = {"token_embedding.weight": text["embeddings.token_embedding.weight"],
             "positional_embedding": text["embeddings.position_embedding.weight"],
             "ln_final.weight": text["final_layer_norm.weight"], "ln_final.bias": text["final_layer_norm.bias"],
             "text_projection": text["text_projection.weight"].T.contiguous()}
    names = {"layer_norm1": "ln_1", "layer_norm2": "ln_2", "mlp.fc1": "mlp.c_fc", "mlp.fc2": "mlp.c_proj",
             "self_attn.out_proj": "attn.out_proj"}
    for layer in range(encoder.config.num_hidden_layers):
        prefix = f"encoder.layers.{layer}."
        for old, new in names.items():
            for kind in ("weight", "bias"):
                state[f"transformer.resblocks.{layer}.{new}.{kind}"] = text[f"{prefix}{old}.{kind}"]
        for kind in ("weight", "bias"):
            state[f"transformer.resblocks.{layer}.attn.in_proj_{kind}"] = torch.cat(
                [text[f"{prefix}self_attn.{p}_proj.{kind}"] for p in "qkv"])
    return state


def write_single_file_checkpoint(path: Path, base) -> Path:
    """``base`` (an SDXLBase) as one ``.safetensors`` in the key layout of ``sd_xl_base_1.0.safetensors``."""
    from safetensors.torch import save_file

    unet_state = base.unet.state_dict()
    state = {f"model.diffusion_model.{new}": unet_state[old] for old, new in _ldm_unet_keys(base.unet).items()}
    state.update({f"first_stage_model.{k}": v for k, v in _ldm_vae_state(base.vae).items()})
    state.update({f"conditioner.embedders.0.transformer.text_model.{k.removeprefix('text_model.')}": v
                  for k, v in base.text_encoder.state_dict().items()})
    state.update({f"conditioner.embedders.1.model.{k}": v for k, v in _open_clip_state(base.text_encoder_2).items()})
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    return path


def kohya_lora_state(base, rank: int = 2, alpha: float = 1.0, seed: int = 10) -> dict[str, torch.Tensor]:
    """A random LoRA for ``base`` (an SDXLBase) in kohya's SDXL layout: ``lora_unet_{original key}`` for the
    UNet's self-attention queries and feed-forward outputs, ``lora_te1_`` / ``lora_te2_`` for both text
    encoders' attention projections (all four, as kohya trains them: diffusers reads a text encoder's part
    only when it holds ``out_proj``), each with ``lora_down`` [rank, in], ``lora_up`` [out, rank] and ``alpha``."""
    generator = torch.Generator().manual_seed(seed)
    modules = {"lora_unet_" + new.removesuffix(".weight").replace(".", "_"): base.unet.get_submodule(old[:-7])
               for old, new in _ldm_unet_keys(base.unet).items() if old.endswith(("attn1.to_q.weight", "ff.net.2.weight"))}
    for prefix, encoder in (("lora_te1_", base.text_encoder), ("lora_te2_", base.text_encoder_2)):
        for name, module in encoder.named_modules():
            if name.endswith(("self_attn.q_proj", "self_attn.k_proj", "self_attn.v_proj", "self_attn.out_proj")):
                modules[prefix + name.replace(".", "_")] = module
    state = {}
    for name, module in modules.items():
        state[f"{name}.lora_down.weight"] = torch.randn(rank, module.in_features, generator=generator)
        state[f"{name}.lora_up.weight"] = torch.randn(module.out_features, rank, generator=generator)
        state[f"{name}.alpha"] = torch.tensor(alpha)
    return state


def kohya_lora_deltas(base, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """What :func:`kohya_lora_state`'s LoRA adds at strength 1, by state-dict key of ``base``'s models
    (``unet.``, ``text_encoder.``, ``text_encoder_2.`` + the diffusers key): (alpha / rank) * up @ down."""
    names = {"lora_unet_" + new.removesuffix(".weight").replace(".", "_"): "unet." + old
             for old, new in _ldm_unet_keys(base.unet).items()}
    for prefix, part in (("lora_te1_", "text_encoder"), ("lora_te2_", "text_encoder_2")):
        names.update({prefix + key.removesuffix(".weight").replace(".", "_"): f"{part}.{key}"
                      for key in getattr(base, part).state_dict()})
    deltas = {}
    for key in state:
        if key.endswith(".alpha"):
            name = key.removesuffix(".alpha")
            down, up = state[f"{name}.lora_down.weight"].double(), state[f"{name}.lora_up.weight"].double()
            deltas[names[name]] = state[key].double() / down.shape[0] * up @ down
    return deltas
