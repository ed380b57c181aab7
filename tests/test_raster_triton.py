"""Triton backend (raster/triton_backend.py): its kernels, forward and backward, against the float64
references on the hard cases. Without a GPU they run in Triton's CPU interpreter (TRITON_INTERPRET=1,
set here before the kernels are first imported); tests marked ``cuda`` run them compiled on a GPU
(docs/cuda_run.md records the last run)."""

import dataclasses
import os

import pytest
import torch

if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")

from artnvg_core.raster import choose_backend, prepare_backend, render  # noqa: E402
from artnvg_core.raster.projection import project  # noqa: E402
from artnvg_core.raster.torch_backend import rasterize  # noqa: E402
from artnvg_core.scene import GaussianScene  # noqa: E402

from raster_scenes import EYES, hard_cases, hard_scene, make_cameras, parity  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
HARD = {case.name: case for case in hard_cases()}
# float32 compositing against float64 (thresholds at 1/255 and T = 1e-4 decided a rounding apart):
# the Triton kernels measured 121-146 dB and gradient errors of 1e-6..1e-5 on every case
MIN_PSNR, MAX_GRAD_ERROR = 120.0, 1e-4


@pytest.mark.parametrize("name", list(HARD))
def test_hard_cases_agree_with_float64_forward_and_backward(name):
    result = parity(HARD[name], "triton", DEVICE)
    assert result["finite"] and result["psnr"] >= MIN_PSNR and result["grad_error"] <= MAX_GRAD_ERROR, result


def _composite_inputs(seed=0, n=40, width=40, height=24):
    """One camera's projection of a hard scene and leaf tensors (means2d, conics, opacities,
    features with depth) to composite, in float64 and float32."""
    scene = hard_scene(seed, n=n)
    cams = make_cameras(EYES[:1], width, height)
    proj = project(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, cams.world_to_cam[0],
                   cams.intrinsics[0], width, height)
    g = torch.Generator().manual_seed(seed)
    features = torch.cat([torch.rand(len(proj.index), 3, generator=g), proj.depths[:, None]], 1)
    leaves = [proj.means2d, proj.conics, proj.opacities, features]
    return proj, [x.detach().double() for x in leaves], [x.detach().float() for x in leaves]


def _composite(backend, proj, leaves, width=40, height=24, **options):
    """Blended features, transmittance and the gradients of a fixed random loss on both."""
    leaves = [x.clone().to(DEVICE).requires_grad_(True) for x in leaves]
    means2d, conics, opacities, features = leaves
    proj = dataclasses.replace(proj, means2d=means2d, conics=conics, opacities=opacities,
                               radii=proj.radii.to(DEVICE), depths=proj.depths.to(DEVICE))
    if backend == "triton":
        from artnvg_core.raster.triton_backend import rasterize_triton

        blended, trans = rasterize_triton(proj, features, width, height, **options)
    else:
        blended, trans = rasterize(proj, features, width, height)
    g = torch.Generator().manual_seed(3)
    w_blend = torch.randn(blended.shape, generator=g, dtype=torch.float64).to(blended)
    w_trans = torch.randn(trans.shape, generator=g, dtype=torch.float64).to(trans)
    ((blended * w_blend).sum() + (trans * w_trans).sum()).backward()
    return [blended.detach().double().cpu(), trans.detach().double().cpu()] + [x.grad.double().cpu() for x in leaves]


@pytest.mark.parametrize(("tile", "chunk"), [(16, 32), (8, 16), (16, 4)])
def test_compositing_and_every_gradient_match_the_float64_reference(tile, chunk):
    """Blended colour and depth, transmittance and the gradients by means2d, conics, opacities and
    features, against the reference compositor in float64 on the same projection, for tile and chunk
    sizes that split the lists differently (a chunk of 4 crosses many chunk boundaries)."""
    proj, f64, f32 = _composite_inputs()
    expected = _composite("torch", proj.__class__(**{k: (v.double() if v.is_floating_point() else v)
                                                     for k, v in vars(proj).items()}), f64)
    got = _composite("triton", proj, f32, tile=tile, chunk=chunk)
    names = ["blended", "transmittance", "means2d grad", "conics grad", "opacities grad", "features grad"]
    for name, a, b in zip(names, got, expected):
        error = float((a - b).norm() / b.norm())
        assert torch.isfinite(a).all() and error <= 1e-5, (name, error)


def test_transmittance_stop_and_saturated_pixels():
    """Twenty opaque Gaussians stacked on one spot: compositing stops before transmittance reaches
    1e-4 (the reference's rule, the same stop); images and gradients agree with float64."""
    n = 20
    means = torch.zeros(n, 3) + torch.linspace(0, 0.5, n)[:, None] * torch.tensor([0.0, 0.0, 1.0])
    g = torch.Generator().manual_seed(1)
    scene = GaussianScene(means, torch.randn(n, 4, generator=g), -1.5 + 0.1 * torch.randn(n, 3, generator=g),
                          torch.full((n,), 3.0), torch.rand(n, 1, 3, generator=g))
    outputs, grads = [], []
    for dtype, backend in ((torch.float32, "triton"), (torch.float64, "torch")):
        params = {k: v.to(DEVICE, dtype).clone().requires_grad_(True) for k, v in scene.tensors().items()}
        out = render(GaussianScene(**params), make_cameras(EYES[:1], dtype=dtype).to(DEVICE), return_depth=True,
                     backend=backend)
        (out.rgb.sum() + out.alpha.sum()).backward()
        outputs.append([out.rgb.detach(), out.alpha.detach(), out.depth.detach() / 4])  # depth ~4
        grads.append({k: p.grad.double().cpu() for k, p in params.items()})
    centre = outputs[0][1][0, 16, 20, 0].item()
    assert 1e-4 < 1 - centre < 1e-3  # stopped, and one more Gaussian would pass 1e-4
    for a, b in zip(*outputs):
        assert (a.double().cpu() - b.cpu()).abs().max() <= 1e-5
    for name, g in grads[0].items():
        assert float((g - grads[1][name]).norm() / grads[1][name].norm()) <= 1e-4, name


@pytest.mark.parametrize("cull", ["opacity", "behind"])
def test_a_render_that_shows_nothing_gives_zero_gradients(cull):
    params = {k: v.clone() for k, v in hard_scene(0, n=8).tensors().items()}
    if cull == "opacity":
        params["opacity_logits"].fill_(-1e4)
    else:
        params["means"] += torch.tensor([0.0, 0.0, -10.0])
    params = {k: v.to(DEVICE).requires_grad_(True) for k, v in params.items()}
    out = render(GaussianScene(**params), make_cameras(EYES[:2]).to(DEVICE), return_depth=True, backend="triton")
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert (out.alpha == 0).all()
    for name, p in params.items():
        assert torch.equal(p.grad, torch.zeros_like(p)), name


def test_backend_choice():
    """auto is triton for float32 CUDA tensors, torch elsewhere; triton refuses float64."""
    assert choose_backend("auto", torch.device("cpu")) == "torch"
    with pytest.raises(ValueError, match="backend 'triton' needs float32"):
        choose_backend("triton", torch.device(DEVICE), torch.float64)
    if torch.cuda.is_available():
        assert choose_backend("auto", torch.device("cuda")) == "triton"
        assert prepare_backend("cuda") == "triton"
