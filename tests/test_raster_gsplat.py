"""gsplat backend (raster/gsplat_backend.py): the same images and gradients as the reference, hard cases
included. CUDA-only tests are marked ``cuda`` (run them with ``pytest -m cuda`` on a GPU; the record of
the last run is docs/cuda_run.md); the announcement of gsplat's kernel build is tested on the CPU."""

import dataclasses
import logging

import pytest
import torch

from artnvg_core.raster import gsplat_backend, prepare_backend, render
from artnvg_core.scene import GaussianScene

from raster_scenes import EYES, hard_cases, hard_scene, make_cameras, many_gaussians, parity

HARD = {case.name: case for case in hard_cases()}
# the gsplat compositor against the float64 references (float32 arithmetic, thresholds at 1/255 and
# T = 1e-4 decided a rounding apart); measured figures are in docs/cuda_run.md
MIN_PSNR, MAX_GRAD_ERROR = 60.0, 1e-2


@pytest.fixture
def gsplat_on_cuda():
    pytest.importorskip("gsplat")


@pytest.mark.cuda
def test_matches_the_reference_on_cuda(gsplat_on_cuda):
    scene = hard_scene(0).to("cuda")
    cams = make_cameras(EYES).to("cuda")
    ref = render(scene, cams, return_depth=True, backend="torch")
    fast = render(scene, cams, return_depth=True, backend="gsplat")
    assert (ref.rgb - fast.rgb).abs().max() <= 1e-3
    assert (ref.alpha - fast.alpha).abs().max() <= 1e-3
    covered = ref.alpha > 0.5
    assert ((ref.depth - fast.depth).abs()[covered] / ref.depth[covered]).max() <= 1e-3


@pytest.mark.cuda
@pytest.mark.parametrize("name", list(HARD))
def test_hard_cases_agree_with_float64_forward_and_backward(gsplat_on_cuda, name):
    result = parity(HARD[name], "gsplat", "cuda")
    assert result["finite"] and result["psnr"] >= MIN_PSNR and result["grad_error"] <= MAX_GRAD_ERROR, result


@pytest.mark.cuda
def test_five_million_gaussians_agree_with_the_reference(gsplat_on_cuda):
    result = parity(many_gaussians(5_000_000), "gsplat", "cuda")
    assert result["finite"] and result["psnr"] >= MIN_PSNR and result["grad_error"] <= MAX_GRAD_ERROR, result


@pytest.mark.cuda
@pytest.mark.parametrize("cull", ["opacity", "behind"])
def test_a_render_that_shows_nothing_gives_zero_gradients(gsplat_on_cuda, cull):
    params = {k: v.clone() for k, v in hard_scene(0, n=8).tensors().items()}
    if cull == "opacity":
        params["opacity_logits"].fill_(-1e4)
    else:
        params["means"] += torch.tensor([0.0, 0.0, -10.0])
    params = {k: v.cuda().requires_grad_(True) for k, v in params.items()}
    out = render(GaussianScene(**params), make_cameras(EYES[:2]).to("cuda"), return_depth=True, backend="gsplat")
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert (out.alpha == 0).all()
    for name, p in params.items():
        assert torch.equal(p.grad, torch.zeros_like(p)), name


@pytest.mark.cuda
@pytest.mark.parametrize("backend", ["gsplat", "triton"])
def test_a_finetune_with_an_extreme_gaussian_loses_nothing(backend, caplog):
    """One Gaussian of log-scale 45 covering the view (once all of gsplat's gradients went NaN):
    every step applies, nothing is held back, the result is finite and has changed; on gsplat and
    on the Triton backend (the default on CUDA)."""
    pytest.importorskip(backend)
    from artnvg_core.cameras import load_cameras
    from artnvg_core.finetune import FinetuneConfig, finetune
    from artnvg_core.formats import load_scene
    from artnvg_core.images import load_image
    from artnvg_core.stylize import DemoInputs

    demo = DemoInputs()
    scene = load_scene(demo.scene)
    huge = dataclasses.replace(scene.select(torch.arange(1)), log_scales=torch.full((1, 3), 45.0),
                               opacity_logits=torch.tensor([-0.24]))
    scene = GaussianScene(**{k: torch.cat([v, getattr(huge, k)]) for k, v in scene.tensors().items()}).to("cuda")
    cameras = load_cameras(demo.cameras).subset([0, 6]).scaled(0.25)
    config = FinetuneConfig(iterations=5, nnfm_max_side=64, backend=backend, optimize="all")
    with caplog.at_level(logging.WARNING):
        result = finetune(scene, cameras, load_image(demo.style), config=config)
    assert not [r for r in caplog.records if r.name == "artnvg_core.finetune.finite_steps"], caplog.text
    assert all(torch.isfinite(v).all() for v in result.tensors().values())
    assert not torch.equal(result.sh, scene.sh)


def test_the_kernel_build_is_announced_once_before_it_starts(monkeypatch):
    """On the CPU, with gsplat's build and import stood in for: the notice comes before the build,
    then its time, each once per process; later loads say nothing."""
    events = []
    monkeypatch.setattr(gsplat_backend, "_loaded", False)
    monkeypatch.setattr(gsplat_backend, "build_pending", lambda: True)
    monkeypatch.setattr(gsplat_backend, "_import_kernels", lambda: events.append("build") or object())
    gsplat_backend.load_kernels(events.append)
    gsplat_backend.load_kernels(events.append)
    assert events[0] == gsplat_backend.BUILD_NOTICE and "BENCHMARKS.md" in events[0]
    assert events[1] == "build" and events[2].startswith("gsplat: CUDA kernels built in ") and len(events) == 3


def test_without_a_cuda_toolkit_the_build_failure_says_what_to_do(monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_loaded", False)
    monkeypatch.setattr(gsplat_backend, "build_pending", lambda: False)
    monkeypatch.setattr(gsplat_backend, "_import_kernels", lambda: None)
    with pytest.raises(RuntimeError, match=r"no CUDA toolkit, nvcc, found\); install .* backend 'torch'"):
        gsplat_backend.load_kernels()


def test_prepare_backend_loads_only_what_the_device_renders_with(monkeypatch):
    loads = []
    monkeypatch.setattr("artnvg_core.raster.load_kernels", loads.append)
    assert prepare_backend("cpu", announce=print) == "torch" and loads == []
    with pytest.raises(ValueError, match="backend 'gsplat' needs float32 CUDA tensors"):
        prepare_backend("cpu", "gsplat")
