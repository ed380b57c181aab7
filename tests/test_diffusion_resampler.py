"""Perceiver Resampler: released parameter names and shapes, maths against a brute-force reference."""

import math

import pytest
import torch

from artnvg_core.diffusion.resampler import PerceiverResampler, ResamplerConfig, resampler_config_from_state_dict
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)


def _released_names(depth: int) -> set[str]:
    """IP-Adapter Plus / CSGO Resampler parameter names, written out by hand."""
    names = {
        "latents",
        "proj_in.weight",
        "proj_in.bias",
        "proj_out.weight",
        "proj_out.bias",
        "norm_out.weight",
        "norm_out.bias",
    }
    for i in range(depth):
        names |= {
            f"layers.{i}.0.{n}"
            for n in (
                "norm1.weight",
                "norm1.bias",
                "norm2.weight",
                "norm2.bias",
                "to_q.weight",
                "to_kv.weight",
                "to_out.weight",
            )
        }
        names |= {f"layers.{i}.1.0.weight", f"layers.{i}.1.0.bias", f"layers.{i}.1.1.weight", f"layers.{i}.1.3.weight"}
    return names


def test_csgo_size_has_released_names_and_shapes():
    with torch.device("meta"):
        resampler = PerceiverResampler(ResamplerConfig(num_queries=32))
    state = resampler.state_dict()
    assert set(state) == _released_names(4)
    assert state["latents"].shape == (1, 32, 2048)
    assert state["proj_in.weight"].shape == (2048, 1664)
    assert state["layers.0.0.to_q.weight"].shape == (768, 2048)
    assert state["layers.0.0.to_kv.weight"].shape == (1536, 2048)
    assert state["layers.0.0.to_out.weight"].shape == (2048, 768)
    assert state["layers.3.1.1.weight"].shape == (8192, 2048)
    assert state["layers.3.1.3.weight"].shape == (2048, 8192)
    assert resampler_config_from_state_dict(state) == resampler.config


def _layer_norm(x, weight, bias):
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + 1e-5) * weight + bias


def _reference(state: dict, features: torch.Tensor, config: ResamplerConfig) -> torch.Tensor:
    """Perceiver resampler written out with explicit loops over heads, float64."""
    s = {k: v.double() for k, v in state.items()}
    x = features.double() @ s["proj_in.weight"].T + s["proj_in.bias"]
    latents = s["latents"].expand(x.shape[0], -1, -1)
    gelu = torch.nn.functional.gelu
    for i in range(config.depth):
        p = f"layers.{i}."
        xn = _layer_norm(x, s[p + "0.norm1.weight"], s[p + "0.norm1.bias"])
        ln = _layer_norm(latents, s[p + "0.norm2.weight"], s[p + "0.norm2.bias"])
        q = ln @ s[p + "0.to_q.weight"].T
        kv = torch.cat([xn, ln], 1) @ s[p + "0.to_kv.weight"].T
        k, v = kv[..., : kv.shape[-1] // 2], kv[..., kv.shape[-1] // 2 :]
        d = config.dim_head
        heads = []
        for h in range(config.heads):
            qh, kh, vh = (t[..., h * d : (h + 1) * d] for t in (q, k, v))
            weights = torch.softmax(qh @ kh.transpose(1, 2) / math.sqrt(d), dim=-1)
            heads.append(weights @ vh)
        latents = torch.cat(heads, -1) @ s[p + "0.to_out.weight"].T + latents
        hidden = _layer_norm(latents, s[p + "1.0.weight"], s[p + "1.0.bias"]) @ s[p + "1.1.weight"].T
        latents = gelu(hidden) @ s[p + "1.3.weight"].T + latents
    out = latents @ s["proj_out.weight"].T + s["proj_out.bias"]
    return _layer_norm(out, s["norm_out.weight"], s["norm_out.bias"])


def test_forward_matches_reference():
    config = ResamplerConfig(
        num_queries=3, embedding_dim=10, dim=12, output_dim=14, depth=2, heads=3, dim_head=4, ff_mult=2
    )
    torch.manual_seed(0)
    resampler = PerceiverResampler(config).double()
    with torch.no_grad():
        for param in resampler.parameters():  # non-trivial LayerNorm affine parameters too
            param.add_(0.1 * torch.randn_like(param))
    features = torch.randn(2, 7, 10, dtype=torch.float64)
    out = resampler(features)
    assert out.shape == (2, 3, 14)
    torch.testing.assert_close(out, _reference(resampler.state_dict(), features, config), rtol=1e-10, atol=1e-10)


def test_bad_input_and_bad_state_raise():
    resampler = PerceiverResampler(
        ResamplerConfig(num_queries=2, embedding_dim=6, dim=8, output_dim=8, depth=1, heads=2, dim_head=4)
    )
    with pytest.raises(ValueError, match=r"\[B, T, 6\]"):
        resampler(torch.zeros(1, 3, 5))
    state = resampler.state_dict()
    del state["latents"]
    with pytest.raises(ValueError, match="'latents' is missing"):
        resampler_config_from_state_dict(state, dim_head=4)
    state = resampler.state_dict()
    with pytest.raises(ValueError, match="not a multiple of dim_head"):
        resampler_config_from_state_dict(state, dim_head=3)
