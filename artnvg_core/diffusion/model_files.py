"""Finding model files on disk, never downloading: an explicit path, else the Hugging Face cache.

Each model ArtNVG needs is a :class:`ModelSource`: what it is, its Hugging Face repository
and the file or folder inside it. :func:`locate` returns an existing path or raises
:class:`MissingModelError` saying which file, where it was looked for and where to get it.
(The ComfyUI layer maps its model folders onto explicit paths before calling in.)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


class MissingModelError(ValueError):
    """A model file or folder was not found (the message says where it was looked for and how to get it)."""


@dataclass(frozen=True)
class ModelSource:
    """A model: ``description``, Hugging Face ``repo`` and ``repo_path`` inside it ('' = the whole repo)."""

    description: str
    repo: str
    repo_path: str = ""

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
        if not self.repo_path:
            return f"huggingface-cli download {self.repo}"
        if self._is_file:
            return f"huggingface-cli download {self.repo} {self.repo_path}"
        return f"huggingface-cli download {self.repo} --include '{self.repo_path}/*'"


SDXL_BASE = ModelSource(
    "SDXL 1.0 base (diffusers folder or single-file checkpoint)", "stabilityai/stable-diffusion-xl-base-1.0"
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
CSGO_WEIGHTS = ModelSource("CSGO content/style weights (4 content / 32 style tokens)", "InstantX/CSGO", "csgo_4_32.bin")


def hf_cache_path(source: ModelSource, cache_dir: str | Path | None = None) -> Path:
    """Where ``source`` would lie in the Hugging Face cache (main revision); may not exist."""
    if cache_dir is None:
        from huggingface_hub import constants

        cache_dir = constants.HF_HUB_CACHE
    repo_dir = Path(cache_dir) / f"models--{source.repo.replace('/', '--')}"
    ref = repo_dir / "refs" / "main"
    revision = ref.read_text().strip() if ref.is_file() else "<revision>"
    return repo_dir / "snapshots" / revision / source.repo_path


def locate(source: ModelSource, path: str | Path | None = None, *, hf_cache_dir: str | Path | None = None) -> Path:
    """The existing path of ``source``: ``path`` when given (it must exist), else the Hugging Face cache.

    Raises :class:`MissingModelError` naming the model, the places looked at and where to get it.
    """
    candidates = [Path(path).expanduser()] if path is not None else [hf_cache_path(source, hf_cache_dir)]
    for candidate in candidates:
        if candidate.exists():
            return candidate
    looked = ", ".join(f"'{c}'" for c in candidates)
    raise MissingModelError(
        f"{source.description} not found: looked for {looked}. Get it from {source.url} "
        f"(e.g. `{source.download_command}`) and pass its path."
    )
