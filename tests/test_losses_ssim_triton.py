"""The fused SSIM kernels (on a CUDA GPU, else in Triton's interpreter on the CPU) against the float64 brute
force and the PyTorch SSIM: values, both inputs' gradients, strided and half inputs, exact zero gradient at
identity."""

import pytest
import torch
from test_losses_ssim import brute_force_ssim

from artnvg_core.losses.ssim import C1, C2, ssim, window_on
from artnvg_core.losses.ssim_triton import TILE_W, fused_ssim


DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def fused(a, b, size=11, sigma=1.5, per_image=False):
    """The fused SSIM of ``a, b`` computed on DEVICE, its value and gradients back on the CPU."""
    value = fused_ssim(a.to(DEVICE), b.to(DEVICE), window_on(size, sigma, DEVICE), C1, C2, per_image)
    return value.cpu()


def pair(shape, seed=0):
    generator = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=generator)
    return a, (a + 0.2 * torch.randn(shape, generator=generator)).clamp(0, 1)


@pytest.mark.slow
@pytest.mark.parametrize("size, sigma, per_image", [(11, 1.5, True), (5, 1.0, False)])
def test_value_and_both_gradients_match_brute_force(size, sigma, per_image):
    # 2 images x 1 channel of 9 x (TILE_W + 3): the window overhangs every border, two tiles a row
    a, b = pair((2, 1, 9, TILE_W + 3))
    a, b = a.requires_grad_(True), b.requires_grad_(True)
    a64, b64 = (x.detach().double().requires_grad_(True) for x in (a, b))
    weights = torch.tensor([1.0, -2.5])  # a different gradient per image
    ours = fused(a, b, size, sigma, per_image)
    reference = brute_force_ssim(a64, b64, size, sigma)
    reference = reference if per_image else reference.mean()
    torch.testing.assert_close(ours.double(), reference, atol=1e-6, rtol=0)
    ((ours * weights).sum() if per_image else ours).backward()
    ((reference * weights).sum() if per_image else reference).backward()
    torch.testing.assert_close(a.grad.double(), a64.grad, atol=1e-6, rtol=1e-4)
    torch.testing.assert_close(b.grad.double(), b64.grad, atol=1e-6, rtol=1e-4)


def test_permuted_half_renders_as_the_finetune_gives_them():
    """[B, H, W, 3] renders permuted to [B, 3, H, W] (channels-last strides), a half target without gradient."""
    render, target = pair((1, 7, 11, 3), seed=1)
    render = render.requires_grad_(True)
    got = fused(render.permute(0, 3, 1, 2), target.half().permute(0, 3, 1, 2))
    got.backward()
    reference_render = render.detach().clone().requires_grad_(True)
    want = ssim(reference_render.permute(0, 3, 1, 2), target.half().permute(0, 3, 1, 2))
    want.backward()
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
    torch.testing.assert_close(render.grad, reference_render.grad, atol=1e-7, rtol=1e-4)


def test_identical_images_give_one_and_exactly_zero_gradient():
    x = torch.rand(1, 2, 10, 12, generator=torch.Generator().manual_seed(3))
    a = x.clone().requires_grad_(True)
    value = fused(a, x)
    (1 - value).backward()
    assert value.item() == pytest.approx(1.0, abs=1e-6)
    assert torch.count_nonzero(a.grad) == 0


def test_without_gradients_the_value_alone():
    a, b = pair((1, 1, 6, 9), seed=4)
    with torch.no_grad():
        torch.testing.assert_close(fused(a.requires_grad_(True), b), ssim(a, b), atol=1e-6, rtol=0)


@pytest.mark.cuda
def test_cuda_ssim_is_the_fused_one_and_matches_the_float64_brute_force():
    a, b = pair((2, 3, 70, 90), seed=5)
    a_cuda = a.cuda().requires_grad_(True)
    value = ssim(a_cuda, b.cuda(), per_image=True)
    assert "FusedSSIM" in type(value.grad_fn).__name__
    a64 = a.double().requires_grad_(True)
    reference = brute_force_ssim(a64, b)
    torch.testing.assert_close(value.double().cpu(), reference, atol=1e-6, rtol=0)
    value.sum().backward()
    reference.sum().backward()
    torch.testing.assert_close(a_cuda.grad.double().cpu(), a64.grad, atol=1e-6, rtol=1e-4)


def test_the_warmups_are_the_launches_of_the_finetunes_ssim(monkeypatch):
    from artnvg_core.losses.ssim_triton import warmups

    from triton_launches import record_launches, warmed

    launched = record_launches(monkeypatch)
    a, b = pair((1, 3, 16, 9))  # 16 rows: specialized as a multiple of 16
    a = a.to(DEVICE).requires_grad_(True)  # the render; its target needs no gradient
    (1 - fused_ssim(a, b.to(DEVICE), window_on(11, 1.5, DEVICE), C1, C2)).backward()
    assert len(launched) == 2 and launched == warmed(warmups(DEVICE, 3, 16, 9))
