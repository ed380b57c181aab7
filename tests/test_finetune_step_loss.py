"""A step's loss: each term against a float64 brute-force reference, picked for the step's views; on CUDA
its graph replays equal the eager call for new renders and views."""

import dataclasses

import pytest
import torch

from artnvg_core.finetune.config import FinetuneConfig
from artnvg_core.losses import NNFMLoss, load_vgg, ssim
from artnvg_core.finetune import step_loss as step_loss_module
from artnvg_core.finetune.step_loss import StepLoss, graphed, vgg_input

LAYERS = ("relu3_1", "relu3_2", "relu3_3")
VIEWS, SIZE = 5, 24


def inputs(device="cpu", seed=0):
    """A style, five stylized views and their originals (as the VGG sees them), two renders of views 3 and 1."""
    generator = torch.Generator().manual_seed(seed)
    style, stylized, originals, image = (torch.rand(*shape, generator=generator).to(device) for shape in (
        (1, 3, 20, 20), (VIEWS, SIZE, SIZE, 3), (VIEWS, 3, SIZE, SIZE), (2, SIZE, SIZE, 3)))
    return style, stylized, originals, image, torch.tensor([3, 1], device=device)


def step_loss(config, style, stylized, originals, device="cpu"):
    vgg = load_vgg("vgg19", None, device)
    with torch.no_grad():
        nnfm = NNFMLoss(vgg(style, LAYERS), layer_groups=(LAYERS,), precision=config.nnfm_search)
    return StepLoss(config, vgg, nnfm, stylized, originals)


def reference_nnfm(render_feats, style_feats):
    """1 - max cosine over every style position, averaged over the render's positions (float64)."""
    def rows(feats):
        stacked = torch.cat([feats[k].double() for k in LAYERS], 1)
        return torch.nn.functional.normalize(stacked.permute(0, 2, 3, 1).reshape(-1, stacked.shape[1]), dim=1)
    return (1 - (rows(render_feats) @ rows(style_feats).T).amax(1)).mean()


def reference_terms(config, style, stylized, originals, image, views):
    """Each term written out in float64 from its definition (finetune's docstring)."""
    vgg = load_vgg("vgg19")
    feats = vgg(vgg_input(image, config), LAYERS)
    with torch.no_grad():
        style_feats, original_feats = vgg(style, LAYERS), vgg(originals[views], LAYERS)
    terms = {}
    if stylized is not None:
        target = stylized[views].double()
        terms["l1"] = config.l1_weight * (image.double() - target).abs().mean()
        terms["ssim"] = config.ssim_weight * (1 - ssim(image.permute(0, 3, 1, 2), target.float().permute(0, 3, 1, 2)))
    terms["nnfm"] = config.nnfm_weight * reference_nnfm(feats, style_feats)
    if stylized is None:
        relative = [(feats[k].double() - original.double()).square().mean() / original.double().square().mean()
                    for k, original in original_feats.items()]
        terms["content"] = config.content_weight * sum(relative) / len(LAYERS)
        image64 = image.double()
        terms["tv"] = config.tv_weight * (image64.diff(dim=1).abs().mean() + image64.diff(dim=2).abs().mean())
    return terms


@pytest.mark.parametrize("with_stylized", [True, False])
def test_terms_and_gradient_match_references(with_stylized):
    style, stylized, originals, image, views = inputs()
    config = FinetuneConfig(nnfm_search="fp32", l1_weight=0.7, ssim_weight=0.3, nnfm_weight=1.3,
                            content_weight=0.4, tv_weight=0.05)
    stylized = stylized if with_stylized else None
    loss_fn = step_loss(config, style, stylized, None if with_stylized else originals)
    expected = reference_terms(config, style, stylized, originals, image.clone().requires_grad_(True), views)
    assert loss_fn.names == tuple(expected)

    image = image.clone().requires_grad_(True)
    loss, terms = loss_fn(image, views)
    assert not terms.requires_grad
    torch.testing.assert_close(terms.double(), torch.stack([v.detach() for v in expected.values()]),
                               rtol=2e-5, atol=1e-7)
    loss.backward()
    reference_image = image.detach().clone().requires_grad_(True)
    sum(reference_terms(config, style, stylized, originals, reference_image, views).values()).backward()
    torch.testing.assert_close(image.grad, reference_image.grad.float(), rtol=1e-3, atol=1e-7)


@pytest.mark.parametrize("budget", [0, 2**30])
def test_content_reference_kept_when_it_fits_and_the_same_either_way(monkeypatch, budget):
    """The original views' features kept or computed each step: the content term equals the brute force's for
    views 3 and 1 both ways."""
    monkeypatch.setattr(step_loss_module, "_cache_budget", lambda device: budget)
    style, _, originals, image, views = inputs()
    config = FinetuneConfig(nnfm_search="fp32", tv_weight=0, content_weight=0.4)
    loss_fn = StepLoss(config, load_vgg("vgg19"), step_loss(config, style, None, None).nnfm, None, originals)
    assert loss_fn.content_reference.cached == (budget > 0)
    _, terms = loss_fn(image, views)
    expected = reference_terms(config, style, None, originals, image, views)["content"]
    torch.testing.assert_close(terms[loss_fn.names.index("content")].double(), expected.detach(), rtol=2e-5, atol=0)


def test_the_content_features_of_every_view_report_progress_and_stop_when_asked():
    """Their first pass, a VGG of every view before the steps (seconds at a capture's size), once passed with no
    bar and could not be stopped."""
    from artnvg_core.progress import Cancelled

    style, _, originals, _, _ = inputs()
    config = FinetuneConfig(nnfm_search="fp32", tv_weight=0, content_weight=0.4)
    nnfm, reports = step_loss(config, style, None, None).nnfm, []
    StepLoss(config, load_vgg("vgg19"), nnfm, None, originals, progress=lambda *report: reports.append(report))
    assert reports == [(done, VIEWS, {}) for done in range(VIEWS + 1)]
    with pytest.raises(Cancelled):
        StepLoss(config, load_vgg("vgg19"), nnfm, None, originals, should_stop=lambda: True)


def test_a_call_asks_to_stop_before_each_convolution_and_search_and_in_its_backward_pass():
    """A call at 512 px takes seconds on a CPU: should_stop is asked within it (the VGG's 7 convolutions up to
    relu3_3, NNFM's one chunk here) and when its backward pass reaches each convolution."""
    from artnvg_core.progress import Cancelled

    style, stylized, _, image, views = inputs()
    config = FinetuneConfig(nnfm_search="fp32")
    asked, stop = [], []
    nnfm = step_loss(config, style, None, None).nnfm
    loss_fn = StepLoss(config, load_vgg("vgg19"), nnfm, stylized, None, should_stop=lambda: asked.append(1) or bool(stop))
    image.requires_grad_(True)
    loss, _ = loss_fn(image, views)
    assert len(asked) == 8
    stop.append(True)
    with pytest.raises(Cancelled):
        loss.backward()
    assert len(asked) == 9 and image.grad is None


def test_weights_leave_out_their_terms():
    style, stylized, originals, image, views = inputs()
    only_nnfm = step_loss(FinetuneConfig(tv_weight=0), style, None, None)
    assert only_nnfm.names == ("nnfm",)
    nothing = step_loss(FinetuneConfig(nnfm_weight=0, tv_weight=0), style, None, None)
    loss, terms = nothing(image.requires_grad_(True), views)
    assert nothing.names == () and terms.shape == (0,) and float(loss.detach()) == 0.0
    loss.backward()  # no term: still a loss to step on, of zero gradient
    assert torch.equal(image.grad, torch.zeros_like(image))


def eager_and_replay_results(eager, replay, device):
    """(eager's, replay's) (loss, terms, gradient) for three new renders and views, each call."""
    results = ([], [])
    for seed, views in ((1, [3, 1]), (2, [0, 4]), (3, [2, 2])):
        image = torch.rand(2, SIZE, SIZE, 3, generator=torch.Generator().manual_seed(seed)).to(device)
        views = torch.tensor(views, device=device)
        for fn, out in zip((eager, replay), results):
            leaf = image.clone().requires_grad_(True)
            loss, terms = fn(leaf, views)
            loss.backward()
            out.append((loss.detach().clone(), terms.clone(), leaf.grad.clone()))  # the graph's, until its next call
    return results


@pytest.mark.cuda
@pytest.mark.parametrize("with_stylized", [True, False])
def test_graph_replays_equal_the_eager_call(with_stylized):
    device = torch.device("cuda")
    style, stylized, originals, _, _ = inputs(device)
    config = FinetuneConfig()
    eager = step_loss(config, style, stylized if with_stylized else None, None if with_stylized else originals, device)
    eager_results, replay_results = eager_and_replay_results(eager, graphed(eager, (2, SIZE, SIZE, 3), device), device)
    torch.testing.assert_close(replay_results, eager_results, rtol=1e-5, atol=1e-8)


@pytest.mark.cuda
def test_the_graphs_outlive_their_step_loss_and_its_kept_features():
    """The graphs read the kept content features by address: with the step loss dropped by the caller and the
    freed memory of the allocator filled with NaN, the replays still equal a fresh eager step loss's calls."""
    import gc

    device = torch.device("cuda")
    style, _, originals, _, _ = inputs(device)
    config = FinetuneConfig()
    kept = step_loss(config, style, None, originals.clone(), device)
    assert kept.content_reference.cached
    replay = graphed(kept, (2, SIZE, SIZE, 3), device)
    sizes = [v.numel() for kept_tensors in (kept.content_reference.store, kept.content_reference.power)
             for v in kept_tensors.values()]
    del kept
    gc.collect()
    poison = [torch.full((n,), float("nan"), device=device) for n in sizes for _ in range(4)]  # takes freed blocks
    del poison
    eager_results, replay_results = eager_and_replay_results(step_loss(config, style, None, originals, device),
                                                             replay, device)
    torch.testing.assert_close(replay_results, eager_results, rtol=1e-5, atol=1e-8)


@pytest.mark.cuda
def test_graphed_finetune_equals_the_eager_one():
    """The same first step's loss terms, and the same update up to the rasterizer's atomic sums' order; with
    torch._dynamo imported, as diffusers imports it (its many objects made the collector free a step loss whose
    kept features a graph still read, before :func:`graphed` held it)."""
    import torch._dynamo  # noqa: F401

    from artnvg_core.cameras import load_cameras
    from artnvg_core.finetune import finetune
    from artnvg_core.formats import read_ply
    from artnvg_core.images import load_image
    from artnvg_core.stylize import DemoInputs

    demo = DemoInputs()
    cameras = load_cameras(demo.cameras).subset([0, 6, 12, 18]).scaled(0.25)
    scene, style = read_ply(demo.scene).to("cuda"), load_image(demo.style)
    config = FinetuneConfig(iterations=12)
    updates, first_steps = [], []
    for graph in (True, False, False):
        infos = {}
        result = finetune(scene, cameras, style, config=dataclasses.replace(config, cuda_graph=graph),
                          progress=lambda step, total, info: infos.setdefault(step, info))
        updates.append(result.sh - scene.sh)
        first_steps.append(infos[1])
    assert first_steps[0].keys() == first_steps[1].keys() and "nnfm" in first_steps[0]
    for name, value in first_steps[0].items():
        assert value == pytest.approx(first_steps[1][name], rel=1e-5, abs=1e-7), name
    scale = updates[1].norm()
    graph_vs_eager, eager_vs_eager = (updates[0] - updates[1]).norm() / scale, (updates[2] - updates[1]).norm() / scale
    assert scale > 0 and graph_vs_eager <= max(3 * eager_vs_eager, 1e-4), (graph_vs_eager, eager_vs_eager)


@pytest.mark.cuda
def test_no_graph_under_the_cuda_malloc_async_allocator():
    """ComfyUI runs PyTorch with cudaMallocAsync: there a finetune with stylized views (SSIM's Triton kernels)
    runs eagerly and finishes, where a capture failed and later crashed the process."""
    import os
    import subprocess
    import sys

    script = """
import torch
from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.formats import read_ply
from artnvg_core.finetune.step_loss import can_graph
from artnvg_core.images import load_image
from artnvg_core.stylize import DemoInputs
assert torch.cuda.get_allocator_backend() == "cudaMallocAsync" and not can_graph(torch.device("cuda"))
demo = DemoInputs()
cameras = load_cameras(demo.cameras).subset([0, 6]).scaled(0.25)
stylized = torch.rand(2, cameras.height, cameras.width, 3)
for _ in range(2):
    finetune(read_ply(demo.scene).to("cuda"), cameras, load_image(demo.style), stylized=stylized,
             config=FinetuneConfig(iterations=4))
print("finished")
"""
    env = {**os.environ, "PYTORCH_CUDA_ALLOC_CONF": "backend:cudaMallocAsync"}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "finished" in done.stdout, done.stderr[-3000:]
