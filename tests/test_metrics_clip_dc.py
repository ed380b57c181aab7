"""CLIP-DC on tiny randomly initialised transformers CLIP models; loader errors."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from artnvg_core.diffusion.images import clip_preprocess
from artnvg_core.diffusion.model_files import MissingModelError
from artnvg_core.metrics.clip_dc import (
    clip_dc_scores,
    clip_image_embeddings,
    direction_consistency,
    load_clip_image_encoder,
)

VISION = {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2, "num_attention_heads": 4,
              "image_size": 28, "patch_size": 7}


@pytest.fixture(scope="module")
def clip_folder(tmp_path_factory):
    """A tiny full CLIPModel (text + vision towers) saved like openai/clip-vit-large-patch14."""
    from transformers import CLIPConfig, CLIPModel

    torch.manual_seed(0)
    config = CLIPConfig(
        text_config={"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1, "num_attention_heads": 4, "vocab_size": 100,
                         "bos_token_id": 0, "eos_token_id": 1},
        vision_config=VISION,
        projection_dim=16,
    )
    folder = tmp_path_factory.mktemp("clip")
    CLIPModel(config).eval().save_pretrained(folder)
    return folder


def _frames(count: int, height: int = 40, width: int = 56) -> torch.Tensor:
    """A smooth camera-path-like sequence: a pattern drifting sideways."""
    ys, xs = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    frames = [torch.stack([0.5 + 0.4 * torch.sin(6 * xs + 0.4 * k), ys, 0.5 + 0.4 * torch.cos(5 * ys - 0.3 * k)], -1)
              for k in range(count)]
    return torch.stack(frames).clamp(0, 1)


def test_direction_consistency_matches_float64_reference():
    generator = np.random.default_rng(0)
    original, stylized = generator.normal(size=(5, 8)), generator.normal(size=(5, 8))
    reference = []
    for k in range(4):
        a, b = stylized[k + 1] - stylized[k], original[k + 1] - original[k]
        reference.append(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
    got = direction_consistency(torch.from_numpy(original), torch.from_numpy(stylized))
    np.testing.assert_allclose(got.numpy(), reference, rtol=1e-12)
    with pytest.raises(ValueError, match="F >= 2"):
        direction_consistency(torch.zeros(1, 8), torch.zeros(1, 8))


def test_loads_a_full_clip_model_folder_and_embeds_like_it(clip_folder):
    from transformers import CLIPImageProcessor, CLIPModel

    encoder = load_clip_image_encoder(clip_folder)
    frames = _frames(3)
    embeddings = clip_image_embeddings(encoder, frames)
    assert embeddings.shape == (3, 16)
    torch.testing.assert_close(embeddings.norm(dim=-1), torch.ones(3))
    # References: the full model's own image features, on our pixels (exact: same tower and
    # projection) and on CLIPImageProcessor's PIL-resized uint8 pixels (close: same preprocessing).
    processor = CLIPImageProcessor(size={"shortest_edge": 28}, crop_size={"height": 28, "width": 28})
    pil_pixels = processor(images=[(f.numpy() * 255).round().astype(np.uint8) for f in frames], return_tensors="pt")
    full = CLIPModel.from_pretrained(clip_folder).eval()
    for pixels, tolerance in ((clip_preprocess(frames, 28), 1e-6), (pil_pixels["pixel_values"], 5e-3)):
        with torch.no_grad():
            reference = full.get_image_features(pixel_values=pixels)
        reference = getattr(reference, "pooler_output", reference)  # newer transformers wrap the tensor
        torch.testing.assert_close(embeddings, F.normalize(reference, dim=-1), atol=tolerance, rtol=0)


def test_clip_dc_end_to_end(clip_folder):
    encoder = load_clip_image_encoder(clip_folder)
    original = _frames(4)
    same = clip_dc_scores(encoder, original, original.clone())
    torch.testing.assert_close(same, torch.ones(3), atol=1e-4, rtol=0)
    recoloured = clip_dc_scores(encoder, original, original[..., [2, 0, 1]] * 0.8)
    assert recoloured.shape == (3,) and ((recoloured >= -1 - 1e-6) & (recoloured <= 1 + 1e-6)).all()
    assert recoloured.mean() < same.mean()
    with pytest.raises(ValueError, match="4 original but 3 stylized"):
        clip_dc_scores(encoder, original, original[:3])


def test_loader_errors_name_what_is_missing(tmp_path, monkeypatch):
    with pytest.raises(MissingModelError, match="nowhere.*openai/clip-vit-large-patch14"):
        load_clip_image_encoder(tmp_path / "nowhere")
    with pytest.raises(MissingModelError, match="no config.json"):
        load_clip_image_encoder(tmp_path)
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    with pytest.raises(MissingModelError, match="empty-cache.*hf download openai/clip-vit-large-patch14"):
        load_clip_image_encoder(None)
    (tmp_path / "config.json").write_text('{"model_type": "clip_vision_model"}')
    with pytest.raises(MissingModelError, match="no weights file"):
        load_clip_image_encoder(tmp_path)
    (tmp_path / "config.json").write_text('{"model_type": "bert"}')
    with pytest.raises(ValueError, match="model_type 'bert'"):
        load_clip_image_encoder(tmp_path)


@pytest.mark.parametrize("content", [[torch.zeros(1)], {"vision_model.x": torch.zeros(1), 5: torch.zeros(1)}],
                         ids=["list", "int key"])
def test_a_torch_file_that_is_no_state_dict_is_refused_naming_it(clip_folder, tmp_path, content):
    """Found probing weight files with hostile pickles: a list ('list' object has no attribute 'items') or a key
    other than a string escaped as AttributeError."""
    (tmp_path / "config.json").write_text((clip_folder / "config.json").read_text())
    torch.save(content, tmp_path / "pytorch_model.bin")
    with pytest.raises(ValueError, match=r"pytorch_model\.bin': not a state dict \(a mapping of names to tensors"):
        load_clip_image_encoder(tmp_path)


def test_loader_rejects_weights_of_another_shape(clip_folder, tmp_path):
    import shutil

    shutil.copy(clip_folder / "model.safetensors", tmp_path / "model.safetensors")
    config = (clip_folder / "config.json").read_text().replace('"hidden_size": 32', '"hidden_size": 48')
    (tmp_path / "config.json").write_text(config)
    with pytest.raises(ValueError, match="do not match config.json"):
        load_clip_image_encoder(tmp_path)
