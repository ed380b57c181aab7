"""The attention maths on raw projected tensors, against head-by-head brute force in float64."""

import pytest
import torch

from artnvg_core.diffusion.attention_math import attend, decoupled_attention, neighbour_view_attention

HEADS, DIM = 2, 3


def _softmax_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[Lq, heads*D], [Lk, heads*D] -> [Lq, heads*D], one head at a time."""
    out = torch.empty_like(q)
    for h in range(HEADS):
        s = slice(h * DIM, (h + 1) * DIM)
        out[:, s] = torch.softmax(q[:, s] @ k[:, s].T / DIM**0.5, dim=-1) @ v[:, s]
    return out


def _qkv(batch: int, length: int = 4) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(batch)
    return [torch.randn(batch, length, HEADS * DIM, generator=generator, dtype=torch.float64) for _ in range(3)]


@pytest.mark.parametrize("views", [1, 2, 3])
def test_each_view_attends_to_its_whole_group(views):
    q, k, v = _qkv(6)
    expected = torch.stack([
        _softmax_attention(q[b], k[b - b % views : b - b % views + views].flatten(0, 1),
                           v[b - b % views : b - b % views + views].flatten(0, 1)) for b in range(6)])
    torch.testing.assert_close(neighbour_view_attention(q, k, v, HEADS, views), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(neighbour_view_attention(q, k, v, HEADS, views, query_chunk=3), expected,
                               rtol=1e-12, atol=1e-12)


def test_chosen_neighbours_only():
    q, k, v = _qkv(3)
    rows = ((2,), (0,), (1,))
    expected = torch.stack([_softmax_attention(q[i], torch.cat([k[i], k[rows[i][0]]]), torch.cat([v[i], v[rows[i][0]]]))
                            for i in range(3)])
    torch.testing.assert_close(neighbour_view_attention(q, k, v, HEADS, 3, neighbours=rows), expected,
                               rtol=1e-12, atol=1e-12)


def test_bad_groups_raise():
    q, k, v = _qkv(4)
    with pytest.raises(ValueError, match="batch 4 is not a multiple of 3 views"):
        neighbour_view_attention(q, k, v, HEADS, 3)
    with pytest.raises(ValueError, match="needs latent_size"):
        neighbour_view_attention(q, k, v, HEADS, 2, kv_downsample=2)
    with pytest.raises(ValueError, match=r"neighbours\[0\]"):
        neighbour_view_attention(q, k, v, HEADS, 2, neighbours=((0,), (0,)))


def test_decoupled_attention_adds_scaled_branches():
    q, k, v = _qkv(2)
    k1, v1 = _qkv(2, length=3)[:2]
    k2, v2 = _qkv(2, length=5)[1:]
    out = decoupled_attention(q, k, v, HEADS, [(k1, v1, 0.7), (k2, v2, 0.0), (k2[:, :0], v2[:, :0], 2.0)])
    expected = torch.stack([_softmax_attention(q[b], k[b], v[b]) + 0.7 * _softmax_attention(q[b], k1[b], v1[b])
                            for b in range(2)])
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(decoupled_attention(q, k, v, HEADS), attend(q, k, v, HEADS), rtol=0, atol=0)
