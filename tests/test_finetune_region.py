"""Finetuning a region: only the selected Gaussians change, the pixels they do not cover stay, and every loss
term is the weighted mean over the pixels they cover (against plain means over the chosen pixels)."""

import pytest
import torch

from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.finetune.step_loss import StepLoss
from artnvg_core.formats import read_ply
from artnvg_core.images import load_image
from artnvg_core.losses import NNFMLoss, load_vgg, style_image_features
from artnvg_core.metrics.color import mean_cov_distance
from artnvg_core.raster import render
from artnvg_core.selection import Sphere, coverage, select_region
from artnvg_core.stylize import DemoInputs

LAYERS = ("relu3_1", "relu3_2", "relu3_3")


@pytest.fixture(scope="module")
def demo():
    inputs = DemoInputs()
    scene = read_ply(inputs.scene).select(slice(0, None, 4))  # 10,000 Gaussians
    cameras = load_cameras(inputs.cameras).subset([0, 6, 12, 18]).scaled(0.125)
    centre = scene.means.median(0).values
    radius = float((scene.means - centre).norm(dim=1).quantile(0.3))
    selection = select_region(scene, Sphere(tuple(centre.tolist()), radius))
    return scene, cameras, load_image(inputs.style), selection


def _renders(scene, cameras):
    with torch.no_grad():
        return render(scene, cameras).rgb.clamp(0, 1)


def _psnr(a, b):
    return float(-10 * torch.log10((a - b).square().mean().clamp_min(1e-20)))


@pytest.mark.parametrize("color_transfer, iterations", [(True, 6), (False, 3)])
def test_only_the_selection_changes_and_uncovered_pixels_stay(demo, color_transfer, iterations):
    scene, cameras, style, selection = demo
    config = FinetuneConfig(iterations=iterations, color_transfer=color_transfer)
    result = finetune(scene, cameras, style, config=config, selection=selection)
    for name, value in result.tensors().items():
        assert torch.equal(value[~selection], getattr(scene, name)[~selection]), name
    assert (result.sh[selection] != scene.sh[selection]).any()
    covered = coverage(scene, selection, cameras)
    before, after = _renders(scene, cameras), _renders(result, cameras)
    outside, inside = covered < 1e-3, covered > 0.5
    assert outside.sum() > 1000 and inside.sum() > 1000
    assert _psnr(after[outside], before[outside]) >= 60
    if color_transfer:  # the region takes the style's colours
        assert mean_cov_distance(after[inside], style) < mean_cov_distance(before[inside], style) - 0.1


def test_region_with_stylized_views_pulls_only_the_region_toward_them(demo):
    scene, cameras, style, selection = demo
    before = _renders(scene, cameras)
    targets = 1 - before  # every pixel far from the target
    config = FinetuneConfig(iterations=8, nnfm_weight=0.0, lr_sh_dc=0.05)
    result = finetune(scene, cameras, style, stylized=targets, config=config, selection=selection)
    after, covered = _renders(result, cameras), coverage(scene, selection, cameras)
    inside, outside = covered > 0.9, covered < 1e-3
    assert (after[inside] - targets[inside]).abs().mean() < (before[inside] - targets[inside]).abs().mean() - 0.05
    assert _psnr(after[outside], before[outside]) >= 60


def test_weighted_terms_are_means_over_the_weighted_pixels():
    """0/1 weights: L1, total variation and NNFM equal their plain means over the pixels (positions) weighed 1,
    which are whole 4x4 blocks, so that the VGG's relu3 positions are weighed 0 or 1 too."""
    g = torch.Generator().manual_seed(0)
    image, target = torch.rand(2, 1, 32, 32, 3, generator=g)
    block = torch.zeros(8, 8)
    block[2:6, 1:5] = 1
    weights = block.repeat_interleave(4, 0).repeat_interleave(4, 1)[None]
    vgg = load_vgg("vgg19")
    style = torch.rand(1, 3, 32, 32, generator=g)
    nnfm = NNFMLoss(style_image_features(vgg, style, LAYERS, None), layer_groups=(LAYERS,))
    config = FinetuneConfig(l1_weight=1.0, ssim_weight=0.0, nnfm_weight=1.0, nnfm_max_side=None)
    views = torch.zeros(1, dtype=torch.long)
    loss = StepLoss(config, vgg, nnfm, target, None, weights)
    _, (l1, _, nnfm_term) = loss(image, views)  # l1, ssim (weighed 0), nnfm
    chosen = weights[0] > 0
    torch.testing.assert_close(l1, (image[0][chosen] - target[0][chosen]).abs().mean(), rtol=1e-6, atol=0)
    # NNFM over the chosen positions: the brute-force best cosine of each against every style position
    feats = vgg(image.permute(0, 3, 1, 2), LAYERS)
    rendered = torch.cat([feats[k] for k in LAYERS], 1)[0].flatten(1).T.double()
    styles = torch.cat([v for v in style_image_features(vgg, style, LAYERS, None).values()], 1)[0].flatten(1).T.double()
    cosines = torch.nn.functional.normalize(rendered, dim=1) @ torch.nn.functional.normalize(styles, dim=1).T
    picked = block.flatten() > 0
    torch.testing.assert_close(nnfm_term.double(), (1 - cosines.max(1).values)[picked].mean(), rtol=1e-4, atol=0)
    # total variation without stylized views: each neighbour pair weighed by its second pixel
    config = FinetuneConfig(nnfm_weight=0.0, tv_weight=1.0, nnfm_max_side=None)
    _, (tv,) = StepLoss(config, vgg, nnfm, None, None, weights)(image, views)
    down = (image[0, 1:] - image[0, :-1]).abs()[chosen[1:]].mean()
    right = (image[0, :, 1:] - image[0, :, :-1]).abs()[chosen[:, 1:]].mean()
    torch.testing.assert_close(tv, down + right, rtol=1e-6, atol=0)


def test_bad_selections_are_refused(demo):
    scene, cameras, style, _ = demo
    with pytest.raises(ValueError, match="boolean mask of the scene's 10,000 Gaussians"):
        finetune(scene, cameras, style, config=FinetuneConfig(iterations=1), selection=torch.ones(3, dtype=torch.bool))
    far = select_region(scene, Sphere((0.0, 0.0, 0.0), 1e-9)) | (torch.arange(len(scene)) == 0)
    far[0] = False
    far[scene.means[:, 2].argmin()] = True  # one Gaussian, out of every view's sight
    with pytest.raises(ValueError, match="no pixel of any of the 4 views sees the 1 selected Gaussian$"):
        finetune(scene, cameras, style, config=FinetuneConfig(iterations=1), selection=far)


def test_the_regions_coverage_renders_report_progress_and_stop_when_asked(demo):
    """The coverage of every view, rendered before anything else, once passed silently (minutes for the bear's
    96 views at full size on a CPU) and could not be stopped: ComfyUI's Cancel waited for it."""
    from artnvg_core.progress import Cancelled

    scene, cameras, style, selection = demo
    reports = []
    finetune(scene, cameras, style, config=FinetuneConfig(iterations=1), selection=selection,
             render_progress=lambda done, total, info: reports.append((info["stage"], done, total)))
    assert reports[:5] == [("region", view, 4) for view in (0, 1, 2, 3, 4)]
    assert {stage for stage, _, _ in reports} == {"region", "setup", "features", "final"}
    asked = []
    with pytest.raises(Cancelled):
        finetune(scene, cameras, style, config=FinetuneConfig(iterations=1), selection=selection,
                 render_progress=lambda done, total, info: asked.append(info["stage"]), should_stop=lambda: bool(asked))
    assert asked == ["region"]
