"""CSD: the backbone is CLIP's image tower, the released checkpoint layout loads, errors are clear."""

import argparse
import pickle
from fractions import Fraction

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from artnvg_core.diffusion.model_files import MissingModelError
from artnvg_core.metrics.csd import (
    CSDConfig,
    CSDStyleEncoder,
    csd_descriptors,
    csd_scores,
    load_csd,
)
from artnvg_core.tensor_files import load_failure

# OpenAI CLIP ViTs have 64-wide heads; the loader infers heads = width // 64.
TINY = CSDConfig(image_size=28, patch_size=7, width=128, layers=2, heads=2, embed_dim=16)


def _openai_names(hf_state: dict, layers: int) -> dict:
    """transformers CLIPVisionTransformer tensors renamed to OpenAI CLIP's VisionTransformer layout (backbone.*)."""
    out = {
        "conv1.weight": hf_state["embeddings.patch_embedding.weight"],
        "class_embedding": hf_state["embeddings.class_embedding"],
        "positional_embedding": hf_state["embeddings.position_embedding.weight"],
    }
    for ours, theirs in (("ln_pre", "pre_layrnorm"), ("ln_post", "post_layernorm")):
        for kind in ("weight", "bias"):
            out[f"{ours}.{kind}"] = hf_state[f"{theirs}.{kind}"]
    for i in range(layers):
        hf, oa = f"encoder.layers.{i}.", f"transformer.resblocks.{i}."
        for kind in ("weight", "bias"):
            out[oa + f"attn.in_proj_{kind}"] = torch.cat([hf_state[hf + f"self_attn.{p}_proj.{kind}"] for p in "qkv"])
            for ours, theirs in (("attn.out_proj", "self_attn.out_proj"), ("ln_1", "layer_norm1"), ("ln_2", "layer_norm2"),
                                 ("mlp.c_fc", "mlp.fc1"), ("mlp.c_proj", "mlp.fc2")):
                out[oa + f"{ours}.{kind}"] = hf_state[hf + f"{theirs}.{kind}"]
    return {f"backbone.{key}": value for key, value in out.items()}


@pytest.fixture(scope="module")
def reference():
    """A tiny transformers CLIPVisionModel (QuickGELU, TINY's shape) and its tensors in CSD's layout."""
    from transformers import CLIPVisionConfig, CLIPVisionModel

    torch.manual_seed(0)
    config = CLIPVisionConfig(hidden_size=TINY.width, intermediate_size=4 * TINY.width, num_hidden_layers=TINY.layers,
                              num_attention_heads=TINY.heads, image_size=TINY.image_size, patch_size=TINY.patch_size,
                              hidden_act="quick_gelu", layer_norm_eps=1e-5)
    model = CLIPVisionModel(config).eval()
    tower = getattr(model, "vision_model", model)  # transformers 4 wraps the tower, 5 does not
    state = _openai_names(tower.state_dict(), TINY.layers)
    state["last_layer_style"] = torch.randn(TINY.width, TINY.embed_dim)
    return model, state


def _released_checkpoint(state: dict, path) -> None:
    """Save ``state`` like CSD's training checkpoint: DDP prefixes, content head, pickled options."""
    module_state = {f"module.{k}": v for k, v in state.items()}
    module_state["module.last_layer_content"] = torch.randn_like(state["last_layer_style"])
    options = argparse.Namespace(lr=np.float64(3e-4), arch="vit_large", lambda_s=np.float64(1.0))
    torch.save({"model_state_dict": module_state, "opt_bb": {}, "opt_proj": {}, "iter": 1000,
                "args": options, "fp16_scaler": None}, path)


def _model_from(state: dict) -> CSDStyleEncoder:
    model = CSDStyleEncoder(TINY).eval()
    model.load_state_dict(state)
    return model


def _images(count: int) -> torch.Tensor:
    return torch.rand(count, 40, 36, 3, generator=torch.Generator().manual_seed(count))


def test_released_layout_loads_and_matches_the_clip_image_tower(reference, tmp_path):
    hf_model, state = reference
    _released_checkpoint(state, tmp_path / "pytorch_model.bin")
    model = load_csd(tmp_path / "pytorch_model.bin")
    assert model.config == TINY
    pixels = torch.randn(3, 3, TINY.image_size, TINY.image_size, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        expected = F.normalize(hf_model(pixel_values=pixels).pooler_output @ state["last_layer_style"], dim=-1)
        torch.testing.assert_close(model(pixels), expected, atol=1e-5, rtol=0)


def test_plain_safetensors_state_dict_loads(reference, tmp_path):
    from safetensors.torch import save_file

    _, state = reference
    save_file({k: v.contiguous() for k, v in state.items()}, str(tmp_path / "csd.safetensors"))
    model = load_csd(tmp_path / "csd.safetensors")
    images = _images(2)
    torch.testing.assert_close(csd_descriptors(model, images), csd_descriptors(_model_from(state), images))


def test_scores_end_to_end_on_a_random_model():
    torch.manual_seed(0)
    model = CSDStyleEncoder(TINY).eval()
    views = _images(3)
    scores = csd_scores(model, views[0], views)
    assert scores.shape == (3,)
    assert scores[0].item() == pytest.approx(1.0, abs=1e-5)  # the style image against itself
    assert (scores[1:] < 1 - 1e-6).all() and (scores >= -1 - 1e-6).all()
    descriptors = csd_descriptors(model, views)
    torch.testing.assert_close(descriptors.norm(dim=-1), torch.ones(3))
    with pytest.raises(ValueError, match=r"one image \[H, W, 3\]"):
        csd_scores(model, views, views)


def test_loader_errors_name_the_file_and_the_problem(reference, tmp_path, monkeypatch):
    with pytest.raises(MissingModelError, match="missing.bin.*tomg-group-umd/CSD-ViT-L"):
        load_csd(tmp_path / "missing.bin")
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    with pytest.raises(MissingModelError, match="empty-cache.*pytorch_model.bin"):
        load_csd(None)
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="garbage.bin: not a loadable CSD checkpoint"):
        load_csd(garbage)
    torch.save({"model_state_dict": Fraction(1, 3)}, tmp_path / "objects.bin")  # refused by weights_only, in our words
    with pytest.raises(ValueError) as refused:
        load_csd(tmp_path / "objects.bin")
    said = load_failure(pickle.UnpicklingError())
    assert str(refused.value) == f"{tmp_path / 'objects.bin'}: not a loadable CSD checkpoint ({said})"
    _, state = reference
    partial = {k: v for k, v in state.items() if ".resblocks.1.mlp" not in k}
    torch.save(partial, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match=r"partial.pt: not a CSD ViT checkpoint: 4 missing keys \[backbone.transformer.resblocks.1.mlp"):
        load_csd(tmp_path / "partial.pt")
    torch.save({"backbone.conv1.weight": torch.zeros(4, 3, 7, 7)}, tmp_path / "headless.pt")
    with pytest.raises(ValueError, match="headless.pt: 'backbone.positional_embedding': expected a 2-d tensor"):
        load_csd(tmp_path / "headless.pt")
