"""The pack's native path inside ComfyUI's own Python, in process: run by test_native_path.py.

Usage: ``python native_path.py COMFYUI_CHECKOUT FOLDER``. FOLDER holds what the test wrote: tiny
SDXL-architecture models in diffusers' key layout (``unet``, ``controlnet``, ``vae``, ``image_encoder``
.safetensors, with ``configs.json``), ``csgo.bin``, ``inputs.safetensors`` (content views, style image,
prompt embeddings, camera centres) and ``cases.json``. ComfyUI's checkpoint detection knows full-size
models only, so the script builds ComfyUI's own model objects (``comfy.supported_models.SDXL``, the
ControlNet loader, ``comfy.sd.VAE``, ``comfy.clip_vision.ClipVisionModel``) from those weights with
ComfyUI's own key converters, then runs the pack's nodes on them: NV-Attention Patch Model, Apply CSGO
and Sample Group, which samples through ``comfy.sample``; a case with ``low_vram`` runs in ComfyUI's
low-VRAM state (``--lowvram``). Writes ``native.safetensors`` (one IMAGE per case) and ``checks.json``:
the batch sizes each case's feed-forward layers (ComfyUI's GEGLU) saw, the errors Apply CSGO and Sample
Group give for inputs of the wrong kind, and what ComfyUI's progress bar saw and raised when a Sample
Group run is cancelled.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

REPO = Path(__file__).resolve().parents[2]


def _comfy_unet_config(config: dict) -> dict:
    """ComfyUI's UNet config of a diffusers SDXL-architecture UNet config."""
    widths, depths = config["block_out_channels"], config["transformer_layers_per_block"]
    depths = [d if kind.startswith("CrossAttn") else 0 for d, kind in zip(depths, config["down_block_types"])]
    layers = config["layers_per_block"]
    return {
        "use_checkpoint": False, "image_size": 32, "out_channels": 4, "in_channels": 4, "use_spatial_transformer": True,
        "legacy": False, "num_classes": "sequential", "adm_in_channels": config["projection_class_embeddings_input_dim"],
        "model_channels": widths[0], "num_res_blocks": [layers] * len(widths),
        "channel_mult": [w // widths[0] for w in widths], "transformer_depth": [d for d in depths for _ in range(layers)],
        "transformer_depth_output": [d for d in depths for _ in range(layers + 1)], "transformer_depth_middle": depths[-1],
        "use_linear_in_transformer": True, "context_dim": config["cross_attention_dim"],
        "num_head_channels": widths[0] // config["attention_head_dim"][0], "use_temporal_attention": False,
        "use_temporal_resblock": False,
    }


def _model(folder: Path, configs: dict):
    import comfy.model_management
    import comfy.model_patcher
    import comfy.supported_models
    import comfy.utils

    unet_config = _comfy_unet_config(configs["unet"])
    model_config = comfy.supported_models.SDXL(unet_config)
    model_config.unet_config.update(unet_config)  # SDXL's class sets 64-channel heads over the tiny model's
    model_config.set_inference_dtype(torch.float32, None)
    model = model_config.get_model({}, "")
    weights = load_file(folder / "unet.safetensors")
    converted = {ldm: weights[key] for key, ldm in comfy.utils.unet_to_diffusers(unet_config).items() if key in weights}
    model.diffusion_model.load_state_dict(converted, strict=True)
    device = comfy.model_management.get_torch_device()
    return comfy.model_patcher.ModelPatcher(model, load_device=device, offload_device=device), unet_config


def _controlnet(folder: Path, unet_config: dict):
    """ComfyUI's loader of diffusers-format ControlNets, told the tiny config its detection cannot find."""
    import comfy.controlnet
    import comfy.model_detection

    detect = comfy.model_detection.unet_config_from_diffusers_unet
    comfy.model_detection.unet_config_from_diffusers_unet = lambda *args, **kwargs: dict(unet_config)
    try:
        return comfy.controlnet.load_controlnet_state_dict(load_file(folder / "controlnet.safetensors"),
                                                           model_options={"dtype": torch.float32})
    finally:
        comfy.model_detection.unet_config_from_diffusers_unet = detect


def _vae(folder: Path, configs: dict):
    import comfy.sd

    config = configs["vae"]
    ddconfig = {"double_z": True, "z_channels": config["latent_channels"], "resolution": 256, "in_channels": 3,
                "out_ch": 3, "ch": config["block_out_channels"][0],
                "ch_mult": [c // config["block_out_channels"][0] for c in config["block_out_channels"]],
                "num_res_blocks": config["layers_per_block"], "attn_resolutions": [], "dropout": 0.0}
    return comfy.sd.VAE(sd=load_file(folder / "vae.safetensors"), dtype=torch.float32,
                        config={"params": {"ddconfig": ddconfig, "embed_dim": config["latent_channels"]}})


def _clip_vision(folder: Path, configs: dict, load: bool = True):
    import comfy.clip_vision

    config_file = folder / f"clip_vision_{configs['image_encoder']['hidden_size']}.json"
    config_file.write_text(json.dumps(configs["image_encoder"]))
    clip_vision = comfy.clip_vision.ClipVisionModel(str(config_file))
    if load:
        missing, unexpected = clip_vision.load_sd(load_file(folder / "image_encoder.safetensors"))
        assert not missing and not unexpected, (missing, unexpected)
    return clip_vision


def _pack():
    """The pack, imported as ComfyUI imports a custom node folder (a package of its own name)."""
    spec = importlib.util.spec_from_file_location("artnvg_pack", REPO / "__init__.py",
                                                  submodule_search_locations=[str(REPO)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["artnvg_pack"] = module
    spec.loader.exec_module(module)
    return importlib.import_module("artnvg_pack.nodes.model_patch_nodes"), importlib.import_module(
        "artnvg_pack.nodes.diffusion_nodes")


def _errors(patch_nodes, model, control_net, vae, clip_vision, csgo, style, folder: Path, configs: dict) -> dict:
    """Apply CSGO's message for each kind of wrong input: a non-SDXL model (SD 1.5's class over a UNet of
    the same tiny size), something else as the ControlNet, a CLIP Vision model of another width, a CSGO
    file whose weights do not fit the MODEL."""
    import dataclasses

    import comfy.model_patcher
    import comfy.supported_models

    sd15_config = dict(_comfy_unet_config(configs["unet"]), adm_in_channels=None, num_classes=None)
    sd15 = comfy.supported_models.SD15(sd15_config)
    sd15.unet_config.update(sd15_config)
    sd15.set_inference_dtype(torch.float32, None)
    other_model = comfy.model_patcher.ModelPatcher(sd15.get_model({}, ""), load_device="cpu", offload_device="cpu")
    wide = dict(configs["image_encoder"], hidden_size=24, intermediate_size=48)
    other_clip = _clip_vision(folder, {"image_encoder": wide}, load=False)
    mismatched = dataclasses.replace(csgo, unet_branches={k: v[:, :-1] for k, v in csgo.unet_branches.items()})
    wrong = {"model": (other_model, control_net, csgo, clip_vision), "control_net": (model, vae, csgo, clip_vision),
             "clip_vision": (model, control_net, csgo, other_clip), "csgo": (model, control_net, mismatched, clip_vision)}
    messages = {}
    for name, (model_, control_, csgo_, clip_) in wrong.items():
        try:
            patch_nodes.ApplyCSGO().apply(model_, control_, csgo_, clip_, style, 0.6, 1.0, "released")
            messages[name] = None
        except ValueError as error:
            messages[name] = str(error)
    return messages


def _cancelled(sample) -> dict:
    """Sample Group under ComfyUI's progress hook (2 steps, the first guided: two sampler runs): the steps it
    reports, then the exception a pressed Cancel (ComfyUI's interrupt flag) raises at the next step."""
    import comfy.model_management
    import comfy.utils

    reported = []
    comfy.utils.set_progress_bar_global_hook(lambda value, total, preview, **_: reported.append([value, total]))
    sample()
    comfy.model_management.interrupt_current_processing(True)
    try:
        sample()
        raised = None
    except Exception as error:  # ComfyUI's InterruptProcessingException
        raised = type(error).__name__
    finally:
        comfy.model_management.interrupt_current_processing(False)
        comfy.utils.set_progress_bar_global_hook(None)
    return {"progress": reported, "cancel": raised}


def main(checkout: Path, folder: Path) -> None:
    sys.path.insert(0, str(checkout))
    from comfy.cli_args import args

    args.cpu = True  # as ``main.py --cpu``, before comfy.model_management reads it
    patch_nodes, diffusion_nodes = _pack()
    from artnvg_core.diffusion.csgo_weights import read_csgo
    from artnvg_core.grouping import ViewGroup, ViewGroups

    configs = json.loads((folder / "configs.json").read_text())
    cases = json.loads((folder / "cases.json").read_text())
    inputs = load_file(folder / "inputs.safetensors")
    model, unet_config = _model(folder, configs)
    control_net, vae, clip_vision = _controlnet(folder, unet_config), _vae(folder, configs), _clip_vision(folder, configs)
    head_width = configs["resampler_head_width"]
    csgo = read_csgo(folder / "csgo.bin", dim_head=head_width)
    views = inputs["content_views"]
    groups = ViewGroups((ViewGroup(tuple(range(len(views)))),), len(views),
                        centers=tuple(map(tuple, inputs["centers"].tolist())))
    positive = [[inputs["text"], {"pooled_output": inputs["pooled"]}]]
    negative = [[inputs["negative_text"], {"pooled_output": inputs["negative_pooled"]}]]
    import comfy.ldm.modules.attention
    import comfy.model_management as model_management

    outputs, batches, normal = {}, {}, model_management.vram_state

    def feed_forward_batches(module, args, output) -> None:
        if isinstance(module, comfy.ldm.modules.attention.GEGLU):
            batches[name].add(args[0].shape[0])

    hook = torch.nn.modules.module.register_module_forward_hook(feed_forward_batches)
    with torch.inference_mode():
        for name, case in cases.items():
            batches[name] = set()
            model_management.vram_state = model_management.VRAMState.LOW_VRAM if case.get("low_vram") else normal
            patched, control = patch_nodes.ApplyCSGO().apply(
                model, control_net, read_csgo(folder / case.get("csgo_file", "csgo.bin"), dim_head=head_width),
                clip_vision, inputs["style_image"], case["style_scale"],
                case["content_scale"], case["content_routing"])
            (patched,) = patch_nodes.NVAttentionPatch().patch(patched, case["neighbour_views"])
            (outputs[name],) = diffusion_nodes.SampleGroup().sample(
                patched, positive, negative, vae, control, views, groups, -1, case["seed"], case["steps"], case["cfg"],
                "ddim", "simple", 1.0, case["control_scale"], case["resolution"], "long_side", case.get("cfg_until", 1.0))
        model_management.vram_state = normal
        hook.remove()
        errors = _errors(patch_nodes, model, control_net, vae, clip_vision, csgo, inputs["style_image"], folder, configs)
        try:  # the VAE given as Sample Group's ControlNet
            diffusion_nodes.SampleGroup().sample(model, positive, negative, vae, vae, views, groups, 0, 0, 1, 5.0, "ddim",
                                                 "simple", 1.0, 1.0, 64, "long_side")
        except ValueError as error:
            errors["sample_group_control_net"] = str(error)
        checks = {"feed_forward_batches": {name: sorted(sizes) for name, sizes in batches.items()},
                  "errors": errors,
                  **_cancelled(lambda: diffusion_nodes.SampleGroup().sample(
                      model, positive, negative, vae, control_net, views, groups, 0, 0, 2, 5.0, "euler", "simple", 1.0,
                      1.0, 64, "long_side", 0.5))}
    save_file({name: image.contiguous() for name, image in outputs.items()}, str(folder / "native.safetensors"))
    (folder / "checks.json").write_text(json.dumps(checks))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
