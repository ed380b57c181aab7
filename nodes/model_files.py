"""Files a loader node offers from one of ComfyUI's model folders (``models/csgo``...), and the message when the
chosen one is not there: the file, the folders looked in (and what they hold), where to get it and where to save it.

A :class:`ModelFile` declares the loader's list input as a COMBO, which ComfyUI does not compare with the value
(its own "Value not in list" says neither where it looked nor where to get the file): the pack's prompt check
(``prompt_checks``) asks :meth:`ModelFile.check` before anything runs, so an empty folder, a file named but not
there, and a file deleted after the server started are all refused with this message; the loader asks again
(:meth:`ModelFile.path`) as it runs.

ComfyUI's own model loaders (:data:`STOCK_LOADERS`: each that makes a MODEL, CONTROL_NET, CLIP_VISION or VAE, with
its file inputs) keep their list and its "Value not in list"; the prompt check gives :meth:`ModelFile.check`'s
message to each node of the pack such a loader feeds. The file the pack's workflows name is told its exact source;
another name, the kind of model wanted and that source as an example.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from artnvg_core.diffusion.model_files import IMAGE_ENCODER_FILE, SDXL_BASE, TILE_CONTROLNET, ModelSource

from .comfy_bridge import model_file_path, model_files, model_folder_paths
from .node_errors import NodeInputError

_LISTED = 5  # files of the folder a message names; then how many more


@dataclass(frozen=True)
class ModelFile:
    """A loader's input ``name``: a file of ComfyUI's model folder ``folder``, the model ``source`` (its Hugging Face
    repository and file: where to get it); ``tooltip`` is the input's tooltip; ``file`` the name the pack's workflows
    give it ('': the source's own file name); ``kind`` what a file of another name should be ('': any name is told
    ``source``)."""

    name: str
    folder: str
    source: ModelSource
    tooltip: str = ""
    file: str = ""
    kind: str = ""

    @property
    def usual_name(self) -> str:
        """The file's name in the pack's workflows: ``file``, else the name of the source's file."""
        return self.file or Path(self.source.download_file or self.source.repo_path).name

    def list_input(self) -> tuple:
        """The declaration of input ``name``, with the folder's files listed now: a COMBO, whose value ComfyUI leaves
        to :meth:`check`."""
        return ("COMBO", {"options": model_files(self.folder), "tooltip": self.tooltip})

    def check(self, node: str, file: str) -> str | None:
        """A loader's ``check_files`` answer (``prompt_checks``): None when ``file`` is in the folder, else the message
        naming ``node``, the input, the file, the folders looked in with what they hold, where to get the file and
        the path to save it as."""
        if file.strip() and model_file_path(self.folder, file) is not None:
            return None
        present = model_files(self.folder)
        held = ", ".join(f"'{name}'" for name in present[:_LISTED]) or "nothing"
        if len(present) > _LISTED:
            held += f" and {len(present) - _LISTED} more"
        looked = ", ".join(model_folder_paths(self.folder)) or f"ComfyUI's models/{self.folder}"
        chosen = f"'{file}' is not in" if file.strip() else "no file chosen from"
        return (f"{node}: input '{self.name}': {chosen} the '{self.folder}' model folder (looked in {looked}; found "
                f"{held}). {self.where_to_get(file)}")

    def where_to_get(self, file: str = "") -> str:
        """Where to get ``file`` and the path to save it as (in the folder ComfyUI searches first): the source for the
        name the pack's workflows use (or for any name, without ``kind``), else ``kind`` with the source as an
        example."""
        folders = model_folder_paths(self.folder)
        saved_as = Path(folders[0] if folders else f"models/{self.folder}") / (file.strip() or self.usual_name)
        source = f"{self.source.description} from {self.source.url} (`{self.source.download_command}`)"
        if self.kind and file.strip() not in ("", self.usual_name):
            return f"Save {self.kind} as {saved_as}, e.g. the {source}"
        direct = self.source.download_as(saved_as)
        if direct:
            return f"Get the {self.source.description} from {self.source.url}: `{direct}` saves it as {saved_as}"
        return f"Get the {source} and save it as {saved_as}"

    def path(self, node: str, file: str) -> Path:
        """The full path of ``file`` in the folder; a :class:`~.node_errors.NodeInputError` with :meth:`check`'s
        message when it is not there."""
        missing = self.check(node, file)
        if missing:
            raise NodeInputError(missing)
        return model_file_path(self.folder, file)


SDXL_LORA_EXAMPLE = ModelSource("Pixel Art XL style LoRA", "nerijs/pixel-art-xl", "pixel-art-xl.safetensors")
SDXL_UNET = ModelSource("SDXL 1.0 base's UNet (diffusers layout, fp16)", SDXL_BASE.repo,
                        "unet/diffusion_pytorch_model.fp16.safetensors")
SDXL_VAE = ModelSource("SDXL VAE, fp16-safe", "madebyollin/sdxl-vae-fp16-fix", "sdxl_vae.safetensors")
SD_CONFIG = ModelSource("Stable Diffusion inference config", "stable-diffusion-v1-5/stable-diffusion-v1-5",
                        "v1-inference.yaml")

# a checkpoint folder holds single files: the library's SDXL source also takes a diffusers folder, which Load Checkpoint
# does not read
SDXL_CHECKPOINT = replace(SDXL_BASE, description="SDXL 1.0 base checkpoint")

CHECKPOINT_FILE = ModelFile("ckpt_name", "checkpoints", SDXL_CHECKPOINT, kind=(
    "an SDXL 1.0 checkpoint (the base or a fine-tune of it: CSGO and the tile ControlNet are trained on SDXL)"))
UNET_FILE = ModelFile("unet_name", "diffusion_models", SDXL_UNET, kind=(
    "an SDXL 1.0 UNet alone (the base's or a fine-tune's, in ComfyUI's or diffusers' layout)"))
CONFIG_FILE = ModelFile("config_name", "configs", SD_CONFIG, kind=(
    "a model config (for an SDXL checkpoint v1-inference.yaml, which ComfyUI ships: the checkpoint then loads as "
    "Load Checkpoint loads it)"))
LORA_FILE = ModelFile("lora_name", "loras", SDXL_LORA_EXAMPLE, kind="a LoRA trained on SDXL 1.0")
CONTROLNET_FILE = ModelFile("control_net_name", "controlnet", TILE_CONTROLNET, kind=(
    "an SDXL tile ControlNet (CSGO's ControlNet weights were trained with TTPlanet's)"))
CLIP_VISION_FILE = ModelFile("clip_name", "clip_vision", IMAGE_ENCODER_FILE,
                             file="CLIP-ViT-bigG-14-laion2B-39B-b160k.safetensors", kind=(
                                 "the OpenCLIP ViT-bigG/14 image encoder (CSGO's resamplers read its 1664-wide "
                                 "features)"))
VAE_FILE = ModelFile("vae_name", "vae", SDXL_VAE, kind="an SDXL VAE")
# ComfyUI 0.3.64's loaders whose MODEL, CONTROL_NET, CLIP_VISION or VAE a node of the pack takes: node type (its title
# in the editor) -> its file inputs
STOCK_LOADERS = {
    "CheckpointLoaderSimple": (CHECKPOINT_FILE,),  # Load Checkpoint
    "CheckpointLoader": (CONFIG_FILE, CHECKPOINT_FILE),  # Load Checkpoint With Config (DEPRECATED)
    "unCLIPCheckpointLoader": (CHECKPOINT_FILE,),
    "ImageOnlyCheckpointLoader": (CHECKPOINT_FILE,),  # Image Only Checkpoint Loader (img2vid model)
    "UNETLoader": (UNET_FILE,),  # Load Diffusion Model
    "LoraLoader": (LORA_FILE,),  # Load LoRA
    "LoraLoaderModelOnly": (LORA_FILE,),
    "ControlNetLoader": (CONTROLNET_FILE,),  # Load ControlNet Model
    "DiffControlNetLoader": (CONTROLNET_FILE,),  # Load ControlNet Model (diff)
    "CLIPVisionLoader": (CLIP_VISION_FILE,),  # Load CLIP Vision
    "VAELoader": (VAE_FILE,),  # Load VAE
}
