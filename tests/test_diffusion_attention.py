"""Neighbouring-view self-attention and decoupled cross-attention on diffusers' Attention layer."""

import pytest
import torch
from diffusers.models.attention_processor import Attention, AttnProcessor2_0

from artnvg_core.diffusion.attention import (
    AttentionControl,
    DecoupledCrossAttention,
    NeighbourViewSelfAttention,
    attention_kwargs,
)
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)

HEADS, HEAD_DIM, WIDTH, CROSS = 2, 4, 8, 6


def _layer(cross: int | None = None) -> Attention:
    torch.manual_seed(0)
    return Attention(WIDTH, cross_attention_dim=cross, heads=HEADS, dim_head=HEAD_DIM, out_bias=True).double().eval()


def _nv(layer: Attention, x: torch.Tensor, views: int, chunk: int | None = None) -> torch.Tensor:
    layer.set_processor(NeighbourViewSelfAttention(chunk))
    return layer(x, **attention_kwargs(AttentionControl(views_per_group=views)))


def _plain(layer: Attention, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
    layer.set_processor(AttnProcessor2_0())
    return layer(x, context)


def _reference_nv(layer: Attention, x: torch.Tensor, views: int) -> torch.Tensor:
    """Brute force: for each view i, softmax(Q_i [K_1..K_N]^T / sqrt(d)) [V_1..V_N], head by head."""
    q, k, v = layer.to_q(x), layer.to_k(x), layer.to_v(x)
    out = torch.empty_like(q)
    for b in range(x.shape[0]):
        group = range(b - b % views, b - b % views + views)
        keys = torch.cat([k[j] for j in group])
        values = torch.cat([v[j] for j in group])
        for h in range(HEADS):
            s = slice(h * HEAD_DIM, (h + 1) * HEAD_DIM)
            weights = torch.softmax(q[b, :, s] @ keys[:, s].T / HEAD_DIM**0.5, dim=-1)
            out[b, :, s] = weights @ values[:, s]
    return layer.to_out[0](out)


def test_nv_matches_brute_force_and_chunking():
    layer = _layer()
    x = torch.randn(6, 5, WIDTH, dtype=torch.float64)  # 2 groups of 3 views, 5 tokens each
    expected = _reference_nv(layer, x, views=3)
    torch.testing.assert_close(_nv(layer, x, 3), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(_nv(layer, x, 3, chunk=4), expected, rtol=1e-12, atol=1e-12)


def test_single_view_equals_plain_attention():
    layer = _layer()
    x = torch.randn(4, 5, WIDTH, dtype=torch.float64)
    torch.testing.assert_close(_nv(layer, x, 1), _plain(layer, x), rtol=1e-12, atol=1e-12)
    layer.set_processor(NeighbourViewSelfAttention())
    torch.testing.assert_close(layer(x), _plain(layer, x), rtol=1e-12, atol=1e-12)  # no control = per view


def test_identical_views_give_the_per_view_result():
    layer = _layer()
    view = torch.randn(1, 5, WIDTH, dtype=torch.float64)
    out = _nv(layer, view.expand(4, -1, -1).contiguous(), 4)
    torch.testing.assert_close(out, _plain(layer, view).expand(4, -1, -1), rtol=1e-12, atol=1e-12)


def test_permuting_views_permutes_outputs():
    layer = _layer()
    x = torch.randn(5, 6, WIDTH, dtype=torch.float64)
    perm = torch.tensor([3, 0, 4, 1, 2])
    torch.testing.assert_close(_nv(layer, x[perm], 5), _nv(layer, x, 5)[perm], rtol=1e-12, atol=1e-12)


def test_groups_and_guidance_halves_never_mix():
    """Batch [uncond v1..v3, cond v1..v3]: changing the uncond half leaves the cond half untouched."""
    layer = _layer()
    x = torch.randn(6, 5, WIDTH, dtype=torch.float64)
    changed = x.clone()
    changed[:3] = torch.randn(3, 5, WIDTH, dtype=torch.float64)
    before, after = _nv(layer, x, 3), _nv(layer, changed, 3)
    assert torch.equal(before[3:], after[3:])
    assert not torch.allclose(before[:3], after[:3])
    # ... while within one group, changing one view changes every view
    changed = x.clone()
    changed[4] += 1.0
    after = _nv(layer, changed, 3)
    assert all(not torch.allclose(before[b], after[b]) for b in (3, 4, 5))


def test_nv_rejects_bad_batches():
    layer = _layer()
    with pytest.raises(ValueError, match="not a multiple of views_per_group 3"):
        _nv(layer, torch.randn(4, 5, WIDTH, dtype=torch.float64), 3)
    with pytest.raises(ValueError, match="views_per_group must be >= 1"):
        AttentionControl(views_per_group=0)


def _reference_sparse_nv(layer: Attention, x: torch.Tensor, control: AttentionControl, grid: tuple[int, int]):
    """Brute force of the approximate NV attention: view i attends to its own tokens and to its
    neighbours' tokens average-pooled over kv_downsample x kv_downsample windows of the token grid."""
    views, factor, (h, w) = control.views_per_group, control.kv_downsample, grid

    def pooled(t):  # [h*w, C] -> [ceil(h/f) * ceil(w/f), C], windows clipped at the border
        t = t.reshape(h, w, -1)
        return torch.stack([
            t[a : a + factor, b : b + factor].reshape(-1, t.shape[-1]).mean(0)
            for a in range(0, h, factor) for b in range(0, w, factor)
        ])

    q, k, v = layer.to_q(x), layer.to_k(x), layer.to_v(x)
    out = torch.empty_like(q)
    for b in range(x.shape[0]):
        first, i = b - b % views, b % views
        others = control.neighbours[i] if control.neighbours else [j for j in range(views) if j != i]
        keys = torch.cat([k[b]] + [pooled(k[first + j]) for j in others])
        values = torch.cat([v[b]] + [pooled(v[first + j]) for j in others])
        for hd in range(HEADS):
            s = slice(hd * HEAD_DIM, (hd + 1) * HEAD_DIM)
            weights = torch.softmax(q[b, :, s] @ keys[:, s].T / HEAD_DIM**0.5, dim=-1)
            out[b, :, s] = weights @ values[:, s]
    return layer.to_out[0](out)


def _control(**fields) -> dict:
    return attention_kwargs(AttentionControl(**fields))


@pytest.mark.parametrize(
    "fields, grid",
    [
        (dict(neighbours=((2,), (0,), (1,))), (3, 2)),
        (dict(kv_downsample=2, latent_size=(12, 8)), (3, 2)),  # layer at 1/4 of the latent grid
        (dict(neighbours=((1, 2), (2, 0), (0, 1)), kv_downsample=2, latent_size=(10, 6)), (5, 3)),  # odd grid
        (dict(kv_downsample=3, latent_size=(5, 3)), (5, 3)),
    ],
)
def test_approximate_nv_matches_brute_force(fields, grid):
    layer = _layer()
    layer.set_processor(NeighbourViewSelfAttention())
    x = torch.randn(6, grid[0] * grid[1], WIDTH, dtype=torch.float64)  # 2 groups of 3 views
    control = AttentionControl(views_per_group=3, **fields)
    expected = _reference_sparse_nv(layer, x, control, grid)
    torch.testing.assert_close(layer(x, **attention_kwargs(control)), expected, rtol=1e-12, atol=1e-12)


def test_all_neighbours_unpooled_is_exact_nv():
    """Listing every other view explicitly only reorders the keys: the exact NV result."""
    layer = _layer()
    layer.set_processor(NeighbourViewSelfAttention())
    x = torch.randn(8, 6, WIDTH, dtype=torch.float64)
    everyone = tuple(tuple(j for j in range(4) if j != i)[::-1] for i in range(4))
    torch.testing.assert_close(
        layer(x, **_control(views_per_group=4, neighbours=everyone)), _reference_nv(layer, x, 4), rtol=1e-12, atol=1e-12
    )


def test_nv_max_tokens_restricts_nv_to_small_layers():
    layer = _layer()
    x = torch.randn(6, 5, WIDTH, dtype=torch.float64)
    per_view, nv = _plain(layer, x), _reference_nv(layer, x, 3)
    layer.set_processor(NeighbourViewSelfAttention())
    torch.testing.assert_close(layer(x, **_control(views_per_group=3, nv_max_tokens=4)), per_view)
    torch.testing.assert_close(layer(x, **_control(views_per_group=3, nv_max_tokens=5)), nv)


@pytest.mark.parametrize(
    "fields, message",
    [
        (dict(views_per_group=3, neighbours=((1,), (0,))), "one row per view"),
        (dict(views_per_group=3, neighbours=((1,), (0, 2), (0,))), "equal length"),
        (dict(views_per_group=3, neighbours=((0,), (0,), (0,))), r"neighbours\[0\] must hold distinct views"),
        (dict(views_per_group=2, neighbours=((1,), (5,))), r"neighbours\[1\]"),
        (dict(kv_downsample=2), "latent_size is required"),
        (dict(kv_downsample=0), "kv_downsample must be >= 1"),
        (dict(nv_max_tokens=0), "nv_max_tokens must be None or >= 1"),
    ],
)
def test_bad_approximation_settings_raise(fields, message):
    with pytest.raises(ValueError, match=message):
        AttentionControl(**fields)


def test_latent_size_must_fit_the_layer():
    layer = _layer()
    layer.set_processor(NeighbourViewSelfAttention())
    with pytest.raises(ValueError, match=r"latent_size \(7, 7\) does not fit a layer of 6 tokens"):
        layer(torch.randn(4, 6, WIDTH, dtype=torch.float64), **_control(views_per_group=2, kv_downsample=2, latent_size=(7, 7)))


def _cross(kind: str | None) -> tuple[Attention, DecoupledCrossAttention]:
    layer = _layer(CROSS)
    torch.manual_seed(1)
    processor = DecoupledCrossAttention(HEADS * HEAD_DIM, CROSS, kind).double()
    layer.set_processor(processor)
    return layer, processor


def _context(text: int = 7, content: int = 2, style: int = 3) -> torch.Tensor:
    return torch.randn(2, text + content + style, CROSS, dtype=torch.float64)


@pytest.mark.parametrize("kind", ["content", "style"])
def test_decoupled_branch_matches_explicit_formula(kind):
    layer, processor = _cross(kind)
    x, context = torch.randn(2, 5, WIDTH, dtype=torch.float64), _context()
    control = AttentionControl(num_content_tokens=2, num_style_tokens=3, content_scale=0.7, style_scale=0.4)
    out = layer(x, context, **attention_kwargs(control))
    text, content, style = context[:, :7], context[:, 7:9], context[:, 9:]
    tokens, scale = (content, 0.7) if kind == "content" else (style, 0.4)

    def attend(keys, values):
        q = layer.to_q(x).unflatten(-1, (HEADS, HEAD_DIM)).transpose(1, 2)
        k, v = (t.unflatten(-1, (HEADS, HEAD_DIM)).transpose(1, 2) for t in (keys, values))
        return (torch.softmax(q @ k.transpose(-1, -2) / HEAD_DIM**0.5, -1) @ v).transpose(1, 2).flatten(2)

    mixed = attend(layer.to_k(text), layer.to_v(text)) + scale * attend(
        processor.to_k_ip(tokens), processor.to_v_ip(tokens)
    )
    torch.testing.assert_close(out, layer.to_out[0](mixed), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["content", "style", None])
def test_zero_scale_or_text_only_equals_plain_text_attention(kind):
    layer, _ = _cross(kind)
    x, context = torch.randn(2, 5, WIDTH, dtype=torch.float64), _context()
    control = AttentionControl(num_content_tokens=2, num_style_tokens=3, content_scale=0.0, style_scale=0.0)
    assert torch.equal(layer(x, context, **attention_kwargs(control)), _plain(layer, x, context[:, :7]))


@pytest.mark.parametrize("kind", ["content", "style", None])
def test_each_processor_reads_only_its_tokens(kind):
    layer, _ = _cross(kind)
    x, context = torch.randn(2, 5, WIDTH, dtype=torch.float64), _context()
    control = attention_kwargs(
        AttentionControl(num_content_tokens=2, num_style_tokens=3, content_scale=1.0, style_scale=1.0)
    )
    base = layer(x, context, **control)
    for part, tokens in (("content", slice(7, 9)), ("style", slice(9, 12))):
        perturbed = context.clone()
        perturbed[:, tokens] += 1.0
        assert torch.equal(layer(x, perturbed, **control), base) == (part != kind)


def test_cross_attention_rejects_short_context_and_masks():
    layer, _ = _cross("style")
    x = torch.randn(2, 5, WIDTH, dtype=torch.float64)
    with pytest.raises(ValueError, match="cannot hold 4 content \\+ 4 style tokens"):
        layer(x, _context(0, 4, 4), **attention_kwargs(AttentionControl(num_content_tokens=4, num_style_tokens=4)))
    with pytest.raises(ValueError, match="attention masks"):
        layer(x, _context(), attention_mask=torch.zeros(2, 1, 12))
    with pytest.raises(ValueError, match="image_tokens must be one of"):
        DecoupledCrossAttention(8, 6, "colour")
