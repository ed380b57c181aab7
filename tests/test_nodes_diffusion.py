"""Load ArtNVG Models, CSGO Encode, NV-Attention Patch and Sample Group on tiny SDXL-architecture models.

The model files are tiny randomly initialised models written to disk in the real layouts
(diffusers SDXL folder, ControlNet folder, transformers image encoder, CSGO ``.bin``);
node outputs are compared with the direct ``artnvg_core`` calls.
"""

from dataclasses import replace

import pytest
import torch
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import write_model_files

from artnvg_core.cameras import CameraSet
from artnvg_core.diffusion import compile_cache, speed
from artnvg_core.diffusion.conditioning import prepare_conditioning
from artnvg_core.diffusion.sampler import SamplerSettings
from artnvg_core.diffusion.speed import SpeedOptions, apply_speedups
from artnvg_core.diffusion.stylize import stylize_views
from artnvg_core.grouping import group_views
from artnvg_core.progress import Cancelled
from nodes import diffusion_nodes
from nodes.diffusion_nodes import (
    HF_CACHE,
    CSGOEncode,
    LoadArtNVGModels,
    NVAttentionPatch,
    SampleGroup,
)
from nodes.node_errors import NodeInputError

PROMPT, NEGATIVE = "a bear, oil painting", "blurry"


def call(node_class, **inputs):
    """Run a node's function as ComfyUI does."""
    with torch.inference_mode():
        return getattr(node_class(), node_class.FUNCTION)(**inputs)


def _images(count: int, seed: int, size: int = 64) -> torch.Tensor:
    return torch.rand(count, size, size, 3, generator=torch.Generator().manual_seed(seed))


def _line_cameras(count: int) -> CameraSet:
    """Cameras along the x axis (centres 0, 1, 2, ...): groups of neighbours are runs of views."""
    world_to_cam = torch.eye(4).repeat(count, 1, 1)
    world_to_cam[:, 0, 3] = -torch.arange(count, dtype=torch.float32)
    intrinsics = torch.tensor([[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]]).repeat(count, 1, 1)
    return CameraSet(world_to_cam, intrinsics, 64, 64, [f"view{i}" for i in range(count)])


@pytest.fixture(scope="module")
def model_files(tmp_path_factory):
    """Paths of tiny model files in the layouts the loader reads, by path input."""
    files = write_model_files(tmp_path_factory.mktemp("models"))
    return {"sdxl_checkpoint_path": str(files["sdxl"]), "controlnet_path": str(files["controlnet"]),
            "image_encoder_path": str(files["image_encoder"]), "csgo_weights_path": str(files["csgo"])}


LISTED = {"sdxl_checkpoint": HF_CACHE, "controlnet": HF_CACHE, "image_encoder": HF_CACHE, "csgo_weights": HF_CACHE}


@pytest.fixture(scope="module")
def loaded(model_files):
    assert LoadArtNVGModels.check_files(**LISTED, **model_files) is None
    (models,) = call(LoadArtNVGModels, **LISTED, dtype="float32", device="cpu", keep_loaded=True, **model_files)
    return models


def test_loader_reads_every_model_from_its_path(loaded):
    assert loaded.models.csgo.num_content_tokens == 4 and loaded.models.csgo.num_style_tokens == 8
    assert loaded.models.base.unet.dtype == torch.float32 and loaded.device == torch.device("cpu")
    assert loaded.keep_loaded and not loaded.neighbour_views


def test_loader_loads_once_per_process(loaded, model_files):
    """The same inputs give the models already loaded; another option loads afresh."""
    inputs = dict(LISTED, dtype="float32", device="cpu", keep_loaded=True, **model_files)
    (again,) = call(LoadArtNVGModels, **inputs)
    assert again.models is loaded.models and again is not loaded
    (other,) = call(LoadArtNVGModels, **dict(inputs, keep_loaded=False))
    assert other.models is not loaded.models


def test_missing_model_names_the_input_the_file_and_where_to_get_it(model_files, tmp_path, monkeypatch):
    listed = dict(LISTED, csgo_weights="csgo_4_32.bin")
    paths = dict(model_files, csgo_weights_path="")
    message = LoadArtNVGModels.check_files(**listed, **paths)
    assert "input 'csgo_weights'" in message and "'csgo_4_32.bin'" in message
    assert "'csgo' model folder" in message and "huggingface.co/InstantX/CSGO" in message

    partial = tmp_path / "partial_sdxl"  # the loader would fail on it: validation says so, naming only that
    partial.mkdir()
    (partial / "model_index.json").write_text("{}")
    message = LoadArtNVGModels.check_files(**LISTED, **dict(model_files, sdxl_checkpoint_path=str(partial)))
    assert message.startswith("Load ArtNVG Models: 1 model file missing, so nothing was run:\n- SDXL diffusers "
                              "folder component 'unet'") and "vae" not in message
    single = tmp_path / "sd_xl_base_1.0.safetensors"
    single.write_bytes(b"")
    message = LoadArtNVGModels.check_files(**LISTED, **dict(model_files, sdxl_checkpoint_path=str(single)),
                                               sdxl_config_dir=str(tmp_path / "configs"))
    assert "SDXL configs for the single-file checkpoint" in message and "configs/model_index.json" in message
    assert LoadArtNVGModels.check_files(**LISTED, **dict(model_files, sdxl_checkpoint_path=str(single))) is None

    missing = tmp_path / "nowhere" / "csgo.bin"
    message = LoadArtNVGModels.check_files(**LISTED, **dict(model_files, csgo_weights_path=str(missing)))
    assert "input 'csgo_weights_path'" in message and str(missing) in message

    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty_cache"))
    message = LoadArtNVGModels.check_files(**LISTED, **dict(model_files, controlnet_path=""))
    assert "input 'controlnet'" in message and "empty_cache" in message and "TTPLanet" in message
    with pytest.raises(NodeInputError, match="Load ArtNVG Models: 1 model file missing.*\n- input 'controlnet'"):
        call(LoadArtNVGModels, **LISTED, dtype="float32", device="cpu", keep_loaded=True,
             **dict(model_files, controlnet_path=""))


def test_every_missing_model_is_named_once_with_its_folder_and_source(tmp_path, monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty_cache"))
    shipped = {"sdxl_checkpoint": "sd_xl_base_1.0.safetensors", "controlnet": "tile.safetensors",
               "image_encoder": HF_CACHE, "csgo_weights": "csgo_4_32.bin"}
    message = LoadArtNVGModels.check_files(**shipped, dtype="float16")  # other inputs are ignored
    lines = message.splitlines()
    assert lines[0] == "Load ArtNVG Models: 4 model files missing, so nothing was run:"
    assert [line.split("'")[1] for line in lines[1:]] == ["sdxl_checkpoint", "controlnet", "image_encoder",
                                                           "csgo_weights"]
    for name in ("'sd_xl_base_1.0.safetensors'", "'tile.safetensors'", "'csgo_4_32.bin'", "empty_cache"):
        assert message.count(name) == 1, name
    for line, url in zip(lines[1:], ("stabilityai/stable-diffusion-xl-base-1.0", "TTPlanet/", "h94/IP-Adapter",
                                     "InstantX/CSGO")):
        assert f"huggingface.co/{url}" in line
    assert "'checkpoints' model folder" in lines[1] and "'csgo' model folder" in lines[4]


def test_patch_turns_neighbouring_view_attention_on_without_touching_the_input(loaded):
    (patched,) = call(NVAttentionPatch, models=loaded, enabled=True)
    assert patched.neighbour_views and not loaded.neighbour_views
    assert patched.models is loaded.models


def test_encode_matches_the_core(loaded):
    style = _images(1, seed=5)
    (embeds,) = call(CSGOEncode, models=loaded, style_image=style, prompt=PROMPT, negative_prompt=NEGATIVE)
    expected = prepare_conditioning(loaded.models, style, PROMPT, NEGATIVE)
    assert torch.equal(embeds.prompt.text, expected.prompt.text)
    assert torch.equal(embeds.prompt.negative_text, expected.prompt.negative_text)
    assert torch.equal(embeds.style.cond, expected.style.cond)
    (blank,) = call(CSGOEncode, models=loaded, style_image=style, prompt=PROMPT, negative_prompt="  ")
    assert not blank.prompt.negative_text.any()  # SDXL: an empty negative prompt gives zero embeddings


SAMPLING = {"seed": 7, "steps": 2, "guidance_scale": 3.0, "content_scale": 1.0, "style_scale": 0.6,
            "control_scale": 1.0, "resolution": 0, "scheduler": "ddim"}


def test_sample_group_all_groups_or_one_matches_the_core(loaded):
    style, content, cameras = _images(1, seed=5), _images(4, seed=6), _line_cameras(4)
    (patched,) = call(NVAttentionPatch, models=loaded, enabled=True)
    (embeds,) = call(CSGOEncode, models=patched, style_image=style, prompt=PROMPT, negative_prompt=NEGATIVE)
    groups = group_views(cameras, 2)
    (every,) = call(SampleGroup, models=patched, embeds=embeds, content_views=content, groups=groups,
                    group_index=-1, **SAMPLING)
    settings = SamplerSettings(steps=2, guidance_scale=3.0, resolution=None, neighbour_views=True)
    expected = stylize_views(loaded.models, content, cameras, style, settings, group_size=2, seed=7,
                             prompt=PROMPT, negative_prompt=NEGATIVE)
    assert every.shape == (4, 64, 64, 3) and torch.equal(every, expected)

    (second,) = call(SampleGroup, models=patched, embeds=embeds, content_views=content, groups=groups,
                     group_index=1, **SAMPLING)
    assert torch.equal(second, every[list(groups[1].views)])

    (without_nv,) = call(SampleGroup, models=loaded, embeds=embeds, content_views=content, groups=groups,
                         group_index=1, **SAMPLING)
    assert not torch.equal(without_nv, second)

    (paper,) = call(SampleGroup, models=patched, embeds=embeds, content_views=content, groups=groups,
                    group_index=-1, content_routing="paper", **SAMPLING)
    expected = stylize_views(loaded.models, content, cameras, style, replace(settings, content_routing="paper"),
                             group_size=2, seed=7, prompt=PROMPT, negative_prompt=NEGATIVE)
    assert torch.equal(paper, expected) and not torch.equal(paper, every)

    (truncated,) = call(SampleGroup, models=patched, embeds=embeds, content_views=content, groups=groups,
                        group_index=-1, cfg_until=0.5, **SAMPLING)
    expected = stylize_views(loaded.models, content, cameras, style, replace(settings, cfg_until=0.5),
                             group_size=2, seed=7, prompt=PROMPT, negative_prompt=NEGATIVE)
    assert torch.equal(truncated, expected) and not torch.equal(truncated, every)


def test_sample_group_errors_name_the_input(loaded, monkeypatch):
    content, groups = _images(3, seed=6), group_views(_line_cameras(4), 2)
    (embeds,) = call(CSGOEncode, models=loaded, style_image=_images(1, seed=5), prompt=PROMPT, negative_prompt="")
    with pytest.raises(NodeInputError, match="Sample Group: input 'content_views': 3 views .* 4 cameras"):
        call(SampleGroup, models=loaded, embeds=embeds, content_views=content, groups=groups, group_index=-1,
             **SAMPLING)
    with pytest.raises(NodeInputError, match="Sample Group: input 'group_index': 2 is out of range for 2 groups"):
        call(SampleGroup, models=loaded, embeds=embeds, content_views=_images(4, seed=6), groups=groups,
             group_index=2, **SAMPLING)
    monkeypatch.setattr(diffusion_nodes, "interrupt_requested", lambda: True)
    with pytest.raises(Cancelled):
        call(SampleGroup, models=loaded, embeds=embeds, content_views=_images(4, seed=6), groups=groups,
             group_index=-1, **SAMPLING)


def test_patch_approximations_and_low_memory_reach_the_sampler(model_files):
    """The patch node's NV approximations and the loader's low-memory mode give the core's result."""
    (low,) = call(LoadArtNVGModels, **LISTED, dtype="float32", device="cpu", keep_loaded=True, memory="low",
                  **model_files)
    assert low.low_memory
    (patched,) = call(NVAttentionPatch, models=low, enabled=True, levels="lowest", nearest_views=1, kv_downsample=2)
    assert (patched.nv_levels, patched.nv_nearest, patched.nv_kv_downsample) == ("lowest", 1, 2)
    style, content, cameras = _images(1, seed=5), _images(4, seed=6), _line_cameras(4)
    (embeds,) = call(CSGOEncode, models=patched, style_image=style, prompt=PROMPT, negative_prompt=NEGATIVE)
    groups = group_views(cameras, 4)
    (out,) = call(SampleGroup, models=patched, embeds=embeds, content_views=content, groups=groups,
                  group_index=-1, **SAMPLING)
    settings = SamplerSettings(steps=2, guidance_scale=3.0, resolution=None, nv_levels="lowest", nv_nearest=1,
                               nv_kv_downsample=2, sequential_cfg=True)
    expected = stylize_views(low.models, content, cameras, style, settings, group_size=4, seed=7,
                             prompt=PROMPT, negative_prompt=NEGATIVE)
    assert torch.equal(out, expected)
    assert all(block._chunk_size == 1 for block in low.models.base.unet.modules() if hasattr(block, "_chunk_size"))


def test_compile_input_applies_the_compiled_blocks_in_full_memory_only(model_files, monkeypatch):
    """The loader's ``compile`` applies ``COMPILED_BLOCKS`` (here its exact hint cache alone: Inductor
    takes minutes on a CPU) and gives the uncompiled result; with low memory it is refused by name. A
    compiled set loads an earlier run's compile artifacts; Sample Group saves them after sampling."""
    applied = []
    monkeypatch.setattr(speed, "COMPILED_BLOCKS", SpeedOptions(cache_hint_embedding=True))
    monkeypatch.setattr(speed, "apply_speedups",
                        lambda models, options: applied.append(options) or apply_speedups(models, options))
    monkeypatch.setattr(compile_cache, "load_compile_cache", lambda device: applied.append(("load", device)))
    monkeypatch.setattr(diffusion_nodes, "save_compile_cache", lambda device: applied.append(("save", device)))
    with pytest.raises(NodeInputError, match="Load ArtNVG Models: compile: .* full-memory mode only"):
        call(LoadArtNVGModels, **LISTED, dtype="float32", device="cpu", keep_loaded=True, memory="low",
             compile=True, **model_files)
    outputs = []
    for compile in (False, True):
        (loaded,) = call(LoadArtNVGModels, **LISTED, dtype="float32", device="cpu", keep_loaded=True,
                         compile=compile, **model_files)
        (embeds,) = call(CSGOEncode, models=loaded, style_image=_images(1, seed=5), prompt=PROMPT,
                         negative_prompt=NEGATIVE)
        outputs.append(call(SampleGroup, models=loaded, embeds=embeds, content_views=_images(4, seed=6),
                            groups=group_views(_line_cameras(4), 4), group_index=-1, **SAMPLING)[0])
    cpu = torch.device("cpu")
    assert applied == [SpeedOptions(cache_hint_embedding=True), ("load", cpu), ("save", cpu)]
    assert torch.equal(outputs[1], outputs[0])
