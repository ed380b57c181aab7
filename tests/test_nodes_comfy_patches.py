"""The pack's ComfyUI patches called as ComfyUI calls them, without ComfyUI: the attention patches against the
core's maths applied to each guidance chunk alone, in float64; the low-VRAM feed-forward against the layers
run on the whole batch."""

import pytest
import torch
from torch import nn

from artnvg_core.diffusion.attention_math import attend, neighbour_view_attention
from artnvg_core.diffusion.csgo import ImageTokens
from nodes.comfy_patches import (
    CONTENT_TOKENS,
    VIEW_CENTERS,
    CSGOState,
    ImageTokenPatch,
    NeighbourViewPatch,
    OneSampleAtATime,
    transformer_layers,
)

HEADS, WIDTH, VIEWS, TOKENS = 2, 6, 3, 4


def _qkv(chunks: int, generator: torch.Generator, length: int = TOKENS) -> list[torch.Tensor]:
    return [torch.randn(chunks * VIEWS, length, WIDTH, generator=generator, dtype=torch.float64) for _ in range(3)]


def _options(cond_or_uncond, **extra) -> dict:
    return {"n_heads": HEADS, "cond_or_uncond": cond_or_uncond, "original_shape": [VIEWS, 4, 2, 2], **extra}


@pytest.mark.parametrize("cond_or_uncond", [[1, 0], [0, 1], [0]])
def test_nv_patch_attends_within_each_guidance_chunk(cond_or_uncond):
    q, k, v = _qkv(len(cond_or_uncond), torch.Generator().manual_seed(0))
    out = NeighbourViewPatch()(q, k, v, _options(cond_or_uncond))
    chunks = [neighbour_view_attention(*(t[i * VIEWS:(i + 1) * VIEWS] for t in (q, k, v)), HEADS, VIEWS)
              for i in range(len(cond_or_uncond))]
    torch.testing.assert_close(out, torch.cat(chunks), rtol=1e-12, atol=1e-12)
    per_view = attend(q, k, v, HEADS)
    assert (out - per_view).abs().max() > 1e-3  # the views do see each other


def test_nv_patch_lowest_level_and_nearest_views():
    q, k, v = _qkv(2, torch.Generator().manual_seed(1))
    lowest = NeighbourViewPatch(lowest_level_factor=2)  # latent 2x2 -> 1 token at the lowest level: 4 tokens skip NV
    torch.testing.assert_close(lowest(q, k, v, _options([1, 0])), attend(q, k, v, HEADS), rtol=1e-12, atol=1e-12)
    centers = torch.tensor([[0.0, 0, 0], [5, 0, 0], [1, 0, 0]])
    nearest = NeighbourViewPatch(nearest=1)(q, k, v, _options([1, 0], **{VIEW_CENTERS: centers}))
    rows = ((2,), (2,), (0,))
    expected = torch.cat([neighbour_view_attention(*(t[i * VIEWS:(i + 1) * VIEWS] for t in (q, k, v)), HEADS, VIEWS,
                                                   neighbours=rows) for i in range(2)])
    torch.testing.assert_close(nearest, expected, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="nearest_views 1 needs the camera centres"):
        NeighbourViewPatch(nearest=1)(q, k, v, _options([1, 0]))


def _state(generator) -> CSGOState:
    style = ImageTokens(torch.randn(1, 2, 5, generator=generator, dtype=torch.float64),
                        torch.randn(1, 2, 5, generator=generator, dtype=torch.float64))
    return CSGOState(style, style_scale=0.7, content_scale=1.3, content_routing="paper")


def _expected(q, k, v, weights, tokens: ImageTokens, scale: float, cond_or_uncond) -> torch.Tensor:
    """Text attention plus each view's own decoupled image attention, row by row, in float64."""
    expected = attend(q, k, v, HEADS).clone()
    for chunk, half in enumerate(tokens.uncond if h == 1 else tokens.cond for h in cond_or_uncond):
        for view in range(VIEWS):
            row = chunk * VIEWS + view
            image = half[min(view, len(half) - 1)]
            k_ip, v_ip = image @ weights[0].T, image @ weights[1].T
            expected[row] += scale * attend(q[row:row + 1], k_ip[None], v_ip[None], HEADS)[0]
    return expected


def _content(generator) -> ImageTokens:
    return ImageTokens(torch.randn(VIEWS, 3, 5, generator=generator, dtype=torch.float64),
                       torch.randn(VIEWS, 3, 5, generator=generator, dtype=torch.float64))


@pytest.mark.parametrize("kind", ["style", "content"])
def test_image_token_patch_gives_each_half_its_tokens(kind):
    generator = torch.Generator().manual_seed(2)
    state = _state(generator)
    weights = [torch.randn(WIDTH, 5, generator=generator, dtype=torch.float64) for _ in range(2)]
    content = _content(generator)
    q, k, v = _qkv(2, generator)
    out = ImageTokenPatch(*weights, kind, state)(q, k, v, _options([1, 0], **{CONTENT_TOKENS: content}))
    tokens, scale = (state.style, 0.7) if kind == "style" else (content, 1.3)
    torch.testing.assert_close(out, _expected(q, k, v, weights, tokens, scale, [1, 0]), rtol=1e-12, atol=1e-12)


def test_image_token_patch_follows_each_groups_tokens_and_batch_layout():
    """The state builds each token batch once (on the queries' device) and reuses it: a new group's content
    tokens, the halves as separate batches, and back, each give that call's own result."""
    generator = torch.Generator().manual_seed(4)
    state = _state(generator)
    weights = [torch.randn(WIDTH, 5, generator=generator, dtype=torch.float64) for _ in range(2)]
    first, second = _content(generator), _content(generator)
    patch = ImageTokenPatch(*weights, "content", state)
    for tokens, cond_or_uncond in ((first, [1, 0]), (second, [1, 0]), (second, [0]), (second, [1]), (first, [1, 0])):
        q, k, v = _qkv(len(cond_or_uncond), generator)
        out = patch(q, k, v, _options(cond_or_uncond, **{CONTENT_TOKENS: tokens}))
        torch.testing.assert_close(out, _expected(q, k, v, weights, tokens, 1.3, cond_or_uncond), rtol=1e-12, atol=1e-12)


def test_content_patch_without_content_tokens_says_what_to_do():
    generator = torch.Generator().manual_seed(3)
    patch = ImageTokenPatch(torch.zeros(WIDTH, 5), torch.zeros(WIDTH, 5), "content", _state(generator))
    with pytest.raises(ValueError, match="content_routing 'paper' needs each view's content tokens"):
        patch(*_qkv(1, generator), _options([0]))


class _Transformer(nn.Module):
    def __init__(self, depth: int):
        super().__init__()
        self.transformer_blocks = nn.ModuleList(nn.Identity() for _ in range(depth))


def test_transformer_layers_follow_the_released_order_and_diffusers_names():
    """A UNet laid out as ComfyUI's SDXL (2 blocks per level, attention at levels 1 and 2, depths 1 and 2)."""
    unet = nn.Module()
    unet.num_res_blocks = [2, 2, 2]
    level = {4: 1, 5: 1, 7: 2, 8: 2}
    unet.input_blocks = nn.ModuleList(
        nn.Sequential(nn.Identity(), _Transformer(level[i])) if i in level else nn.Sequential(nn.Identity())
        for i in range(9))
    unet.middle_block = nn.Sequential(nn.Identity(), _Transformer(2), nn.Identity())
    unet.output_blocks = nn.ModuleList(
        nn.Sequential(nn.Identity(), _Transformer(2 if i < 3 else 1)) if i < 6 else nn.Sequential(nn.Identity())
        for i in range(9))
    layers = transformer_layers(unet)
    assert [(x.block, x.number, x.transformer) for x in layers][:3] == [("input", 4, 0), ("input", 5, 0),
                                                                          ("input", 7, 0)]
    assert [x.block for x in layers] == ["input"] * 6 + ["output"] * 9 + ["middle"] * 2
    assert layers[2].diffusers_name == "down_blocks.2.attentions.0.transformer_blocks.0"
    assert layers[6].diffusers_name == "up_blocks.0.attentions.0.transformer_blocks.0"
    assert layers[13].diffusers_name == "up_blocks.1.attentions.1.transformer_blocks.0"
    assert layers[-1].path == "middle_block.1.transformer_blocks.1"
    assert layers[-1].diffusers_name == "mid_block.attentions.0.transformer_blocks.1"


def test_one_sample_at_a_time_equals_the_batch_and_keeps_the_layers_names():
    """ComfyUI's FeedForward.net (projection and GELU, dropout, projection) on a batch of 5 samples: equal to
    the batch run, each layer sees one sample, and the parameters keep their names (weight patches key them)."""
    torch.manual_seed(0)
    net = nn.Sequential(nn.Sequential(nn.Linear(6, 24, dtype=torch.float64), nn.GELU()), nn.Dropout(0.0),
                        nn.Linear(24, 6, dtype=torch.float64))
    x = torch.randn(5, 7, 6, dtype=torch.float64)
    expected = net(x)
    patched = OneSampleAtATime(*net)
    seen = []
    patched[0].register_forward_hook(lambda module, args, out: seen.append(args[0].shape[0]))
    torch.testing.assert_close(patched(x), expected, rtol=0, atol=1e-12)  # the GEMMs block by batch size
    assert seen == [1] * 5
    assert list(patched.state_dict()) == list(net.state_dict()) and patched[2] is net[2]
