"""CLIP-DC, CLIP Direction Consistency (Instruct-NeRF2NeRF): consistency along a camera path.

For frames o_k (original renders) and s_k (stylized renders) of one camera path, with C the
L2-normalised CLIP image embedding (as in InstructPix2Pix's ``ClipSimilarity``):

    CLIP-DC = mean_k cos(C(s_k+1) - C(s_k), C(o_k+1) - C(o_k))

over adjacent frames. It is 1 when the stylized frames change in CLIP space exactly as the
original frames do.

Weights: a transformers CLIP model (``CLIPModel`` or ``CLIPVisionModelWithProjection``
folder; the paper family uses ViT-L/14, ``openai/clip-vit-large-patch14``), from an explicit
folder or the Hugging Face cache, never downloaded.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F

from ..diffusion.images import check_images, clip_preprocess
from ..diffusion.model_files import MissingModelError, ModelSource, locate
from ..tensor_files import read_tensors

CLIP_VIT_L = ModelSource("CLIP ViT-L/14 image encoder (transformers folder with config.json)",
                         "openai/clip-vit-large-patch14")
_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
_VISION_PREFIXES = ("vision_model.", "visual_projection.")


def _vision_config(folder: Path):
    """The image tower's CLIPVisionConfig, with the projection size of a full CLIP config."""
    from transformers import AutoConfig, CLIPConfig, CLIPVisionConfig

    try:
        config = AutoConfig.from_pretrained(str(folder), local_files_only=True)
    except (OSError, ValueError) as error:
        raise ValueError(f"{folder / 'config.json'}: not a readable transformers config ({error})") from error
    if isinstance(config, CLIPConfig):
        vision = config.vision_config
        vision.projection_dim = config.projection_dim
        return vision
    if isinstance(config, CLIPVisionConfig):
        return config
    raise ValueError(f"{folder / 'config.json'}: model_type {config.model_type!r}, expected 'clip' or 'clip_vision_model'")


def _vision_state(folder: Path) -> dict[str, torch.Tensor]:
    """The image tower's tensors (``vision_model.*``, ``visual_projection.*``) of the folder's weight file."""
    path = next((folder / name for name in _WEIGHT_FILES if (folder / name).is_file()), None)
    if path is None:
        raise MissingModelError(f"{folder}: no weights file ({' or '.join(_WEIGHT_FILES)}); expected the files of "
                                f"{CLIP_VIT_L.url} (`{CLIP_VIT_L.download_command}`)")
    state = read_tensors(path)  # ValueError naming the file: unreadable, truncated, not a state dict
    return {key: value for key, value in state.items() if key.startswith(_VISION_PREFIXES)}


def load_clip_image_encoder(path: str | Path | None = None, *, device: str | torch.device = "cpu"):
    """A frozen ``CLIPVisionModelWithProjection`` in eval mode on ``device``.

    path: a transformers folder (config.json + model.safetensors or pytorch_model.bin) of a
    CLIPModel or CLIPVisionModelWithProjection; None looks for
    ``openai/clip-vit-large-patch14`` in the Hugging Face cache. Only the image tower is
    loaded; every one of its tensors must be present with the configured shape. Raises
    :class:`MissingModelError` (a ValueError) saying what is missing, where it was looked for
    and how to get it; a ValueError for unreadable or foreign files.
    """
    from transformers import CLIPVisionModelWithProjection

    folder = locate(CLIP_VIT_L, path)
    if not (folder / "config.json").is_file():
        raise MissingModelError(
            f"{folder}: not a transformers CLIP folder (no config.json); expected e.g. the files of "
            f"{CLIP_VIT_L.url} (`{CLIP_VIT_L.download_command}`)"
        )
    model = CLIPVisionModelWithProjection(_vision_config(folder))
    state = _vision_state(folder)
    expected = model.state_dict()
    missing = sorted(k for k in expected if k not in state and not k.endswith("position_ids"))
    wrong = [f"{k} {tuple(state[k].shape)} != {tuple(v.shape)}" for k, v in expected.items()
             if k in state and state[k].shape != v.shape]
    if missing or wrong:
        raise ValueError(f"{folder}: weights do not match config.json: missing {missing[:6]}, wrong shapes {wrong[:6]}")
    model.load_state_dict(state, strict=False)
    return model.to(device).eval().requires_grad_(False)


@torch.no_grad()
def clip_image_embeddings(model, images: torch.Tensor, *, batch_size: int = 16) -> torch.Tensor:
    """L2-normalised projected CLIP embeddings [B, D] (float32) of ``images`` [B, H, W, 3] in [0, 1]."""
    images = check_images(images, "clip_image_embeddings: images")
    size = model.config.image_size
    param = next(model.parameters())
    embeddings = []
    for start in range(0, images.shape[0], batch_size):
        pixels = clip_preprocess(images[start:start + batch_size].to(param.device), size)
        embeddings.append(model(pixel_values=pixels.to(param.dtype)).image_embeds.float())
    return F.normalize(torch.cat(embeddings), dim=-1)


def direction_consistency(original: torch.Tensor, stylized: torch.Tensor) -> torch.Tensor:
    """cos(s_k+1 - s_k, o_k+1 - o_k) [F - 1] for embeddings [F, D] of F >= 2 path frames."""
    if original.shape != stylized.shape or original.ndim != 2 or original.shape[0] < 2:
        raise ValueError(
            "direction_consistency: expected two [F, D] embedding batches of the same shape with F >= 2, "
            f"got {tuple(original.shape)} and {tuple(stylized.shape)}"
        )
    return F.cosine_similarity(stylized.diff(dim=0), original.diff(dim=0), dim=-1)


def clip_dc_scores(model, original_frames: torch.Tensor, stylized_frames: torch.Tensor) -> torch.Tensor:
    """Per-step CLIP direction consistency [F - 1] of frames [F, H, W, 3] along one camera path.

    The metric is the mean of the returned values.
    """
    if original_frames.shape[0] != stylized_frames.shape[0]:
        raise ValueError(
            f"clip_dc_scores: {original_frames.shape[0]} original but {stylized_frames.shape[0]} stylized frames"
        )
    return direction_consistency(clip_image_embeddings(model, original_frames),
                                 clip_image_embeddings(model, stylized_frames))
