"""The native path (the pack's patches on ComfyUI's own models, sampled by ComfyUI) equals the diffusers path.

Runs when ARTNVG_COMFYUI_ROOT names a ComfyUI checkout (conftest.py): native_path.py runs in ComfyUI's
Python, in process, on tiny random SDXL-architecture models that this test builds and writes (widths
that ComfyUI's fixed 32-group norms and 256-wide size embedding accept), and the library's
``stylize_group`` samples the same models with diffusers. Same scheduler on both sides: DDIM (ComfyUI's
``ddim`` sampler with its ``simple`` schedule, diffusers' DDIMScheduler with trailing timesteps and a
final step to sigma 0: the same timesteps 999, 749, 499, 249 for 4 steps), same seed and initial noise,
the same prompt embeddings. Content views are 224 px (the tiny image encoder's size) with values on the
1/255 grid, so both CLIP preprocessings are the normalisation alone; sampling is at 64 px.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
import torch
from diffusers import AutoencoderKL, UNet2DConditionModel
from diffusion_tiny import (
    CROSS_DIM,
    RESAMPLER_HEAD_WIDTH,
    TEXT_WIDTH,
    csgo_state,
    tiny_controlnet,
    tiny_image_encoder,
    tiny_text_encoders,
    tiny_tokenizer,
    write_csgo_file,
)
from safetensors.torch import load_file, save_file

from artnvg_core.diffusion.architectures import SDXL_SCHEDULER_CONFIG, SDXL_UNET_CONFIG, SDXL_VAE_CONFIG
from artnvg_core.diffusion.conditioning import prepare_conditioning
from artnvg_core.diffusion.csgo_weights import load_csgo
from artnvg_core.diffusion.models import DiffusionModels, SDXLBase
from artnvg_core.diffusion.sampler import stylize_group
from artnvg_core.diffusion.settings import SamplerSettings

SCRIPT = Path(__file__).with_name("native_path.py")
TOLERANCE = 2e-4  # on images in [0, 1], float32 on both sides
VIEWS = 3
COMMON = dict(seed=7, steps=4, cfg=5.0, style_scale=0.8, content_scale=1.2, control_scale=0.9, resolution=64)
CASES = {
    "nv_released": dict(COMMON, neighbour_views=True, content_routing="released"),
    "per_view_released": dict(COMMON, neighbour_views=False, content_routing="released"),
    "nv_paper": dict(COMMON, neighbour_views=True, content_routing="paper"),
    "per_view_paper": dict(COMMON, neighbour_views=False, content_routing="paper"),
    # guidance in the first 1 of 4 steps (the presets' cfg_until): two chained runs of ComfyUI's sampler
    "nv_released_guided_1_of_4": dict(COMMON, neighbour_views=True, content_routing="released", cfg_until=0.25),
    # the same weights, the ControlNet's keyed by module path (the other layout CSGO's loader reads)
    "nv_released_module_path_keys": dict(COMMON, neighbour_views=True, content_routing="released",
                                         csgo_file="csgo_by_path.bin"),
    # in ComfyUI's low-VRAM state (--lowvram): the feed-forward layers one sample at a time
    "nv_released_low_vram": dict(COMMON, neighbour_views=True, content_routing="released", low_vram=True),
}


def _models(tmp_path: Path) -> DiffusionModels:
    """Tiny SDXL-architecture models that ComfyUI's modules can also hold (widths multiples of 32, SDXL's
    256-wide size embedding, the standard ControlNet hint encoder), with CSGO loaded (its file with the
    optional UNet conv_in); the files hold the weights before CSGO's."""
    torch.manual_seed(0)
    unet = UNet2DConditionModel(**dict(
        SDXL_UNET_CONFIG, sample_size=8, block_out_channels=(32, 64, 64), transformer_layers_per_block=(1, 1, 2),
        attention_head_dim=(4, 8, 8), cross_attention_dim=CROSS_DIM, projection_class_embeddings_input_dim=6 * 256
        + TEXT_WIDTH)).eval()
    torch.manual_seed(1)
    vae = AutoencoderKL(**dict(SDXL_VAE_CONFIG, block_out_channels=(32,) * 4, layers_per_block=1, sample_size=64)).eval()
    text_encoder, text_encoder_2 = tiny_text_encoders()
    scheduler = dict(SDXL_SCHEDULER_CONFIG, timestep_spacing="trailing", set_alpha_to_one=True)
    base = SDXLBase(unet, vae, text_encoder, text_encoder_2, tiny_tokenizer(), tiny_tokenizer(pad_token="!"), scheduler)
    controlnet = tiny_controlnet(unet, hint_channels=(16, 32, 96, 256))
    generator = torch.Generator().manual_seed(5)
    conv_in = {name: 0.2 * torch.randn(value.shape, generator=generator) for name, value in unet.conv_in.state_dict().items()}
    path = write_csgo_file(tmp_path / "csgo.bin", {**csgo_state(unet, controlnet), "conv_in_unet_sd": conv_in})
    write_csgo_file(tmp_path / "csgo_by_path.bin",
                    {**csgo_state(unet, controlnet, controlnet_by_index=False), "conv_in_unet_sd": conv_in})
    weights = {"unet": unet.state_dict(), "controlnet": controlnet.state_dict(), "vae": vae.state_dict()}
    encoder = tiny_image_encoder()
    weights["image_encoder"] = encoder.state_dict()
    for name, state in weights.items():
        save_file({k: v.contiguous() for k, v in state.items()}, str(tmp_path / f"{name}.safetensors"))
    configs = {"unet": dict(unet.config), "vae": dict(vae.config), "image_encoder": encoder.config.to_dict(),
               "resampler_head_width": RESAMPLER_HEAD_WIDTH}
    (tmp_path / "configs.json").write_text(json.dumps(configs, default=list))
    csgo = load_csgo(path, unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    return DiffusionModels(base=base, controlnet=controlnet, image_encoder=encoder, csgo=csgo)


def _inputs(tmp_path: Path, models: DiffusionModels) -> dict:
    generator = torch.Generator().manual_seed(3)
    views = torch.randint(0, 256, (VIEWS, 224, 224, 3), generator=generator).float() / 255
    style = torch.randint(0, 256, (1, 224, 224, 3), generator=generator).float() / 255
    conditioning = prepare_conditioning(models, style, "a painting", "blurry")
    prompt = conditioning.prompt
    centers = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]], dtype=torch.float64)
    save_file({"content_views": views, "style_image": style, "text": prompt.text, "pooled": prompt.pooled,
               "negative_text": prompt.negative_text, "negative_pooled": prompt.negative_pooled, "centers": centers},
              str(tmp_path / "inputs.safetensors"))
    return {"views": views, "conditioning": conditioning}


def _reference(models: DiffusionModels, inputs: dict, case: dict) -> torch.Tensor:
    settings = SamplerSettings(steps=case["steps"], guidance_scale=case["cfg"], content_scale=case["content_scale"],
                               style_scale=case["style_scale"], control_scale=case["control_scale"],
                               content_routing=case["content_routing"], neighbour_views=case["neighbour_views"],
                               resolution=case["resolution"], scheduler="ddim", cfg_until=case.get("cfg_until", 1.0))
    return stylize_group(models, inputs["views"], inputs["conditioning"], settings, seed=case["seed"])


@pytest.fixture(scope="module")
def outputs(tmp_path_factory, comfy_checkout):
    checkout, python = comfy_checkout
    folder = tmp_path_factory.mktemp("native")
    models = _models(folder)
    inputs = _inputs(folder, models)
    (folder / "cases.json").write_text(json.dumps(CASES))
    reference = {name: _reference(models, inputs, case) for name, case in CASES.items()}
    run = subprocess.run([python, str(SCRIPT), str(checkout), str(folder)], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, f"native_path.py failed:\n{run.stdout[-3000:]}\n{run.stderr[-6000:]}"
    return reference, load_file(folder / "native.safetensors"), json.loads((folder / "checks.json").read_text())


@pytest.mark.parametrize("case", list(CASES))
def test_native_path_equals_the_diffusers_path(outputs, case):
    reference, native, _ = outputs
    assert native[case].shape == reference[case].shape
    torch.testing.assert_close(native[case], reference[case], rtol=0, atol=TOLERANCE)


def test_each_patch_changes_the_result_well_beyond_the_tolerance(outputs):
    """The comparison can see the patches: NV on/off, the content routing and the guided steps each move the
    images by far more than the tolerance, so a native path that lost one could not pass."""
    _, native, _ = outputs
    for first, second in (("nv_released", "per_view_released"), ("nv_paper", "nv_released"),
                          ("per_view_paper", "per_view_released"), ("nv_released_guided_1_of_4", "nv_released")):
        assert (native[first] - native[second]).abs().max() > 10 * TOLERANCE, (first, second)


def test_low_vram_runs_each_feed_forward_one_sample_at_a_time(outputs):
    """Under --lowvram every GEGLU of the UNet and the ControlNet sees one sample (the case is held to the
    diffusers path by test_native_path_equals_the_diffusers_path); otherwise the whole batch: both guidance
    halves of the views."""
    batches = outputs[2]["feed_forward_batches"]
    assert batches["nv_released_low_vram"] == [1]
    assert batches["nv_released"] == [2 * VIEWS]


def test_inputs_of_the_wrong_kind_are_named_before_sampling(outputs):
    errors = outputs[2]["errors"]
    assert errors["model"].startswith("Apply CSGO: input 'model': a BaseModel checkpoint; CSGO needs SDXL")
    assert errors["control_net"].startswith("Apply CSGO: input 'control_net': a VAE; expected an SDXL ControlNet")
    assert errors["sample_group_control_net"].startswith("Sample Group: input 'control_net': a VAE; expected an SDXL "
                                                          "ControlNet")
    assert errors["clip_vision"].startswith("Apply CSGO: input 'clip_vision': its features are 24 wide, CSGO's "
                                            "resamplers read 16: use ViT-bigG/14")
    assert errors["csgo"].startswith("Apply CSGO: input 'csgo': 'csgo.bin' does not fit this MODEL's cross-attention")
    assert re.search(r"wrong shapes \['\d+\.to_k_ip\.weight \[64, 15\] != \[64, 16\]'", errors["csgo"])


def test_sample_group_moves_comfyuis_progress_bar_and_stops_on_cancel(outputs):
    checks = outputs[2]
    assert checks["progress"][-1] == [2, 2] and [value for value, _ in checks["progress"]] == [1, 2]
    assert checks["cancel"] == "InterruptProcessingException"
