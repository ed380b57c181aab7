"""Triton backend (raster/triton_backend.py, triton_tiles.py): its kernels, forward and backward, against the float64
references on the hard cases. Without a GPU they run in Triton's CPU interpreter (TRITON_INTERPRET=1,
set here before the kernels are first imported); tests marked ``cuda`` run them compiled on a GPU
(docs/cuda_run.md records the last run)."""

import dataclasses
import math
import os

import pytest
import torch

if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")

from artnvg_core.raster import choose_backend, prepare_backend, render  # noqa: E402
from artnvg_core.raster.projection import ALPHA_MIN, project  # noqa: E402
from artnvg_core.raster.torch_backend import TILE, _tile_lists, rasterize  # noqa: E402
from artnvg_core.raster.triton_backend import Pass, rasterize_triton  # noqa: E402
from artnvg_core.raster.triton_tiles import ListCapacity, tile_lists  # noqa: E402
from artnvg_core.scene import GaussianScene  # noqa: E402

from raster_scenes import EYES, hard_cases, hard_scene, make_cameras, parity  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
HARD = {case.name: case for case in hard_cases()}
# float32 compositing against float64 (thresholds at 1/255 and T = 1e-4 decided a rounding apart):
# the Triton kernels measured 121-146 dB and gradient errors of 1e-6..1e-5 on every case
MIN_PSNR, MAX_GRAD_ERROR = 120.0, 1e-4


@pytest.mark.slow
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
        blended, trans = rasterize_triton(proj, features, width, height, **options)
    else:
        blended, trans = rasterize(proj, features, width, height)
    g = torch.Generator().manual_seed(3)
    w_blend = torch.randn(blended.shape, generator=g, dtype=torch.float64).to(blended)
    w_trans = torch.randn(trans.shape, generator=g, dtype=torch.float64).to(trans)
    ((blended * w_blend).sum() + (trans * w_trans).sum()).backward()
    return [blended.detach().double().cpu(), trans.detach().double().cpu()] + [x.grad.double().cpu() for x in leaves]


@pytest.mark.parametrize(("tile", "passes"), [(16, ((16, 32, 4), (16, 32, 4))), (8, ((8, 4, 2), (2, 16, 1))),
                                              (16, ((4, 16, 2), (2, 4, 1)))])
def test_compositing_and_every_gradient_match_the_float64_reference(tile, passes):
    """Blended colour and depth, transmittance and the gradients by means2d, conics, opacities and
    features, against the reference compositor in float64 on the same projection, for tile, rows and
    chunk sizes that split the pixels and lists differently (a chunk of 4 crosses many chunk
    boundaries; programs of 2 rows share a tile's list 8 ways)."""
    proj, f64, f32 = _composite_inputs()
    expected = _composite("torch", proj.__class__(**{k: (v.double() if v.is_floating_point() else v)
                                                     for k, v in vars(proj).items()}), f64)
    got = _composite("triton", proj, f32, tile=tile, passes=tuple(Pass(*p) for p in passes))
    names = ["blended", "transmittance", "means2d grad", "conics grad", "opacities grad", "features grad"]
    for name, a, b in zip(names, got, expected):
        error = float((a - b).norm() / b.norm())
        assert torch.isfinite(a).all() and error <= 1e-5, (name, error)


def _on_device(proj):
    """``proj`` with the fields tile_lists reads on the tests' device."""
    return dataclasses.replace(proj, **{k: getattr(proj, k).to(DEVICE)
                                        for k in ("means2d", "conics", "opacities", "radii", "depths")})


def _peak_alpha(proj, gauss, tile_x, tile_y, tile, width, height):
    """The largest o * exp(-sigma) (sigma >= 0) of Gaussian ``gauss`` over the pixel centres of one tile
    inside the image, in float64 from the float32 projection (brute force)."""
    xs = torch.arange(tile_x * tile, min((tile_x + 1) * tile, width), dtype=torch.float64) + 0.5
    ys = torch.arange(tile_y * tile, min((tile_y + 1) * tile, height), dtype=torch.float64) + 0.5
    dx = xs[None, :] - proj.means2d[gauss, 0].double()
    dy = ys[:, None] - proj.means2d[gauss, 1].double()
    a, b, c = proj.conics[gauss].double()
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    return float(torch.where(sigma >= 0, proj.opacities[gauss].double() * torch.exp(-sigma), 0.0).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_tile_lists_keep_every_tile_a_gaussian_reaches_in_the_references_order(seed):
    """Triton's tile lists (counted and written by kernels, sorted by 16-bit tile keys) are the
    reference's ``_tile_lists`` (footprint boxes) less the tiles whose pixel centres the Gaussian cannot
    reach at alpha >= 1/255: each tile's run a subsequence of the reference's (depth order, ties in
    projection order), keeping every pair with a pixel at or above 1/255 (float64 brute force over the
    tile) and dropping those far below it; rows culled with radii -1 (as the fused projection leaves
    them) get no tiles."""
    width, height = 100, 70  # the last tiles cut by the image
    scene = hard_scene(seed, n=60)
    cams = make_cameras(EYES[:1], width, height)
    proj = project(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, cams.world_to_cam[0],
                   cams.intrinsics[0], width, height)
    proj.depths[::3] = proj.depths[0]  # ties, broken by projection order
    order, starts, counts = _tile_lists(proj, width, height)
    tiles_x = -(-width // TILE)
    boxes = [order[s:s + n].tolist() for s, n in zip(starts.tolist(), counts.tolist())]
    peaks = [[_peak_alpha(proj, g, t % tiles_x, t // tiles_x, TILE, width, height) for g in run]
             for t, run in enumerate(boxes)]
    culled = 5
    padded = dataclasses.replace(
        proj, means2d=torch.cat([proj.means2d, torch.rand(culled, 2) * 50]),
        conics=torch.cat([proj.conics, torch.full((culled, 3), float("nan"))]),
        opacities=torch.cat([proj.opacities, torch.ones(culled)]),
        radii=torch.cat([proj.radii, torch.full((culled, 2), -1)]),
        depths=torch.cat([torch.full((culled,), -1.0), proj.depths]).roll(-culled))
    for rows in (proj, padded):
        ids, offsets = tile_lists(_on_device(rows), width, height, tile=TILE)
        ids, offsets = ids.long().cpu().tolist(), offsets.long().cpu().tolist()
        for t, (run, peak) in enumerate(zip(boxes, peaks)):
            kept = ids[offsets[t]:offsets[t + 1]]
            assert kept == [g for g in run if g in kept], t  # the reference's order
            assert all(g in kept for g, p in zip(run, peak) if p >= ALPHA_MIN), t
            assert all(g not in kept for g, p in zip(run, peak) if p < 0.99 * ALPHA_MIN), t
    assert len(order) > 3 * len(proj.depths)  # footprints span several tiles
    dropped = sum(p < ALPHA_MIN for peak in peaks for p in peak)
    assert dropped > 0.15 * len(order), (dropped, len(order))  # boxes' corners and the needles' sides


def test_lists_given_a_capacity_equal_the_exact_ones_or_say_they_overflowed():
    """With a :class:`ListCapacity` the first render waits for its count and sizes the room; later ones
    get the room without waiting: lists within it equal the exact lists (padding never reaches a tile's
    run); one that outgrows it is flagged on the device and by the host check, which grows the room
    to fit, and the render then equals the exact one again."""
    width, height = 100, 70
    scene = hard_scene(0, n=60)
    cams = make_cameras(EYES[:1], width, height)

    def lists_of(scale):
        proj = project(scene.means, scene.quats, scene.log_scales + math.log(scale), scene.opacity_logits,
                       cams.world_to_cam[0], cams.intrinsics[0], width, height)
        return _on_device(proj)

    def runs(ids, offsets):
        return [ids[offsets[t]:offsets[t + 1]].tolist() for t in range(len(offsets) - 1)]

    small, large = lists_of(1.0), lists_of(3.0)  # larger footprints: more intersections
    exact_small, exact_large = (runs(*tile_lists(p, width, height)) for p in (small, large))
    total_small = sum(map(len, exact_small))
    capacity = ListCapacity()
    capacity.SLACK = 0  # room: MARGIN times the count, which the large footprints outgrow
    assert sum(map(len, exact_large)) > ListCapacity.MARGIN * total_small
    assert runs(*tile_lists(small, width, height, capacity=capacity)) == exact_small
    assert capacity.room == int(ListCapacity.MARGIN * total_small)  # sized from the count
    assert capacity.take_overflow() is None  # nothing recorded yet
    ids, offsets = tile_lists(small, width, height, capacity=capacity)
    assert len(ids) == capacity.room and runs(ids, offsets) == exact_small
    assert not bool(capacity.take_overflow()) and not capacity.overflowed()
    truncated = runs(*tile_lists(large, width, height, capacity=capacity))
    assert truncated != exact_large and bool(capacity.take_overflow())
    assert capacity.overflowed() and capacity.room >= sum(map(len, exact_large))
    assert runs(*tile_lists(large, width, height, capacity=capacity)) == exact_large
    assert not bool(capacity.take_overflow()) and not capacity.overflowed()


@pytest.mark.slow
def test_skipping_blocks_no_pixel_uses_changes_nothing():
    """The kernels skip blocks of Gaussians that no open pixel uses: bit for bit the same images, and
    the same gradients (up to the order of the backward's atomic additions on a GPU)."""
    proj, _, f32 = _composite_inputs(seed=2, n=60)
    passes = (Pass(4, 4, 1), Pass(4, 4, 1))
    skipped, walked = (_composite("triton", proj, f32, passes=passes, skip=skip) for skip in (True, False))
    for a, b in zip(skipped[:2], walked[:2]):
        assert torch.equal(a, b)
    for a, b in zip(skipped[2:], walked[2:]):
        assert float((a - b).abs().max() / b.abs().max()) <= 1e-6


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


def _fused_errors(scene, cameras, cam=0, degree=None, seed=1):
    """The fused projection + colours kernel pair (raster/triton_projection.py) in float32 against
    autograd through the float64 references project() + sh_to_color() on one camera: whether the kept
    set and radii agree, the relative error of each output (kept Gaussians) and of each parameter's
    gradient for random weights on every output, and whether every gradient is finite."""
    from artnvg_core.raster.sh import sh_to_color
    from artnvg_core.raster.triton_projection import project_color_triton

    degree = scene.sh_degree if degree is None else degree
    w2c, k, center = cameras.world_to_cam[cam], cameras.intrinsics[cam], cameras.centers[cam]
    size = (cameras.width, cameras.height)
    settings = (0.01, scene.blur_px2, scene.antialiased)
    p64 = {n: v.double().clone().requires_grad_(True) for n, v in scene.tensors().items()}
    ref = project(p64["means"], p64["quats"], p64["log_scales"], p64["opacity_logits"], w2c.double(), k.double(),
                  *size, *settings)
    ref_colors = sh_to_color(p64["sh"].index_select(0, ref.index),
                             p64["means"].index_select(0, ref.index) - center.double(), degree)
    p32 = {n: v.float().to(DEVICE).clone().requires_grad_(True) for n, v in scene.tensors().items()}
    proj, colors = project_color_triton(*(p32[n] for n in ("means", "quats", "log_scales", "opacity_logits", "sh")),
                                        w2c.to(DEVICE), k.to(DEVICE), center.to(DEVICE), *size, degree, *settings)
    kept = (proj.radii[:, 0] >= 0).nonzero()[:, 0].cpu()
    same = torch.equal(kept, ref.index) and torch.equal(proj.radii.cpu()[kept], ref.radii)
    outputs = {"means2d": (proj.means2d, ref.means2d), "conics": (proj.conics, ref.conics),
               "depths": (proj.depths, ref.depths), "opacities": (proj.opacities, ref.opacities),
               "colors": (colors, ref_colors)}
    g = torch.Generator().manual_seed(seed)
    loss32, loss64 = 0, 0
    errors = {}
    for name, (got, expected) in outputs.items():
        got = got.cpu().double()[kept] if same else expected.detach()
        w = torch.randn(expected.shape, generator=g, dtype=torch.float64) / expected.detach().abs().mean().clamp_min(1e-30)
        loss32, loss64 = loss32 + (got * w).sum(), loss64 + (expected * w).sum()
        errors[name] = float((got.detach() - expected.detach()).norm() / expected.detach().norm().clamp_min(1e-300))
    loss32.backward()
    loss64.backward()
    finite = all(bool(torch.isfinite(p.grad).all()) for p in p32.values())
    for name in p64:
        errors[f"{name} grad"] = float((p32[name].grad.cpu().double() - p64[name].grad).norm()
                                       / p64[name].grad.norm().clamp_min(1e-300))
    return same, finite, errors


def test_fused_projection_and_colours_match_float64_on_every_hard_case():
    """Every hard case (both cameras): the same Gaussians kept with the same radii, every output and
    gradient finite and at float32's precision against float64 (measured: at most 4e-7)."""
    for i, case in enumerate(HARD.values()):
        same, finite, errors = _fused_errors(case.scene, case.cameras, cam=i % 2)
        assert same and finite and max(errors.values()) <= 2e-6, (case.name, errors)


def _ordinary_scene(seed, degree, antialiased):
    """Random well-conditioned Gaussians in front of camera EYES[0], plus ones straddling the near plane
    (centres 0.002-0.05 past it) and ones past the 1.3x field-of-view clamp whose footprints reach the
    image."""
    g = torch.Generator().manual_seed(seed)
    n = 24
    means = torch.randn(n, 3, generator=g) * 0.6
    means[:4] = torch.tensor([0.0, 0.0, -4.0 + 0.01]) + torch.tensor([[0.001, 0.0, 0.002], [-0.002, 0.001, 0.01],
                                                                      [0.0, -0.001, 0.03], [0.003, 0.002, 0.05]])
    means[4:8] = torch.tensor([[3.5, 0.2, 0.0], [-3.8, -0.1, 0.3], [0.1, 3.6, -0.2], [0.3, -3.5, 0.5]])
    log_scales = torch.randn(n, 3, generator=g) * 0.3 - 2.0
    log_scales[:4] = -4.0
    log_scales[4:8] = 0.0
    return GaussianScene(means, torch.randn(n, 4, generator=g), log_scales, torch.randn(n, generator=g) + 1.0,
                         torch.randn(n, 16, 3, generator=g) * 0.5, antialiased=antialiased)


@pytest.mark.parametrize(("degree", "antialiased"), [(0, False), (1, True), (2, False), (3, True)])
def test_fused_backward_matches_float64_vector_jacobian_products(degree, antialiased):
    """The backward kernel alone on ordinary inputs: its gradients for random weights on every output
    against float64 autograd, for each SH degree (coefficients past it get zero gradients), antialiased
    or not, with Gaussians straddling the near plane and past the field-of-view clamp (both kept)."""
    scene = _ordinary_scene(degree, degree, antialiased)
    cams = make_cameras(EYES[:1])
    same, finite, errors = _fused_errors(scene, cams, degree=degree)
    assert same and finite and max(errors.values()) <= 2e-6, errors
    proj = project(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, cams.world_to_cam[0],
                   cams.intrinsics[0], cams.width, cams.height)
    assert {0, 4, 5, 6, 7} <= set(proj.index.tolist())  # the hard rows are kept, so their gradients count


@pytest.mark.parametrize("n, width, height, degree, depth, antialiased", [
    (37, 40, 24, None, False, False),  # no size a multiple of 16; the scene's own degree
    (16, 48, 17, 1, True, True),  # 3 tiles wide; a lower degree, depth (4 features), opacity compensated
])
def test_the_warmups_are_the_launches_a_render_and_its_backward_make(monkeypatch, n, width, height, degree, depth,
                                                                     antialiased):
    from artnvg_core.raster import triton_warmups

    from triton_launches import record_launches, warmed

    scene = dataclasses.replace(hard_scene(3, n=n), antialiased=antialiased).to(DEVICE)
    cameras = make_cameras(EYES[:1], width, height).to(DEVICE)
    launched = record_launches(monkeypatch)
    leaves = [t.detach().requires_grad_(True) for t in (scene.means, scene.quats, scene.log_scales,
                                                         scene.opacity_logits, scene.sh)]
    seen = dataclasses.replace(scene, means=leaves[0], quats=leaves[1], log_scales=leaves[2],
                               opacity_logits=leaves[3], sh=leaves[4])
    out = render(seen, cameras, sh_degree=degree, return_depth=depth, backend="triton")
    (out.rgb.sum() + out.alpha.sum()).backward()
    warmups = triton_warmups(scene, cameras, sh_degree=degree, return_depth=depth, gradients=True)
    assert len(launched) == 7 and launched == warmed(warmups)  # projection 3, tiles 2, compositing 2
    forward = warmed(triton_warmups(scene, cameras, sh_degree=degree, return_depth=depth))
    assert len(forward) == 4 and forward < launched
