import pytest
import torch

from artnvg_core.losses import NNFMLoss, load_vgg, nearest_style_indices, shrink_to_max_side, style_image_features
from artnvg_core.losses.nnfm import default_chunk_elements
from artnvg_core.progress import Cancelled

GROUPS = (("a1", "a2"), ("b1",))


def random_feats(seed, batch, size_a, size_b) -> dict:
    """ReLU-like features: group a = layers a1 (5 ch) + a2 (7 ch) at size_a, group b = b1 (4 ch) at size_b."""
    gen = torch.Generator().manual_seed(seed)
    return {
        "a1": torch.rand(batch, 5, *size_a, generator=gen),
        "a2": torch.rand(batch, 7, *size_a, generator=gen),
        "b1": torch.rand(batch, 4, *size_b, generator=gen),
    }


def brute_force_nnfm(render: dict, style: dict, groups) -> torch.Tensor:
    """Float64 NNFM: full cosine matrix per group (layers concatenated), max per render position."""
    total = torch.zeros((), dtype=torch.float64)
    for group in groups:
        r = torch.cat([render[n].double() for n in group], 1)
        s = torch.cat([style[n].double() for n in group], 1)
        r = r.permute(0, 2, 3, 1).reshape(-1, r.shape[1])
        s = s.permute(0, 2, 3, 1).reshape(-1, s.shape[1])
        cos = (r / r.norm(dim=1, keepdim=True)) @ (s / s.norm(dim=1, keepdim=True)).T
        total = total + (1 - cos.max(dim=1).values).mean()
    return total


def test_matches_brute_force_value_and_gradient():
    render = {k: v.requires_grad_(True) for k, v in random_feats(0, 2, (4, 5), (3, 2)).items()}
    render64 = {k: v.detach().double().requires_grad_(True) for k, v in render.items()}
    style = random_feats(1, 1, (6, 3), (2, 4))
    loss = NNFMLoss(style, GROUPS)(render)
    reference = brute_force_nnfm(render64, style, GROUPS)
    assert loss.dtype == torch.float32
    assert loss.item() == pytest.approx(reference.item(), abs=1e-6)
    loss.backward()
    reference.backward()
    for name in render:
        assert torch.allclose(render[name].grad.double(), render64[name].grad, atol=1e-6), name


def test_several_style_images_pool_their_positions():
    render = random_feats(2, 1, (3, 3), (2, 2))
    style = random_feats(3, 3, (2, 4), (3, 1))
    loss = NNFMLoss(style, GROUPS)(render)
    assert loss.item() == pytest.approx(brute_force_nnfm(render, style, GROUPS).item(), abs=1e-6)


def test_zero_when_render_is_the_style_image():
    feats = random_feats(4, 1, (5, 6), (3, 3))
    assert NNFMLoss(feats, GROUPS)(feats).item() == pytest.approx(0.0, abs=1e-6)


def test_zero_on_real_vgg_features_of_the_style_image_itself(shared_data):
    from test_losses_vgg import load_style

    vgg = load_vgg()
    layers = ("relu3_1", "relu3_2", "relu3_3")
    hokusai = load_style(shared_data, "hokusai", size=64)
    loss = NNFMLoss(style_image_features(vgg, hokusai, layers))
    assert loss(vgg(hokusai, layers)).item() == pytest.approx(0.0, abs=1e-5)
    assert loss(vgg(load_style(shared_data, "stripes", size=64), layers)).item() > 0.1


@pytest.mark.parametrize("budget", [1, 7, 30, 10**9])
def test_chunked_matches_unchunked(budget):
    gen = torch.Generator().manual_seed(5)
    render = torch.nn.functional.normalize(torch.randn(23, 6, generator=gen), dim=1)
    style = torch.nn.functional.normalize(torch.randn(17, 6, generator=gen), dim=1)
    style[9] = style[3]  # a tie: the lowest index wins, as in an unchunked argmax
    render[4] = style[3]
    expected = (render @ style.T).argmax(dim=1)
    assert expected[4] == 3
    assert torch.equal(nearest_style_indices(render, style, budget), expected)

    feats = random_feats(6, 2, (4, 4), (3, 3))
    style_feats = random_feats(7, 1, (5, 4), (4, 2))
    small = NNFMLoss(style_feats, GROUPS, max_chunk_elements=budget)(feats)
    large = NNFMLoss(style_feats, GROUPS, max_chunk_elements=10**9)(feats)
    assert small.item() == large.item()


def test_the_search_asks_to_stop_before_each_chunk_of_rows():
    """The search takes seconds at 512 px on a CPU: a stop ends it at the next chunk, in NNFMLoss's too."""
    gen = torch.Generator().manual_seed(5)
    render = torch.nn.functional.normalize(torch.randn(23, 6, generator=gen), dim=1)
    style = torch.nn.functional.normalize(torch.randn(17, 6, generator=gen), dim=1)
    asked = []
    nearest_style_indices(render, style, 17 * 5, should_stop=lambda: asked.append(1) or False)
    assert len(asked) == 5  # 23 rows, 5 a chunk
    asked.clear()
    with pytest.raises(Cancelled):
        nearest_style_indices(render, style, 17 * 5, should_stop=lambda: asked.append(1) or len(asked) == 3)
    assert len(asked) == 3
    with pytest.raises(Cancelled):
        NNFMLoss(random_feats(7, 1, (5, 4), (4, 2)), GROUPS)(random_feats(6, 2, (4, 4), (3, 3)), should_stop=lambda: True)


def test_on_a_cpu_the_search_holds_2_to_the_23_similarities_a_chunk_unless_told():
    """64x64 positions against 64x64 (2^24) in two chunks of rows, a stop asked before each; the 4x3 group in one."""
    asked = []
    NNFMLoss(random_feats(7, 1, (64, 64), (4, 3)), GROUPS)(random_feats(6, 1, (64, 64), (4, 3)),
                                                           should_stop=lambda: asked.append(1) or False)
    assert len(asked) == 3
    assert default_chunk_elements(torch.device("cuda", 0)) == 2**26


def test_zero_feature_vectors_give_finite_loss_and_gradient():
    render = random_feats(8, 1, (3, 3), (2, 2))
    render["a1"][0, :, 1, 1] = 0
    render["a2"][0, :, 1, 1] = 0
    render = {k: v.requires_grad_(True) for k, v in render.items()}
    style = random_feats(9, 1, (3, 3), (2, 2))
    style["b1"][0, :, 0, 0] = 0
    loss = NNFMLoss(style, GROUPS)(render)
    loss.backward()
    assert torch.isfinite(loss)
    assert all(torch.isfinite(v.grad).all() for v in render.values())
    # The zero position has cosine 0 with every style feature: it contributes 1 / 9 to group a.
    assert loss.item() >= 1.0 / 9


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_low_precision_close_to_float32(dtype):
    render = random_feats(10, 1, (6, 6), (4, 4))
    style = random_feats(11, 1, (6, 6), (4, 4))
    nnfm = NNFMLoss(style, GROUPS)
    reference = nnfm(render).item()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert nnfm(render).item() == pytest.approx(reference, abs=1e-6)
    low = {k: v.to(dtype).requires_grad_(True) for k, v in render.items()}
    loss = nnfm(low)
    assert loss.dtype == torch.float32
    assert loss.item() == pytest.approx(reference, abs=0.02)
    loss.backward()
    assert all(v.grad.dtype == dtype and torch.isfinite(v.grad).all() for v in low.values())


def test_bad_features_raise():
    style = random_feats(12, 1, (3, 3), (2, 2))
    nnfm = NNFMLoss(style, GROUPS)
    render = random_feats(13, 1, (3, 3), (2, 2))
    with pytest.raises(ValueError, match="b1"):
        nnfm({k: v for k, v in render.items() if k != "b1"})
    with pytest.raises(ValueError, match="channels"):
        nnfm({**render, "b1": torch.rand(1, 3, 2, 2)})
    with pytest.raises(ValueError, match="equal B, h, w"):
        NNFMLoss({**style, "a2": torch.rand(1, 7, 4, 3)}, GROUPS)
    with pytest.raises(ValueError, match="layer_groups"):
        NNFMLoss(style, ())


def test_style_image_is_shrunk_to_max_side_and_never_enlarged():
    seen = []

    def extractor(image, layers):
        seen.append(tuple(image.shape))
        return {name: image * 1.0 for name in layers}

    image = torch.rand(1, 3, 40, 100, requires_grad=True)
    feats = style_image_features(extractor, image, ["x"], max_side=50)
    style_image_features(extractor, image, ["x"], max_side=500)
    style_image_features(extractor, image, ["x"], max_side=None)
    assert seen == [(1, 3, 20, 50), (1, 3, 40, 100), (1, 3, 40, 100)]
    assert not feats["x"].requires_grad
    assert torch.allclose(feats["x"][0, :, 0, 0], image[0, :, :2, :2].mean(dim=(1, 2)))
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        style_image_features(extractor, image[0], ["x"])


def test_halving_equals_arfs_bilinear_half_and_gradients_flow():
    """ARF feeds VGG ``interpolate(render, scale_factor=0.5, mode="bilinear")``: for a factor of two that
    is a 2x2 average, which is what shrinking a 64 x 48 image to a long side of 32 must give."""
    image = torch.rand(2, 3, 48, 64, dtype=torch.float64, requires_grad=True)
    shrunk = shrink_to_max_side(image, 32)
    arf = torch.nn.functional.interpolate(image, scale_factor=0.5, mode="bilinear")
    assert shrunk.shape == (2, 3, 24, 32)
    torch.testing.assert_close(shrunk, arf, rtol=0, atol=1e-15)
    shrunk.sum().backward()
    torch.testing.assert_close(image.grad, torch.full_like(image, 0.25))
    assert shrink_to_max_side(image, 64) is image and shrink_to_max_side(image, None) is image
    assert shrink_to_max_side(torch.rand(1, 3, 5, 300), 30).shape == (1, 3, 1, 30)  # never below one pixel


@pytest.mark.parametrize("precision, tolerance", [("fp32", 1e-6), ("tf32", 1e-6), ("bf16", 2**-7)])
def test_search_precision_picks_a_match_within_its_rounding_of_the_best(precision, tolerance):
    """Against the float64 brute force on ReLU-like features of VGG's relu3 width (768 = 3 x 256): every
    match the search picks has a true cosine within ``tolerance`` of the best (on the CPU "tf32" is
    float32), every position whose best match leads the second best by more than that is matched to the
    best itself, and the loss on the chosen matches equals the float64 loss on the same matches (the
    search changes which match, never how the loss is computed)."""
    gen = torch.Generator().manual_seed(14)
    render = torch.rand(1, 768, 24, 20, generator=gen).clamp_min(0.3) - 0.3
    style = torch.rand(1, 768, 30, 16, generator=gen).clamp_min(0.3) - 0.3
    cos = brute_force_cosines(render, style)
    chosen = nearest_style_indices(_unit(render), _unit(style), 2**12, precision)
    best = cos.max(dim=1).values
    picked = cos.gather(1, chosen[:, None])[:, 0]
    assert float((best - picked).max()) <= tolerance
    top2 = cos.topk(2, dim=1).values
    clear = top2[:, 0] - top2[:, 1] > tolerance
    assert clear.sum() > 10 and torch.equal(chosen[clear], cos.argmax(dim=1)[clear])
    loss = NNFMLoss({"a": style}, (("a",),), precision=precision)({"a": render})
    assert loss.item() == pytest.approx(float((1 - picked).mean()), abs=1e-6)
    with pytest.raises(ValueError, match="precision"):
        NNFMLoss({"a": style}, (("a",),), precision="fp16")


def _unit(features: torch.Tensor) -> torch.Tensor:
    rows = features.permute(0, 2, 3, 1).reshape(-1, features.shape[1])
    return torch.nn.functional.normalize(rows, dim=1)


def brute_force_cosines(render: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
    """Float64 cosine of every render position [N] with every style position [M]: [N, M]."""
    return _unit(render.double()) @ _unit(style.double()).T
