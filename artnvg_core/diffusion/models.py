"""Loading the diffusion models from explicit paths (or the Hugging Face cache), never downloading.

* SDXL 1.0 base: a diffusers folder (``model_index.json`` + component subfolders), or a
  single-file checkpoint (``.safetensors``/``.ckpt``, e.g. ``sd_xl_base_1.0.safetensors``; a ``.ckpt`` may hold
  its tensors under ``state_dict``, as Lightning saves them: :func:`~artnvg_core.tensor_files.read_tensors`).
  Its configs and tokenizers come with the package (:mod:`.sdxl_config`), so it loads with no
  network; ``config_dir`` may name another diffusers-format SDXL folder (its weights are not read).
* VAE override (e.g. madebyollin/sdxl-vae-fp16-fix): a diffusers folder or one ``.safetensors``
  with diffusers keys. fp16-safe decoding: a VAE whose config says ``force_upcast`` runs in bfloat16
  when float16 is requested on a GPU that computes bfloat16 natively (as ComfyUI runs it), else in float32.
* Tile ControlNet: a diffusers folder, or one ``.safetensors`` with diffusers keys (config from a
  ``config.json`` beside it, else the SDXL ControlNet architecture of the loaded UNet).
* Image encoder: a transformers ``CLIPVisionModelWithProjection`` folder, or one ``.safetensors``
  (config from a ``config.json`` beside it, else ViT-bigG/14).
* CSGO weights: see :mod:`artnvg_core.diffusion.csgo_weights` (installs ArtNVG's processors).

Weights are read straight onto the device they run on (:mod:`artnvg_core.tensor_files`), into models
built on the meta device, and cast there; no diffusers pipeline is built (LoRAs excepted,
:func:`~artnvg_core.diffusion.lora.fuse_loras`). Single weight files, and a model folder's one weight
file, are loaded strictly: missing or unexpected keys raise ValueError. A folder's sharded or ``.bin``
weights, and the text encoders of an SDXL folder (transformers renames their keys), go through the
library's own ``from_pretrained``, then to the device.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
from transformers import (
    CLIPTextConfig,
    CLIPTextModel,
    CLIPTextModelWithProjection,
    CLIPTokenizer,
    CLIPVisionConfig,
    CLIPVisionModelWithProjection,
)

from ..json_objects import parse_json
from ..progress import ProgressFn, StopFn, check_stop
from ..statedict import assign_strict, parameters_on_meta
from ..tensor_files import read_tensors
from .architectures import VIT_BIGG_IMAGE_ENCODER_CONFIG, controlnet_config_from_unet, transformers_config_kwargs
from .csgo import CSGOProjections
from .csgo_weights import load_csgo
from .lora import LoRA, check_lora, fuse_loras
from .model_cache import file_key
from .model_files import (
    IMAGE_ENCODER,
    SDXL_BASE,
    SDXL_VAE_FP16_FIX,
    TILE_CONTROLNET,
    MissingModelError,
    ModelFiles,
    check_model_files,
    check_sdxl,
    locate,
    require_path,
)
from .quiet_notices import library_progress_bars_hidden, sdxl_loading_notices_silenced
from .sdxl_config import built_in_sdxl_config

@dataclass
class SDXLBase:
    """The SDXL components the sampler uses; ``scheduler_config`` configures any diffusers scheduler."""

    unet: UNet2DConditionModel
    vae: AutoencoderKL
    text_encoder: CLIPTextModel
    text_encoder_2: CLIPTextModelWithProjection
    tokenizer: CLIPTokenizer
    tokenizer_2: CLIPTokenizer
    scheduler_config: dict
    force_zeros_for_empty_prompt: bool = True


@dataclass
class DiffusionModels:
    """Everything the ArtNVG group sampler runs (``csgo`` None = no content/style tokens)."""

    base: SDXLBase
    controlnet: ControlNetModel
    image_encoder: CLIPVisionModelWithProjection | None = None
    csgo: CSGOProjections | None = None

    def __post_init__(self) -> None:
        if self.csgo is not None and self.image_encoder is None:
            raise ValueError("DiffusionModels: CSGO projections need an image_encoder to compute their tokens")


def _vae_dtype(force_upcast: bool, dtype: torch.dtype, device: str | torch.device) -> torch.dtype:
    """The dtype of a VAE asked for in ``dtype`` on ``device``: ``dtype``, except for a float16 request on a VAE
    that overflows in float16 (``force_upcast``, SDXL's own): bfloat16 (float32's range) on a CUDA GPU of compute
    capability 8.0 or more, as ComfyUI decodes SDXL there (20 % faster than float32, BENCHMARKS.md "Whole runs"),
    else float32."""
    if dtype != torch.float16 or not force_upcast:
        return dtype
    device = torch.device(device)
    native_bf16 = device.type == "cuda" and torch.cuda.get_device_capability(device) >= (8, 0)
    return torch.bfloat16 if native_bf16 else torch.float32


def load_state_dict_strict(model: torch.nn.Module, path: Path, device: str | torch.device = "cpu",
                           dtype: torch.dtype | None = None) -> None:
    """Load the weight file at ``path`` into ``model`` (built in :func:`parameters_on_meta` or not), its
    tensors read straight onto ``device`` (:func:`~artnvg_core.tensor_files.read_tensors`; floating ones in
    ``dtype`` when given, else the file's); every key must match in name and shape
    (:func:`~artnvg_core.statedict.assign_strict`)."""
    assign_strict(model, read_tensors(path, device, dtype), f"weights '{path}'")


def _placed(model: torch.nn.Module, device: str | torch.device, dtype: torch.dtype) -> torch.nn.Module:
    """``model`` on ``device`` in ``dtype``, each tensor moved and cast at once, through
    ``torch.nn.Module.to``: diffusers' own ``to`` warns on every dtype cast ("modules ... that should
    be kept in float32: []"), even when a model keeps nothing in float32, as none of these does."""
    return torch.nn.Module.to(model, device=device, dtype=dtype).eval()


def _json_config(config: Path) -> dict:
    """The JSON object in the config file ``config`` (diffusers would take a list or a string for a Hub
    repository's name)."""
    return parse_json(config.read_bytes(), f"{config}: the model's config")


def _config_beside(path: Path) -> dict | None:
    """:func:`_json_config` of the ``config.json`` beside the weight file ``path``, None when there is none."""
    config = path.parent / "config.json"
    return _json_config(config) if config.is_file() else None


def _weights_variant(folder: Path) -> str | None:
    """'fp16' when a folder holds only fp16-variant weights (``*.fp16.safetensors``), else None."""
    files = [p.name for p in folder.glob("*.safetensors")] + [p.name for p in folder.glob("*.bin")]
    plain = [f for f in files if ".fp16." not in f]
    return "fp16" if files and not plain else None


def _weights_file(folder: Path, dtype: torch.dtype) -> Path | None:
    """The one ``.safetensors`` file of a model folder that a load in ``dtype`` reads: its fp16 variant for
    float16 when there is one, else the plain file (the variant when it is all there is); None for sharded
    or ``.bin`` weights (their library's own loader reads those)."""
    files = sorted(folder.glob("*.safetensors"))
    fp16 = [f for f in files if f.name.endswith(".fp16.safetensors")]
    plain = [f for f in files if f not in fp16]
    chosen = fp16 if (dtype == torch.float16 and fp16) or not plain else plain
    return chosen[0] if len(chosen) == 1 else None


def _from_folder(cls, folder: Path, device: str | torch.device, dtype: torch.dtype) -> torch.nn.Module:
    """A diffusers or transformers model (``cls``) from its folder: built on the meta device from its
    ``config.json`` and its one weight file read straight onto ``device`` in ``dtype``
    (:func:`load_state_dict_strict`: the file's keys must be the model's); other layouts through the
    library's own ``from_pretrained``, then placed."""
    weights = _weights_file(folder, dtype)
    if weights is None:
        model = cls.from_pretrained(folder, local_files_only=True, variant=_weights_variant(folder))
        return _placed(model, device, dtype)
    with parameters_on_meta():
        model = (cls.from_config(cls.load_config(folder)) if hasattr(cls, "load_config")
                 else cls(cls.config_class.from_pretrained(folder)))
    load_state_dict_strict(model, weights, device, dtype)
    return model.eval()


@contextmanager
def _config_folder(config_dir: str | Path | None) -> Iterator[Path]:
    """The SDXL config folder of a single-file checkpoint: ``config_dir`` when given, else the built-in one."""
    if config_dir is not None:
        yield Path(config_dir)
        return
    with built_in_sdxl_config() as folder:
        yield folder


SDXL_FILE_TEXT_ENCODER_2 = "conditioner.embedders.1.model."  # OpenCLIP bigG's keys in an SDXL single file


def _sdxl_models_from_file(path: Path, folder: Path, dtype: torch.dtype, vae_dtype: torch.dtype,
                           device: str | torch.device) -> dict[str, torch.nn.Module]:
    """SDXL's four models from a single-file checkpoint (original key layout) and the configs in ``folder``:
    the file read once straight onto ``device`` in its own dtype, its keys mapped to diffusers' and
    transformers' by diffusers' converters there, each model built on the meta device and given the
    converted tensors, cast to its dtype on the device. Strict: a model whose keys the file does not
    fill exactly is a ValueError naming the file."""
    from diffusers.loaders.single_file_utils import (
        convert_ldm_clip_checkpoint,
        convert_ldm_unet_checkpoint,
        convert_ldm_vae_checkpoint,
        convert_open_clip_checkpoint,
    )

    checkpoint = read_tensors(path, device)
    with parameters_on_meta():
        unet = UNet2DConditionModel.from_config(UNet2DConditionModel.load_config(folder / "unet"))
        vae = AutoencoderKL.from_config(AutoencoderKL.load_config(folder / "vae"))
        text_encoder = CLIPTextModel(CLIPTextConfig.from_pretrained(folder / "text_encoder"))
        text_encoder_2 = CLIPTextModelWithProjection(CLIPTextConfig.from_pretrained(folder / "text_encoder_2"))
    clip_l = convert_ldm_clip_checkpoint(checkpoint)
    if not hasattr(text_encoder, "text_model"):  # transformers >= 5.6 builds CLIPTextModel without the wrapper
        clip_l = {k.removeprefix("text_model."): v for k, v in clip_l.items()}
    states = {"unet": convert_ldm_unet_checkpoint(checkpoint, dict(unet.config)),
              "vae": convert_ldm_vae_checkpoint(checkpoint, dict(vae.config)), "text_encoder": clip_l,
              "text_encoder_2": convert_open_clip_checkpoint(text_encoder_2, checkpoint, SDXL_FILE_TEXT_ENCODER_2)}
    del checkpoint
    models = {"unet": unet, "vae": vae, "text_encoder": text_encoder, "text_encoder_2": text_encoder_2}
    for name, model in models.items():
        wanted = vae_dtype if name == "vae" else dtype
        assign_strict(model, {k: v.to(wanted) if v.is_floating_point() else v for k, v in states.pop(name).items()},
                      f"SDXL checkpoint '{path}' ({name})")
        model.eval()
    return models


def _sdxl_models_from_folder(path: Path, dtype: torch.dtype, vae_dtype: torch.dtype,
                             device: str | torch.device) -> dict[str, torch.nn.Module]:
    """SDXL's four models from a diffusers folder: the UNet and VAE by :func:`_from_folder`, the text
    encoders by transformers' ``from_pretrained`` (which knows its key renames), then placed."""
    text = {name: _placed(cls.from_pretrained(path / name, local_files_only=True,
                                              variant=_weights_variant(path / name)), device, dtype)
            for name, cls in (("text_encoder", CLIPTextModel), ("text_encoder_2", CLIPTextModelWithProjection))}
    return {"unet": _from_folder(UNet2DConditionModel, path / "unet", device, dtype),
            "vae": _from_folder(AutoencoderKL, path / "vae", device, vae_dtype), **text}


def load_sdxl(
    path: str | Path | None = None,
    *,
    config_dir: str | Path | None = None,
    dtype: torch.dtype = torch.float16,
    device: str | torch.device = "cpu",
    hf_cache_dir: str | Path | None = None,
    loras: tuple[LoRA, ...] = (),
) -> SDXLBase:
    """SDXL base from a diffusers folder or a single-file checkpoint (see the module docstring), with
    ``loras`` fused into its UNet and text encoders on ``device`` (:func:`~artnvg_core.diffusion.lora.fuse_loras`).

    path None looks in the Hugging Face cache. For a single file, ``config_dir`` (default: the
    configs and tokenizers shipped with the package) provides configs and tokenizers. The weights are read
    straight onto ``device`` (:mod:`artnvg_core.tensor_files`); no diffusers pipeline is built unless
    ``loras`` are fused.
    """
    path = locate(SDXL_BASE, path, hf_cache_dir=hf_cache_dir)
    check_sdxl(path, config_dir)
    configs = contextlib.nullcontext(path) if path.is_dir() else _config_folder(config_dir)
    with configs as folder, sdxl_loading_notices_silenced():
        vae_config, scheduler_config, index = (_json_config(folder / name) for name in (
            "vae/config.json", "scheduler/scheduler_config.json", "model_index.json"))  # before any model loads
        vae_dtype = _vae_dtype(vae_config.get("force_upcast", True), dtype, device)
        models = (_sdxl_models_from_folder(path, dtype, vae_dtype, device) if path.is_dir()
                  else _sdxl_models_from_file(path, folder, dtype, vae_dtype, device))
        tokenizers = {name: CLIPTokenizer.from_pretrained(folder / name) for name in ("tokenizer", "tokenizer_2")}
    base = SDXLBase(**models, **tokenizers, scheduler_config=scheduler_config,
                    force_zeros_for_empty_prompt=bool(index.get("force_zeros_for_empty_prompt", True)))
    fuse_loras(base, loras)
    return base


def load_vae(
    path: str | Path | None = None,
    *,
    dtype: torch.dtype = torch.float16,
    device: str | torch.device = "cpu",
    hf_cache_dir: str | Path | None = None,
) -> AutoencoderKL:
    """An SDXL VAE (default: madebyollin/sdxl-vae-fp16-fix from the cache), fp16-safe (module docstring)."""
    path = locate(SDXL_VAE_FP16_FIX, path, hf_cache_dir=hf_cache_dir)
    if path.is_dir():
        vae = AutoencoderKL.from_pretrained(path, local_files_only=True, variant=_weights_variant(path))
    else:
        config = _config_beside(path)
        if config is None:
            raise MissingModelError(f"VAE weights '{path}': no config.json beside the file")
        with parameters_on_meta():
            vae = AutoencoderKL.from_config(config)
        load_state_dict_strict(vae, path, device, _vae_dtype(vae.config.force_upcast, dtype, device))
    return _placed(vae, device, _vae_dtype(vae.config.force_upcast, dtype, device))


def load_controlnet(
    path: str | Path | None = None,
    *,
    unet_config: dict | None = None,
    dtype: torch.dtype = torch.float16,
    device: str | torch.device = "cpu",
    hf_cache_dir: str | Path | None = None,
) -> ControlNetModel:
    """The tile ControlNet from a diffusers folder or a diffusers-keyed ``.safetensors`` file.

    A single file takes its config from ``config.json`` beside it, else from ``unet_config``.
    """
    path = locate(TILE_CONTROLNET, path, hf_cache_dir=hf_cache_dir)
    if path.is_dir():
        return _from_folder(ControlNetModel, path, device, dtype)
    config = _config_beside(path)
    if config is None and unet_config is None:
        raise MissingModelError(
            f"ControlNet weights '{path}': no config.json beside the file and no UNet config to derive one from"
        )
    with parameters_on_meta():
        controlnet = ControlNetModel.from_config(config or controlnet_config_from_unet(unet_config))
    load_state_dict_strict(controlnet, path, device, dtype)
    return controlnet.eval()


def load_image_encoder(
    path: str | Path | None = None,
    *,
    dtype: torch.dtype = torch.float16,
    device: str | torch.device = "cpu",
    hf_cache_dir: str | Path | None = None,
) -> CLIPVisionModelWithProjection:
    """The IP-Adapter SDXL image encoder from a transformers folder or a single ``.safetensors`` file."""
    path = locate(IMAGE_ENCODER, path, hf_cache_dir=hf_cache_dir)
    if path.is_dir():
        require_path(path / "config.json", "image encoder folder")
        return _from_folder(CLIPVisionModelWithProjection, path, device, dtype)
    config = _config_beside(path) or VIT_BIGG_IMAGE_ENCODER_CONFIG
    with parameters_on_meta():
        encoder = CLIPVisionModelWithProjection(CLIPVisionConfig(**transformers_config_kwargs(config)))
    load_state_dict_strict(encoder, path, device, dtype)
    return encoder.eval()


def _bytes(path: Path) -> int:
    """Size of a file, or of every file under a folder (a diffusers folder, a Hugging Face snapshot)."""
    return sum(size for _, size, _ in file_key(path)[1])


def load_diffusion_models(
    files: ModelFiles,
    *,
    sdxl_config_dir: str | Path | None = None,
    vae: str | Path | None = None,
    dtype: torch.dtype = torch.float16,
    device: str | torch.device = "cpu",
    query_chunk_size: int | None = None,
    hf_cache_dir: str | Path | None = None,
    loras: tuple[LoRA, ...] = (),
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> DiffusionModels:
    """Load every model of ``files`` (a None field = the Hugging Face cache; ``vae`` None = SDXL's own
    VAE), fuse ``loras`` into SDXL (:func:`load_sdxl`) and attach CSGO.

    All files are checked (:func:`check_model_files`, :func:`~artnvg_core.diffusion.lora.check_lora`) before
    any is loaded, so a missing one fails fast.
    query_chunk_size: see :class:`artnvg_core.diffusion.attention.NeighbourViewSelfAttention`.
    progress(bytes loaded, bytes of all the files, {"loading": name}) is called as each model starts
    loading, and once more, without "loading", when all are (the libraries' own bars hidden meanwhile:
    :func:`~.quiet_notices.library_progress_bars_hidden`); should_stop() is checked before each model
    and raises :class:`~artnvg_core.progress.Cancelled`.
    """
    found = check_model_files(files, sdxl_config_dir=sdxl_config_dir, hf_cache_dir=hf_cache_dir)
    for lora in loras:
        check_lora(lora)
    sizes = {"SDXL": _bytes(found.sdxl), **({"VAE": _bytes(vae)} if vae is not None else {}),
             "ControlNet": _bytes(found.controlnet), "image encoder": _bytes(found.image_encoder),
             "CSGO": _bytes(found.csgo)}
    done, total = 0, sum(sizes.values())

    def loading(name: str, load):
        nonlocal done
        check_stop(should_stop)
        if progress is not None:
            progress(done, total, {"loading": name})
        with library_progress_bars_hidden():
            model = load()
        done += sizes[name]
        return model

    base = loading("SDXL", lambda: load_sdxl(found.sdxl, config_dir=sdxl_config_dir, dtype=dtype, device=device,
                                             hf_cache_dir=hf_cache_dir, loras=loras))
    if vae is not None:
        base.vae = loading("VAE", lambda: load_vae(vae, dtype=dtype, device=device))
    control = loading("ControlNet", lambda: load_controlnet(found.controlnet, unet_config=dict(base.unet.config),
                                                            dtype=dtype, device=device))
    encoder = loading("image encoder", lambda: load_image_encoder(found.image_encoder, dtype=dtype, device=device))
    projections = loading("CSGO", lambda: load_csgo(found.csgo, base.unet, control, query_chunk_size=query_chunk_size))
    if progress is not None:
        progress(total, total, {})
    return DiffusionModels(base=base, controlnet=control, image_encoder=encoder, csgo=projections)
