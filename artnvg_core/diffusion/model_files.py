"""Finding model files on disk, never downloading: an explicit path, else the Hugging Face cache.

Each model ArtNVG needs is a :class:`ModelSource`: what it is, its Hugging Face repository
and the file or folder inside it. The four files of the diffusion stylizer travel together as one
:class:`ModelFiles` (:data:`MODEL_SOURCES` names the source of each field). :func:`locate` returns an existing path or raises
:class:`MissingModelError` saying which file, where it was looked for and where to get it.
(The ComfyUI layer maps its model folders onto explicit paths before calling in.)
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, fields
from pathlib import Path


class MissingModelError(ValueError):
    """A model file or folder was not found (the message says where it was looked for and how to get it)."""


@dataclass(frozen=True)
class ModelSource:
    """A model: ``description``, Hugging Face ``repo`` and ``repo_path`` inside it ('' = the whole repo);
    ``download_file``: the one file of the repo that suffices, when there is one (what the download command names)."""

    description: str
    repo: str
    repo_path: str = ""
    download_file: str = ""

    @property
    def _is_file(self) -> bool:
        return "." in Path(self.repo_path).name

    @property
    def url(self) -> str:
        if not self.repo_path:
            return f"https://huggingface.co/{self.repo}"
        return f"https://huggingface.co/{self.repo}/{'blob' if self._is_file else 'tree'}/main/{self.repo_path}"

    @property
    def download_command(self) -> str:
        """The command that fetches it into the Hugging Face cache: ``hf download`` (huggingface_hub's command
        line since 0.34; 1.x and later have no ``huggingface-cli``)."""
        if self.download_file:
            return f"hf download {self.repo} {self.download_file}"
        if not self.repo_path:
            return f"hf download {self.repo}"
        if self._is_file:
            return f"hf download {self.repo} {self.repo_path}"
        return f"hf download {self.repo} --include '{self.repo_path}/*'"

    def download_as(self, path: str | Path) -> str | None:
        """The command that saves the model's one file as ``path`` (``hf download ... --local-dir`` its folder), where
        that file lies at the repository's top under ``path``'s name; else None (a file in a folder of the
        repository would come with that folder, another name would need a rename)."""
        path = Path(path)
        file = self.download_file or (self.repo_path if self._is_file else "")
        if not file or "/" in file or file != path.name:
            return None
        return f"hf download {self.repo} {file} --local-dir {shlex.quote(str(path.parent))}"


SDXL_BASE = ModelSource(
    "SDXL 1.0 base (diffusers folder or single-file checkpoint)", "stabilityai/stable-diffusion-xl-base-1.0",
    download_file="sd_xl_base_1.0.safetensors",
)
SDXL_VAE_FP16_FIX = ModelSource(
    "SDXL VAE, fp16-safe (diffusers folder or .safetensors)", "madebyollin/sdxl-vae-fp16-fix"
)
TILE_CONTROLNET = ModelSource(
    "TTPlanet SDXL tile ControlNet (realistic)",
    "TTPlanet/TTPLanet_SDXL_Controlnet_Tile_Realistic",
    "TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors",
)
IMAGE_ENCODER = ModelSource(
    "IP-Adapter SDXL image encoder (OpenCLIP ViT-bigG/14)", "h94/IP-Adapter", "sdxl_models/image_encoder"
)
IMAGE_ENCODER_FILE = ModelSource(  # its weights as the one file ComfyUI's Load CLIP Vision reads
    "IP-Adapter SDXL image encoder (OpenCLIP ViT-bigG/14)", "h94/IP-Adapter",
    "sdxl_models/image_encoder/model.safetensors",
)
CSGO_WEIGHTS = ModelSource("CSGO content/style weights (4 content / 32 style tokens)", "InstantX/CSGO", "csgo_4_32.bin")


MODEL_SOURCES = {"sdxl": SDXL_BASE, "controlnet": TILE_CONTROLNET, "image_encoder": IMAGE_ENCODER,
                 "csgo": CSGO_WEIGHTS}


@dataclass(frozen=True)
class ModelFiles:
    """The diffusion stylizer's four model files or folders; None: the Hugging Face cache.
    Each field's model is ``MODEL_SOURCES[field]``."""

    sdxl: str | Path | None = None
    controlnet: str | Path | None = None
    image_encoder: str | Path | None = None
    csgo: str | Path | None = None

    def items(self) -> list[tuple[str, str | Path | None]]:
        """(field name, path) of the four, in the order SDXL, ControlNet, image encoder, CSGO."""
        return [(field.name, getattr(self, field.name)) for field in fields(self)]


def hf_cache_path(source: ModelSource, cache_dir: str | Path | None = None) -> Path:
    """Where ``source`` would lie in the Hugging Face cache (main revision); may not exist."""
    if cache_dir is None:
        from huggingface_hub import constants

        cache_dir = constants.HF_HUB_CACHE
    repo_dir = Path(cache_dir) / f"models--{source.repo.replace('/', '--')}"
    ref = repo_dir / "refs" / "main"
    revision = ref.read_text().strip() if ref.is_file() else "<revision>"
    return repo_dir / "snapshots" / revision / source.repo_path


def locate(source: ModelSource, path: str | Path | None = None, *, hf_cache_dir: str | Path | None = None,
           option: str = "") -> Path:
    """The existing path of ``source``: ``path`` when given (it must exist), else the Hugging Face cache.

    Raises :class:`MissingModelError` naming the model, the places looked at, where to get it and the
    ``option`` that takes its path (e.g. "--controlnet"), when given.
    """
    candidates = [Path(path).expanduser()] if path is not None else [hf_cache_path(source, hf_cache_dir)]
    for candidate in candidates:
        if candidate.exists():
            return candidate
    looked = ", ".join(f"'{c}'" for c in candidates)
    raise MissingModelError(
        f"{source.description} not found: looked for {looked}. Get it from {source.url} "
        f"(e.g. `{source.download_command}`) and pass its path{f' with {option}' if option else ''}."
    )


SDXL_COMPONENTS = ("unet", "vae", "text_encoder", "text_encoder_2", "tokenizer", "tokenizer_2", "scheduler")


def require_path(path: Path, what: str) -> Path:
    """``path`` when it exists, else :class:`MissingModelError` naming ``what`` and the path."""
    if not path.exists():
        raise MissingModelError(f"{what}: '{path}' does not exist")
    return path


def check_sdxl(path: Path, config_dir: str | Path | None = None) -> None:
    """An SDXL folder holds its index and components; a single file's explicit ``config_dir`` holds its index
    (without one, the configs shipped with the package are used)."""
    if path.is_dir():
        require_path(path / "model_index.json", "SDXL diffusers folder")
        for name in SDXL_COMPONENTS:
            require_path(path / name, f"SDXL diffusers folder component '{name}'")
        require_path(path / "vae" / "config.json", "SDXL VAE config")
    elif config_dir is not None:
        require_path(Path(config_dir) / "model_index.json",
                     f"SDXL configs for the single-file checkpoint '{path}' (a diffusers-format SDXL folder)")


def check_model_files(
    files: ModelFiles,
    *,
    sdxl_config_dir: str | Path | None = None,
    hf_cache_dir: str | Path | None = None,
) -> ModelFiles:
    """The existing paths of ``files`` (a None field: the Hugging Face cache), after checking without
    loading anything that each file or folder holds what its loader reads.
    Raises :class:`MissingModelError` naming the first thing missing, and only that, with the command line's
    option for it (--sdxl, --controlnet, --image-encoder, --csgo: the fields' names)."""
    found = ModelFiles(**{name: locate(MODEL_SOURCES[name], path, hf_cache_dir=hf_cache_dir,
                                       option=f"--{name.replace('_', '-')}") for name, path in files.items()})
    check_sdxl(found.sdxl, sdxl_config_dir)
    for path, what in ((found.controlnet, "ControlNet folder"), (found.image_encoder, "image encoder folder")):
        if path.is_dir():
            require_path(path / "config.json", what)
    return found


def weight_files(found: ModelFiles) -> list[Path]:
    """The weight files a load of ``found`` (existing paths, :func:`check_model_files`) reads: each single
    file, and in a folder every ``.safetensors``/``.bin`` file but the plain twin of an fp16 variant
    (``x.safetensors`` beside ``x.fp16.safetensors``: a float16 load reads the variant)."""
    paths = []
    for _, path in found.items():
        path = Path(path)
        if path.is_file():
            paths.append(path)
            continue
        weights = sorted(p for suffix in ("*.safetensors", "*.bin") for p in path.rglob(suffix))
        variants = {p.with_name(p.name.replace(".fp16.", ".")) for p in weights if ".fp16." in p.name}
        paths += [p for p in weights if p not in variants]
    return paths


def missing_model(files: ModelFiles, *, sdxl_config_dir: str | Path | None = None) -> str | None:
    """None when every file the diffusion models' load reads is there (:func:`check_model_files`), else the
    first missing one's message."""
    try:
        check_model_files(files, sdxl_config_dir=sdxl_config_dir)
    except MissingModelError as error:
        return str(error)
    return None
