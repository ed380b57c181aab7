import pytest
import torch

from artnvg_core.losses import ssim


def brute_force_ssim(a: torch.Tensor, b: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-image SSIM in float64 from explicit window sums over a zero-padded image."""
    a, b = a.double(), b.double()
    half = size // 2
    g = torch.exp(-torch.tensor([(i - half) ** 2 for i in range(size)], dtype=torch.float64) / (2 * sigma**2))
    w2d = torch.outer(g, g) / g.sum() ** 2
    height, width = a.shape[-2:]

    def local_mean(x):
        padded = torch.nn.functional.pad(x, (half, half, half, half))
        total = torch.zeros_like(x)
        for dy in range(size):
            for dx in range(size):
                total = total + w2d[dy, dx] * padded[..., dy : dy + height, dx : dx + width]
        return total

    mu_a, mu_b = local_mean(a), local_mean(b)
    var_a = local_mean(a * a) - mu_a**2
    var_b = local_mean(b * b) - mu_b**2
    cov = local_mean(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.flatten(1).mean(1)


def _pair(seed=0, shape=(2, 3, 9, 13)):
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=gen)
    b = (a + 0.2 * torch.randn(shape, generator=gen)).clamp(0, 1)
    return a, b


def test_identical_images_give_one():
    a, _ = _pair()
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-6)
    assert torch.allclose(ssim(a, a, per_image=True), torch.ones(2), atol=1e-6)


@pytest.mark.parametrize("size, sigma", [(11, 1.5), (5, 1.0)])
def test_matches_brute_force_value_and_gradient(size, sigma):
    # 9x13 images: the 11x11 window overhangs the border everywhere, so padding is exercised.
    a, b = _pair()
    a.requires_grad_(True)
    a64 = a.detach().double().requires_grad_(True)
    ours = ssim(a, b, window_size=size, sigma=sigma, per_image=True)
    reference = brute_force_ssim(a64, b, size, sigma)
    assert torch.allclose(ours.double(), reference, atol=1e-5)
    ours.sum().backward()
    reference.sum().backward()
    assert torch.allclose(a.grad.double(), a64.grad, atol=1e-5, rtol=1e-3)
    assert ssim(a, b, window_size=size, sigma=sigma).item() == pytest.approx(reference.mean().item(), abs=1e-5)


def test_symmetric():
    a, b = _pair(1)
    assert torch.allclose(ssim(a, b, per_image=True), ssim(b, a, per_image=True), atol=1e-7)


def test_decreases_with_noise():
    gen = torch.Generator().manual_seed(2)
    image = torch.rand(1, 3, 32, 32, generator=gen)
    image = torch.nn.functional.avg_pool2d(image, 3, 1, 1)  # some structure, not pure noise
    noise = torch.randn(image.shape, generator=gen)
    values = [ssim(image, (image + level * noise).clamp(0, 1)).item() for level in (0.01, 0.05, 0.2, 0.5)]
    assert all(x > y for x, y in zip(values, values[1:])), values
    assert values[0] > 0.9 and values[-1] < 0.3


def test_low_precision_inputs_and_autocast_computed_in_float32():
    a, b = _pair(3)
    reference = ssim(a, b)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under_autocast = ssim(a, b)
    assert under_autocast.dtype == torch.float32
    assert under_autocast.item() == pytest.approx(reference.item(), abs=1e-6)
    half = ssim(a.half(), b.half())
    assert half.dtype == torch.float32
    assert half.item() == pytest.approx(reference.item(), abs=2e-3)


def test_bad_input_raises():
    a, _ = _pair()
    with pytest.raises(ValueError, match="one shape"):
        ssim(a, a[:, :, :8])
    with pytest.raises(ValueError, match="one shape"):
        ssim(a[0], a[0])
    with pytest.raises(ValueError, match="odd"):
        ssim(a, a, window_size=4)


def test_gradient_is_exactly_zero_for_identical_images():
    """Adam normalises step sizes, so even rounding noise would move parameters."""
    x = torch.rand(2, 3, 24, 20, generator=torch.Generator().manual_seed(3))
    a = x.clone().requires_grad_(True)
    (1 - ssim(a, x)).backward()
    assert torch.count_nonzero(a.grad) == 0
