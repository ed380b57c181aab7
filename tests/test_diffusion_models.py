"""Model loading from explicit paths and the Hugging Face cache, with tiny models written to disk."""

import pytest
import torch
from diffusers import ControlNetModel
from safetensors.torch import save_file

import artnvg_core.diffusion.models as models_module
from artnvg_core.diffusion.model_files import (
    CSGO_WEIGHTS,
    IMAGE_ENCODER,
    MissingModelError,
    ModelFiles,
    check_model_files,
    hf_cache_path,
    locate,
)
from artnvg_core.diffusion.models import (
    load_controlnet,
    load_diffusion_models,
    load_image_encoder,
    load_sdxl,
    load_vae,
)
from artnvg_core.progress import Cancelled
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import (
    csgo_state,
    diffusers_pipeline,
    tiny_base,
    tiny_controlnet,
    tiny_image_encoder,
    tiny_scheduler,
    write_csgo_file,
    write_model_files,
    write_single_file_checkpoint,
)


def _same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k].float(), sb[k].float()) for k in sa)


@pytest.fixture(scope="module")
def sdxl_folder(tmp_path_factory):
    base = tiny_base()
    folder = tmp_path_factory.mktemp("sdxl")
    diffusers_pipeline(base, tiny_scheduler()).save_pretrained(folder)
    return folder, base


def test_sdxl_folder_loads(sdxl_folder):
    folder, base = sdxl_folder
    loaded = load_sdxl(folder, dtype=torch.float32)
    for name in ("unet", "vae", "text_encoder", "text_encoder_2"):
        assert _same_weights(getattr(loaded, name), getattr(base, name)), name
    assert loaded.tokenizer("a cat").input_ids == base.tokenizer("a cat").input_ids
    assert loaded.tokenizer_2.pad_token == "!"
    assert loaded.scheduler_config["timestep_spacing"] == "leading"
    assert loaded.force_zeros_for_empty_prompt


def test_fp16_request_keeps_an_overflowing_vae_in_float32(sdxl_folder):
    folder, _ = sdxl_folder
    loaded = load_sdxl(folder, dtype=torch.float16)
    assert loaded.unet.dtype == torch.float16 and loaded.vae.dtype == torch.float32  # force_upcast
    assert load_sdxl(folder, dtype=torch.bfloat16).vae.dtype == torch.bfloat16


@pytest.mark.parametrize("capability, expected", [((8, 0), torch.bfloat16), ((9, 0), torch.bfloat16),
                                                  ((7, 5), torch.float32)])
def test_fp16_request_runs_an_overflowing_vae_in_bfloat16_where_the_gpu_computes_it(monkeypatch, capability,
                                                                                    expected):
    """As ComfyUI decodes SDXL: bfloat16 on CUDA GPUs of compute capability 8.0 and more, float32 on older ones
    and on the CPU; a VAE that does not overflow (fp16-fix) and other requests keep the dtype asked for."""
    from artnvg_core.diffusion.models import _vae_dtype

    asked = []
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device: asked.append(device) or capability)
    assert _vae_dtype(True, torch.float16, "cuda:1") == expected
    assert asked == [torch.device("cuda:1")]
    assert _vae_dtype(True, torch.float16, "cpu") == torch.float32
    assert _vae_dtype(False, torch.float16, "cuda") == torch.float16
    assert _vae_dtype(True, torch.float32, "cuda") == torch.float32
    assert _vae_dtype(True, torch.bfloat16, "cuda") == torch.bfloat16


@pytest.mark.parametrize("missing, option", [(0, "--sdxl"), (1, "--controlnet"), (2, "--image-encoder"), (3, "--csgo")])
def test_a_missing_model_file_names_the_option_that_takes_its_path(tmp_path, missing, option):
    """It said '... and pass its path.', leaving the user to find which of the four options."""
    (tmp_path / "there").mkdir()
    paths = [tmp_path / "there"] * missing + [tmp_path / "gone"] * (4 - missing)
    with pytest.raises(MissingModelError, match=rf"looked for '.*gone'\. Get it from .* and pass its path with {option}\.$"):
        check_model_files(ModelFiles(*paths))


def test_sdxl_errors_name_the_missing_piece(tmp_path, sdxl_folder):
    with pytest.raises(MissingModelError, match="looked for '.*missing_sdxl'.*`hf download "
                       "stabilityai/stable-diffusion-xl-base-1.0 sd_xl_base_1.0.safetensors`"):  # one file suffices
        load_sdxl(tmp_path / "missing_sdxl")
    (tmp_path / "partial").mkdir()
    (tmp_path / "partial" / "model_index.json").write_text("{}")
    with pytest.raises(MissingModelError, match="component 'unet'.*partial/unet' does not exist"):
        load_sdxl(tmp_path / "partial")
    checkpoint = tmp_path / "sd_xl_base_1.0.safetensors"
    checkpoint.write_bytes(b"")
    with pytest.raises(MissingModelError, match=r"SDXL configs for the single-file checkpoint .*configs/model_index"):
        load_sdxl(checkpoint, config_dir=tmp_path / "configs")


TINY_TEXT = dict(vocab_size=49408, hidden_size=4, intermediate_size=16, num_hidden_layers=2, num_attention_heads=2,
                 max_position_embeddings=77, projection_dim=8, bos_token_id=49406, eos_token_id=49407,
                 pad_token_id=49407)
TINY_TEXT_2 = dict(TINY_TEXT, hidden_size=12, pad_token_id=0)  # widths 4 + 12: the tiny UNet's context of 16


def _tiny_single_file(tmp_path, monkeypatch, dtype: torch.dtype = torch.float32):
    """A tiny SDXL (in ``dtype``) written in sd_xl_base_1.0.safetensors' key layout, and the shipped config
    folder's layout with its architectures put where the loader looks for the built-in one."""
    from contextlib import contextmanager

    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection

    from artnvg_core.diffusion import models
    from artnvg_core.diffusion.sdxl_config import write_sdxl_config_dir

    original = tiny_base()
    torch.manual_seed(3)
    original.text_encoder = CLIPTextModel(CLIPTextConfig(**TINY_TEXT)).eval()
    original.text_encoder_2 = CLIPTextModelWithProjection(CLIPTextConfig(**TINY_TEXT_2)).eval()
    for name in ("unet", "vae", "text_encoder", "text_encoder_2"):
        getattr(original, name).to(dtype)
    checkpoint = write_single_file_checkpoint(tmp_path / "sd_xl_base_1.0.safetensors", original)

    @contextmanager
    def tiny_built_in_config():  # the shipped folder's layout and tokenizers, with tiny architectures
        yield write_sdxl_config_dir(tmp_path / "configs", unet=dict(original.unet.config),
                                    vae=dict(original.vae.config), text_encoder=TINY_TEXT, text_encoder_2=TINY_TEXT_2)

    monkeypatch.setattr(models, "built_in_sdxl_config", tiny_built_in_config)
    return original, checkpoint, tiny_built_in_config


def test_single_file_checkpoint_loads_offline_with_the_shipped_configs(tmp_path, monkeypatch):
    """A checkpoint in sd_xl_base_1.0.safetensors' key layout loads with no network, an empty Hugging Face cache
    and no config folder: every weight arrives unchanged and the shipped CLIP tokenizers are used."""
    import socket

    from huggingface_hub import constants

    original, checkpoint, _ = _tiny_single_file(tmp_path, monkeypatch)

    def no_network(*args, **kwargs):
        raise AssertionError("network access")

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty_cache"))
    monkeypatch.setattr(socket.socket, "connect", no_network)
    loaded = load_sdxl(checkpoint, dtype=torch.float32)
    for name in ("unet", "vae", "text_encoder", "text_encoder_2"):
        assert _same_weights(getattr(loaded, name), getattr(original, name)), name
    assert loaded.tokenizer("a photo of a cat").input_ids == [49406, 320, 1125, 539, 320, 2368, 49407]
    assert (loaded.tokenizer.pad_token, loaded.tokenizer_2.pad_token) == ("<|endoftext|>", "!")
    assert loaded.scheduler_config["_class_name"] == "EulerDiscreteScheduler" and loaded.force_zeros_for_empty_prompt


def test_a_ckpt_single_file_wrapped_as_lightning_saves_it_loads(tmp_path, monkeypatch):
    """A .ckpt as the original Stability/CompVis files and many fine-tunes are saved, {"state_dict": ...} with a
    training step beside it, loads as the .safetensors of the same weights does (as ComfyUI's loader reads it)."""
    from safetensors.torch import load_file

    original, checkpoint, _ = _tiny_single_file(tmp_path, monkeypatch)
    wrapped = tmp_path / "sd_xl_base_1.0.ckpt"
    torch.save({"state_dict": load_file(str(checkpoint)), "global_step": 0}, wrapped)
    loaded = load_sdxl(wrapped, dtype=torch.float32)
    for name in ("unet", "vae", "text_encoder", "text_encoder_2"):
        assert _same_weights(getattr(loaded, name), getattr(original, name)), name


def test_single_file_loads_bit_for_bit_as_diffusers_pipeline_loads_it(tmp_path, monkeypatch):
    """An fp16 checkpoint read straight to the device and converted there gives, in float16, the very
    tensors, dtypes and configs that diffusers' ``StableDiffusionXLPipeline.from_single_file`` gives
    (the VAE kept in float32 for its force_upcast, as before), and a scheduler config from which every
    scheduler the sampler offers is built alike."""
    from diffusers import StableDiffusionXLPipeline

    _, checkpoint, configs = _tiny_single_file(tmp_path, monkeypatch, torch.float16)
    loaded = load_sdxl(checkpoint, dtype=torch.float16)
    with configs() as folder:
        pipe = StableDiffusionXLPipeline.from_single_file(str(checkpoint), config=str(folder),
                                                          torch_dtype=torch.float16, local_files_only=True,
                                                          add_watermarker=False)
    pipe.vae.to(torch.float32)
    for name in ("unet", "vae", "text_encoder", "text_encoder_2"):
        ours, theirs = getattr(loaded, name).state_dict(), getattr(pipe, name).state_dict()
        assert ours.keys() == theirs.keys(), name
        for key, tensor in theirs.items():
            assert ours[key].dtype == tensor.dtype and torch.equal(ours[key], tensor), (name, key)
        assert dict(getattr(loaded, name).config) == dict(getattr(pipe, name).config) if name in ("unet", "vae") \
            else getattr(loaded, name).config.to_dict() == getattr(pipe, name).config.to_dict()
    from artnvg_core.diffusion.sampler import SCHEDULERS

    def built(scheduler_class, config):  # what the sampler builds from a scheduler config
        return {k: v for k, v in scheduler_class.from_config(config).config.items() if k != "_use_default_values"}

    for scheduler_class in SCHEDULERS.values():
        assert built(scheduler_class, loaded.scheduler_config) == built(scheduler_class, pipe.scheduler.config)


def _tensors_of(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """Every parameter and buffer (computed ones too) of ``model``, by name."""
    return {**dict(model.named_parameters()), **dict(model.named_buffers())}


def test_a_stylize_runs_models_are_their_files_bit_for_bit(tmp_path, monkeypatch):
    """What a stylize run loads (load_diffusion_models on SDXL's single file, the ControlNet's, the image encoder's
    folder and CSGO's .bin, in float16) is what the libraries' own loaders give from the same files, CSGO
    attached alike: every parameter and buffer of every model, of the same kind (a parameter wanting gradients,
    or a buffer), dtype and device, bit for bit. The loaders' speed-ups (fewer Python calls per tensor) must
    change no loaded value."""
    from diffusers import StableDiffusionXLPipeline
    from transformers import CLIPVisionModelWithProjection

    from artnvg_core.diffusion.csgo_weights import load_csgo

    original, checkpoint, configs = _tiny_single_file(tmp_path, monkeypatch, torch.float16)
    tiny_controlnet(original.unet).save_pretrained(tmp_path / "controlnet")
    tiny_image_encoder().save_pretrained(tmp_path / "image_encoder")
    write_csgo_file(tmp_path / "csgo.bin", csgo_state(original.unet, tiny_controlnet(original.unet)))
    tile = tmp_path / "controlnet" / "diffusion_pytorch_model.safetensors"
    loaded = load_diffusion_models(ModelFiles(checkpoint, tile, tmp_path / "image_encoder", tmp_path / "csgo.bin"),
                                   dtype=torch.float16)
    with configs() as folder:
        pipe = StableDiffusionXLPipeline.from_single_file(str(checkpoint), config=str(folder), torch_dtype=torch.float16,
                                                          local_files_only=True, add_watermarker=False)
    pipe.vae.to(torch.float32)  # an fp16 request keeps SDXL's VAE in float32 on the CPU
    controlnet = ControlNetModel.from_pretrained(tmp_path / "controlnet", torch_dtype=torch.float16)
    csgo = load_csgo(tmp_path / "csgo.bin", pipe.unet, controlnet)
    pairs = {"unet": (loaded.base.unet, pipe.unet), "vae": (loaded.base.vae, pipe.vae),
             "text_encoder": (loaded.base.text_encoder, pipe.text_encoder),
             "text_encoder_2": (loaded.base.text_encoder_2, pipe.text_encoder_2),
             "controlnet": (loaded.controlnet, controlnet), "csgo": (loaded.csgo, csgo),
             "image_encoder": (loaded.image_encoder, CLIPVisionModelWithProjection.from_pretrained(
                 tmp_path / "image_encoder", dtype=torch.float16))}
    for name, (ours, theirs) in pairs.items():
        ours, theirs = _tensors_of(ours), _tensors_of(theirs)
        assert ours.keys() == theirs.keys(), name
        for key, tensor in theirs.items():
            mine = ours[key]
            assert (type(mine), mine.dtype, mine.device, mine.requires_grad) == (
                type(tensor), tensor.dtype, tensor.device, tensor.requires_grad), (name, key)
            assert torch.equal(mine, tensor), (name, key)


def test_shipped_configs_are_sdxl_base_1_0():
    """The built-in folder builds SDXL's four models with their published parameter counts, and its tokenizer
    is CLIP's (49,408 tokens, the vocabulary derived from the shipped merges)."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer

    from artnvg_core.diffusion.sdxl_config import built_in_sdxl_config

    with built_in_sdxl_config() as folder, torch.device("meta"):
        counts = [sum(p.numel() for p in model.parameters()) for model in (
            UNet2DConditionModel.from_config(UNet2DConditionModel.load_config(folder, subfolder="unet")),
            AutoencoderKL.from_config(AutoencoderKL.load_config(folder, subfolder="vae")),
            CLIPTextModel(CLIPTextConfig.from_pretrained(folder, subfolder="text_encoder")),
            CLIPTextModelWithProjection(CLIPTextConfig.from_pretrained(folder, subfolder="text_encoder_2")),
        )]
        tokenizer = CLIPTokenizer.from_pretrained(folder, subfolder="tokenizer_2", local_files_only=True)
    assert counts == [2_567_463_684, 83_653_863, 123_060_480, 694_659_840]
    assert len(tokenizer) == 49408 and tokenizer.convert_tokens_to_ids(["a</w>", "cat</w>"]) == [320, 2368]


def test_locate_explicit_path_then_hf_cache(tmp_path):
    with pytest.raises(MissingModelError) as error:
        locate(CSGO_WEIGHTS, tmp_path / "csgo_4_32.bin")
    message = str(error.value)
    assert "CSGO content/style weights" in message and str(tmp_path / "csgo_4_32.bin") in message
    assert "https://huggingface.co/InstantX/CSGO/blob/main/csgo_4_32.bin" in message
    assert "hf download InstantX/CSGO csgo_4_32.bin" in message
    repo = tmp_path / "cache" / "models--h94--IP-Adapter"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123\n")
    target = repo / "snapshots" / "abc123" / "sdxl_models" / "image_encoder"
    assert hf_cache_path(IMAGE_ENCODER, tmp_path / "cache") == target
    with pytest.raises(MissingModelError, match="--include 'sdxl_models/image_encoder/\\*'"):
        locate(IMAGE_ENCODER, hf_cache_dir=tmp_path / "cache")
    target.mkdir(parents=True)
    assert locate(IMAGE_ENCODER, hf_cache_dir=tmp_path / "cache") == target


def test_a_download_command_saves_a_top_level_file_as_the_path_asked_for():
    """``hf download REPO FILE --local-dir DIR`` saves the repository's FILE as DIR/FILE (a file in a folder of the
    repository as DIR/FOLDER/FILE): a command is given only where that is the path asked for."""
    from artnvg_core.diffusion.model_files import IMAGE_ENCODER_FILE, SDXL_BASE

    assert CSGO_WEIGHTS.download_as("models/csgo/csgo_4_32.bin") == \
        "hf download InstantX/CSGO csgo_4_32.bin --local-dir models/csgo"
    assert SDXL_BASE.download_as("/my models/checkpoints/sd_xl_base_1.0.safetensors") == (
        "hf download stabilityai/stable-diffusion-xl-base-1.0 sd_xl_base_1.0.safetensors --local-dir "
        "'/my models/checkpoints'")  # quoted for the shell
    assert CSGO_WEIGHTS.download_as("models/csgo/mine.bin") is None  # another name: a rename
    assert IMAGE_ENCODER_FILE.download_as("models/clip_vision/model.safetensors") is None  # in a folder
    assert IMAGE_ENCODER.download_as("models/clip_vision/image_encoder") is None  # a folder


def test_controlnet_folder_and_single_files(tmp_path):
    base = tiny_base()
    controlnet = tiny_controlnet(base.unet)
    controlnet.save_pretrained(tmp_path / "cn_folder")
    assert _same_weights(load_controlnet(tmp_path / "cn_folder", dtype=torch.float32), controlnet)
    # a single file with a config.json beside it
    (tmp_path / "with_config").mkdir()
    controlnet.save_config(tmp_path / "with_config")
    save_file(controlnet.state_dict(), tmp_path / "with_config" / "tile.safetensors")
    assert _same_weights(
        load_controlnet(tmp_path / "with_config" / "tile.safetensors", dtype=torch.float32), controlnet
    )
    # a single file whose config comes from the UNet (the SDXL ControlNet architecture)
    derived = ControlNetModel.from_unet(base.unet)
    save_file(derived.state_dict(), tmp_path / "tile.safetensors")
    loaded = load_controlnet(tmp_path / "tile.safetensors", unet_config=dict(base.unet.config), dtype=torch.float32)
    assert _same_weights(loaded, derived)
    with pytest.raises(MissingModelError, match="no config.json beside the file and no UNet config"):
        load_controlnet(tmp_path / "tile.safetensors")
    state = derived.state_dict()
    state["conv_in.weights"] = state.pop("conv_in.weight")
    save_file(state, tmp_path / "renamed.safetensors")
    with pytest.raises(
        ValueError,
        match=r"renamed.safetensors' do not fit ControlNetModel: 1 missing key "
        r"\[conv_in.weight\], 1 unexpected key \[conv_in.weights\]",
    ):
        load_controlnet(tmp_path / "renamed.safetensors", unet_config=dict(base.unet.config))


def test_image_encoder_folder_and_single_file(tmp_path):
    encoder = tiny_image_encoder()
    encoder.save_pretrained(tmp_path / "image_encoder")
    assert _same_weights(load_image_encoder(tmp_path / "image_encoder", dtype=torch.float32), encoder)
    (tmp_path / "clip_vision").mkdir()
    encoder.config.to_json_file(tmp_path / "clip_vision" / "config.json")
    state = dict(encoder.state_dict())
    state["vision_model.embeddings.position_ids"] = torch.arange(257)[None]  # as older files carry it
    save_file(state, tmp_path / "clip_vision" / "model.safetensors")
    loaded = load_image_encoder(tmp_path / "clip_vision" / "model.safetensors", dtype=torch.bfloat16)
    assert loaded.dtype == torch.bfloat16 and _same_weights(loaded, encoder.to(torch.bfloat16))


def test_single_files_load_without_building_random_weights(tmp_path, monkeypatch):
    """The single-file loaders build the model's layers with parameters on the meta device and without
    their random initialisation (a full-size ControlNet or ViT-bigG is seconds of CPU time and a float32
    copy; beside another thread's Python, each call of it waited for the interpreter lock) and take the
    file's tensors; the encoder's computed position ids stay real, so it encodes an image as the original
    does."""
    initialised = []
    for layer in (torch.nn.Linear, torch.nn.modules.conv._ConvNd):
        reset = layer.reset_parameters

        def spy(self, reset=reset):
            initialised.append(self.weight.is_meta)
            reset(self)

        monkeypatch.setattr(layer, "reset_parameters", spy)
    base = tiny_base()
    derived = ControlNetModel.from_unet(base.unet)
    encoder = tiny_image_encoder().eval()
    save_file(derived.state_dict(), tmp_path / "tile.safetensors")
    (tmp_path / "clip_vision").mkdir()
    encoder.config.to_json_file(tmp_path / "clip_vision" / "config.json")
    save_file(encoder.state_dict(), tmp_path / "clip_vision" / "model.safetensors")
    initialised.clear()
    controlnet = load_controlnet(tmp_path / "tile.safetensors", unet_config=dict(base.unet.config), dtype=torch.float32)
    loaded = load_image_encoder(tmp_path / "clip_vision" / "model.safetensors", dtype=torch.float32)
    assert initialised == []
    assert _same_weights(controlnet, derived) and _same_weights(loaded, encoder)
    image = torch.rand(1, 3, encoder.config.image_size, encoder.config.image_size)
    with torch.no_grad():
        assert torch.equal(loaded(image).image_embeds, encoder(image).image_embeds)


def test_loading_in_another_dtype_logs_no_third_party_warning(tmp_path):
    """A cast at load is silent (diffusers' own ``to`` warns on every dtype cast, with nothing to
    keep in float32), and gives the asked dtype."""
    import logging

    base = tiny_base()
    derived = ControlNetModel.from_unet(base.unet)
    save_file(derived.state_dict(), tmp_path / "tile.safetensors")
    records = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append
    logging.getLogger("diffusers").addHandler(handler)
    try:
        controlnet = load_controlnet(tmp_path / "tile.safetensors", unet_config=dict(base.unet.config),
                                     dtype=torch.bfloat16)
    finally:
        logging.getLogger("diffusers").removeHandler(handler)
    assert controlnet.dtype == torch.bfloat16 and _same_weights(controlnet, derived.to(torch.bfloat16))
    assert not records, [r.getMessage() for r in records]


def test_vae_single_file_needs_its_config(tmp_path):
    vae = tiny_base().vae
    (tmp_path / "vae").mkdir()
    save_file(vae.state_dict(), tmp_path / "vae" / "sdxl_vae.safetensors")
    with pytest.raises(MissingModelError, match="no config.json beside the file"):
        load_vae(tmp_path / "vae" / "sdxl_vae.safetensors")
    vae.save_config(tmp_path / "vae")
    loaded = load_vae(tmp_path / "vae" / "sdxl_vae.safetensors", dtype=torch.float16)
    assert loaded.dtype == torch.float32 and _same_weights(loaded, vae)


@pytest.mark.parametrize("text, problem", [("{not json", "not valid JSON"), ("[1, 2]", "expected a JSON object, got a list")])
def test_a_broken_config_beside_a_single_file_is_refused_naming_it(tmp_path, text, problem):
    """Found probing the model files: json's own error ('Expecting property name ...') named no file, and a
    config that is no JSON object went to diffusers as a Hub repository's name (a download attempt)."""
    (tmp_path / "model.safetensors").write_bytes(b"")
    (tmp_path / "config.json").write_text(text)
    for load in (load_vae, load_controlnet, load_image_encoder):
        with pytest.raises(ValueError, match=rf"config\.json: the model's config: {problem}"):
            load(tmp_path / "model.safetensors")


def test_a_broken_config_of_an_sdxl_folder_is_refused_naming_it_before_any_model_loads(tmp_path):
    """Found probing the model files: a model_index.json that is no JSON object was read after the four models
    had loaded (an empty component folder failed first, in transformers), and json's errors named no file."""
    from artnvg_core.diffusion.model_files import SDXL_COMPONENTS

    for name in SDXL_COMPONENTS:
        (tmp_path / name).mkdir()
    (tmp_path / "vae" / "config.json").write_text("{}")
    (tmp_path / "scheduler" / "scheduler_config.json").write_text("{}")
    (tmp_path / "model_index.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"model_index\.json: the model's config: expected a JSON object, got a list"):
        load_sdxl(tmp_path)


def test_load_everything_and_attach_csgo(tmp_path, sdxl_folder):
    folder, base = sdxl_folder
    controlnet = tiny_controlnet(base.unet)
    controlnet.save_pretrained(tmp_path / "controlnet")
    tiny_image_encoder().save_pretrained(tmp_path / "image_encoder")
    state = csgo_state(base.unet, controlnet, num_style_tokens=16)
    write_csgo_file(tmp_path / "csgo.bin", state)
    models = load_diffusion_models(
        ModelFiles(folder, tmp_path / "controlnet", tmp_path / "image_encoder", tmp_path / "csgo.bin"),
        dtype=torch.float32,
        hf_cache_dir=tmp_path / "no_cache",
    )
    assert models.csgo.num_content_tokens == 4 and models.csgo.num_style_tokens == 16
    processors = list(models.base.unet.attn_processors.values())
    assert torch.equal(processors[1].to_k_ip.weight, state["ip_adapter"]["1.to_k_ip.weight"])
    with pytest.raises(MissingModelError, match="CSGO content/style weights .* not found"):
        load_diffusion_models(
            ModelFiles(folder, tmp_path / "controlnet", tmp_path / "image_encoder", None),
            dtype=torch.float32,
            hf_cache_dir=tmp_path / "no_cache",
        )


def test_loading_reports_the_bytes_of_each_model_and_stops_between_models(tmp_path, monkeypatch):
    """progress follows the files' bytes (each folder's files summed), announcing each model as it starts
    and ending at the total; a stop asked while one model loads is honoured before the next, which is not
    loaded."""
    paths = ModelFiles(**write_model_files(tmp_path))

    def size(path):
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size

    sizes = [size(paths.sdxl), size(paths.controlnet), size(paths.image_encoder), size(paths.csgo)]
    seen = []
    load_diffusion_models(paths, dtype=torch.float32, progress=lambda done, total, info: seen.append(
        (done, total, info.get("loading"))))
    before = [sum(sizes[:k]) for k in range(5)]
    names = ("SDXL", "ControlNet", "image encoder", "CSGO", None)
    assert seen == [(done, sum(sizes), name) for done, name in zip(before, names)]
    seen.clear()

    def never(*args, **kwargs):
        raise AssertionError("a model was loaded after the stop")

    monkeypatch.setattr(models_module, "load_image_encoder", never)
    with pytest.raises(Cancelled):
        load_diffusion_models(paths, dtype=torch.float32, should_stop=lambda: len(seen) == 2,
                              progress=lambda done, total, info: seen.append(info["loading"]))
    assert seen == ["SDXL", "ControlNet"]


def test_weight_files_are_the_files_a_load_reads(tmp_path):
    """Single files as given; in folders each weight file, the fp16 variant and not its plain twin."""
    from artnvg_core.diffusion.model_files import weight_files

    for name in ("sdxl/unet/diffusion_pytorch_model.safetensors", "sdxl/unet/diffusion_pytorch_model.fp16.safetensors",
                 "sdxl/vae/diffusion_pytorch_model.safetensors", "sdxl/text_encoder/model.bin", "sdxl/unet/config.json",
                 "encoder/model.safetensors", "tile.safetensors", "csgo.bin"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    found = ModelFiles(tmp_path / "sdxl", tmp_path / "tile.safetensors", tmp_path / "encoder", tmp_path / "csgo.bin")
    assert weight_files(found) == [tmp_path / name for name in (
        "sdxl/text_encoder/model.bin", "sdxl/unet/diffusion_pytorch_model.fp16.safetensors",
        "sdxl/vae/diffusion_pytorch_model.safetensors", "tile.safetensors", "encoder/model.safetensors", "csgo.bin")]
