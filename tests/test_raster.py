"""Rasterizer tests: brute-force float64 reference, finite-difference gradients, hard cases, a real scene."""

import dataclasses

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from artnvg_core.cameras import CameraSet
from artnvg_core.progress import Cancelled
from artnvg_core.raster import check_render_inputs, render
from artnvg_core.scene import GaussianScene

from raster_reference import brute_force_render
from raster_scenes import EYES, hard_scene, make_cameras




@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_brute_force_float64(seed):
    scene = hard_scene(seed)
    cams = make_cameras(EYES)
    background = torch.tensor([0.2, 0.5, 0.9])
    out = render(scene, cams, background=background, return_depth=True, backend="torch")
    assert out.rgb.shape == (3, 32, 40, 3) and out.alpha.shape == (3, 32, 40, 1) and out.depth.shape == (3, 32, 40, 1)
    s = scene.to(dtype=torch.float64)
    for c in range(len(cams)):
        rgb, alpha, depth = brute_force_render(
            s.means, s.quats, s.log_scales, s.opacity_logits, s.sh, cams.world_to_cam[c], cams.intrinsics[c], 40, 32,
            background=background.numpy(),
        )
        assert np.abs(out.rgb[c].numpy() - rgb).max() <= 1e-4
        assert np.abs(out.alpha[c, ..., 0].numpy() - alpha).max() <= 1e-4
        covered = alpha > 0.5
        rel = np.abs(out.depth[c, ..., 0].numpy() - depth)[covered] / depth[covered]
        assert rel.max() <= 1e-4


@pytest.mark.parametrize(("blur", "antialiased"), [(0.3, True), (0.1, True), (0.1, False)])
def test_trainer_filters_match_brute_force_float64(blur, antialiased):
    scene = dataclasses.replace(hard_scene(6), blur_px2=blur, antialiased=antialiased)
    cams = make_cameras(EYES[:2])
    out = render(scene, cams, backend="torch")
    s = scene.to(dtype=torch.float64)
    for c in range(len(cams)):
        rgb, alpha, _ = brute_force_render(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh,
                                           cams.world_to_cam[c], cams.intrinsics[c], 40, 32,
                                           blur=blur, antialiased=antialiased)
        assert np.abs(out.rgb[c].numpy() - rgb).max() <= 1e-4
        assert np.abs(out.alpha[c, ..., 0].numpy() - alpha).max() <= 1e-4
    classic = render(hard_scene(6), cams, backend="torch").rgb
    assert (out.rgb - classic).abs().max() > 1e-2  # the settings change the image


def test_mip_splatting_ply_renders_as_its_trainer_did(tmp_path):
    from artnvg_core.formats import read_ply, write_ply

    scene = hard_scene(7, n=40)
    filter_3d = torch.rand(len(scene), generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 0.2
    path = tmp_path / "mip.ply"
    write_ply(scene, path)
    data = PlyData.read(str(path))["vertex"].data
    table = np.empty(len(data), dtype=data.dtype.descr + [("filter_3D", "<f4")])
    for name in data.dtype.names:
        table[name] = data[name]
    table["filter_3D"] = filter_3d.numpy()
    PlyData([PlyElement.describe(table, "vertex")]).write(str(path))
    mip = read_ply(path)
    assert (mip.blur_px2, mip.antialiased) == (0.1, True)
    cams = make_cameras(EYES[:2])
    out = render(mip, cams, backend="torch")
    s = scene.to(dtype=torch.float64)
    f = torch.from_numpy(table["filter_3D"]).double().numpy()
    for c in range(len(cams)):
        rgb, alpha, _ = brute_force_render(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh,
                                           cams.world_to_cam[c], cams.intrinsics[c], 40, 32,
                                           blur=0.1, antialiased=True, filter_3d=f)
        assert np.abs(out.rgb[c].numpy() - rgb).max() <= 1e-4
        assert np.abs(out.alpha[c, ..., 0].numpy() - alpha).max() <= 1e-4
    write_ply(mip, tmp_path / "again.ply")  # written with a zero filter_3D: reads back identical
    again = read_ply(tmp_path / "again.ply")
    assert (again.blur_px2, again.antialiased) == (0.1, True)
    assert all(torch.equal(getattr(again, k), v) for k, v in mip.tensors().items())


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_lower_sh_degree_matches_truncated_scene(degree):
    scene = hard_scene(3, n=30)
    cams = make_cameras(EYES[:1])
    truncated = GaussianScene(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh[:, : (degree + 1) ** 2])
    a = render(scene, cams, sh_degree=degree, backend="torch").rgb
    b = render(truncated, cams, backend="torch").rgb
    assert torch.equal(a, b)


def test_float64_render_equals_brute_force_tightly():
    scene = hard_scene(4, dtype=torch.float64)
    cams = make_cameras(EYES[:1], dtype=torch.float64)
    out = render(scene, cams, backend="torch")
    rgb, _, _ = brute_force_render(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh,
                                   cams.world_to_cam[0], cams.intrinsics[0], 40, 32)
    assert np.abs(out.rgb[0].numpy() - rgb).max() <= 1e-9


def smooth_scene(seed=5, n=6):
    """A few well-separated, moderately opaque Gaussians: no threshold is near,
    so the image is a smooth function of every parameter."""
    g = torch.Generator().manual_seed(seed)
    return GaussianScene(
        (torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.3),
        torch.randn(n, 4, generator=g, dtype=torch.float64),
        torch.full((n, 3), -1.6, dtype=torch.float64) + 0.2 * torch.randn(n, 3, generator=g, dtype=torch.float64),
        torch.randn(n, generator=g, dtype=torch.float64) * 0.3 - 0.5,
        torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * 0.3,
    )


@pytest.mark.slow
def test_gradients_match_finite_differences_float64():
    base = smooth_scene()
    cams = make_cameras([[0.3, -0.2, -3.0], [2.0, 0.5, -2.0]], width=20, height=18, dtype=torch.float64)
    weights = torch.randn(2, 18, 20, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    depth_w = torch.randn(2, 18, 20, 1, generator=torch.Generator().manual_seed(10), dtype=torch.float64)

    def loss_of(**params):
        s = GaussianScene(**{**base.tensors(), **params})
        out = render(s, cams, return_depth=True, backend="torch")
        return (out.rgb * weights).sum() + (out.depth * out.alpha * depth_w).sum() * 0.1

    for name, value in base.tensors().items():
        param = value.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(loss_of(**{name: param}), param)
        numeric = torch.zeros_like(value)
        eps = 1e-6
        for idx in np.ndindex(*value.shape):
            plus, minus = value.clone(), value.clone()
            plus[idx] += eps
            minus[idx] -= eps
            numeric[idx] = (loss_of(**{name: plus}) - loss_of(**{name: minus})) / (2 * eps)
        assert torch.allclose(grad, numeric, rtol=1e-5, atol=1e-6), name


def test_hard_cases_give_finite_images_and_gradients():
    scene = hard_scene(6)
    params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
    out = render(GaussianScene(**params), make_cameras(EYES), return_depth=True, backend="torch")
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.alpha).all() and torch.isfinite(out.depth).all()
    (out.rgb.sum() + out.depth.sum()).backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_a_stop_asked_after_the_forward_pass_ends_the_backward_pass_before_any_tile_batch():
    """The reference backend's backward recomputes each batch of tiles (seconds for a 512 px view on a CPU):
    should_stop is asked before each, so a stop ends it there, with no gradient given to the scene."""
    scene, view = hard_scene(seed=3), make_cameras(EYES[:1], width=512, height=512, focal=450.0)
    params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
    asked, stop = [], []
    out = render(GaussianScene(**params), view, backend="torch", should_stop=lambda: asked.append(1) or bool(stop))
    forward_asks, stop[:] = len(asked), [True]
    with pytest.raises(Cancelled):
        out.rgb.sum().backward()
    assert forward_asks > 2 and len(asked) == forward_asks + 1
    assert all(p.grad is None for p in params.values())


def test_empty_scene_and_fully_culled_scene():
    empty = GaussianScene(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 1, 3))
    cams = make_cameras(EYES[:2])
    out = render(empty, cams, background=torch.tensor([0.1, 0.2, 0.3]), backend="torch")
    assert torch.allclose(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand(2, 32, 40, 3))
    assert (out.alpha == 0).all()
    behind = hard_scene(0).select(torch.arange(3))
    behind = GaussianScene(behind.means + torch.tensor([0.0, 0.0, -10.0]), behind.quats, behind.log_scales,
                           behind.opacity_logits, behind.sh)
    assert (render(behind, cams.subset([0]), backend="torch").alpha == 0).all()


@pytest.mark.parametrize("cull", ["opacity", "behind", "empty"])
def test_backward_through_a_render_that_shows_nothing_gives_zero_gradients(cull):
    """Every Gaussian culled (opacity logits -1e4, all behind the camera, or none at all): the
    render is the background, and a loss on colour, alpha and depth back-propagates zeros."""
    params = dict(hard_scene(0, n=8).tensors())
    if cull == "opacity":
        params["opacity_logits"] = torch.full_like(params["opacity_logits"], -1e4)
    elif cull == "behind":
        params["means"] = params["means"] + torch.tensor([0.0, 0.0, -10.0])
    else:
        params = {k: v[:0] for k, v in params.items()}
    params = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = render(GaussianScene(**params), make_cameras(EYES[:2]), background=torch.tensor([0.1, 0.2, 0.3]),
                 return_depth=True, backend="torch")
    assert (out.alpha == 0).all() and torch.allclose(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand_as(out.rgb))
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for name, p in params.items():
        assert p.grad is not None and torch.equal(p.grad, torch.zeros_like(p)), name


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda t: t.__setitem__(("means", 0, 0), float("nan")), "means"),
        (lambda t: t.__setitem__(("log_scales", 1, 2), float("inf")), "log_scales"),
        (lambda t: t.__setitem__(("sh", 0, 0, 0), float("nan")), "sh"),
        (lambda t: t.__setitem__(("opacity_logits", 4), float("-inf")), "opacity_logits"),
    ],
)
def test_invalid_inputs_rejected(mutate, field):
    params = {k: v.clone() for k, v in hard_scene(0, n=5).tensors().items()}

    class Setter:
        def __setitem__(self, key, value):
            name, *idx = key
            params[name][tuple(idx)] = value

    mutate(Setter())
    with pytest.raises(ValueError, match=f"scene.{field} has non-finite"):
        render(GaussianScene(**params), make_cameras(EYES[:1]), backend="torch")


def _device_reads(monkeypatch) -> list[str]:
    """The names of the tensor-to-host reads made from now on (the test's end restores them)."""
    reads = []
    for method in ("tolist", "item", "__bool__"):
        original = getattr(torch.Tensor, method)
        def counted(self, *args, _original=original, _name=method):
            reads.append(_name)
            return _original(self, *args)

        monkeypatch.setattr(torch.Tensor, method, counted)
    return reads


def test_input_checks_read_the_device_once(monkeypatch):
    """render's value checks (every scene tensor finite, the cameras finite, positive focal lengths) are
    reduced where the tensors live and read back together: one wait for the device, not one a check."""
    scene, cams = hard_scene(0, n=5), make_cameras(EYES[:1])
    reads = _device_reads(monkeypatch)
    check_render_inputs(scene, cams)
    assert reads == ["tolist"]
    broken = CameraSet(cams.world_to_cam * float("nan"), cams.intrinsics, 40, 32, ["x"])
    with pytest.raises(ValueError, match="non-finite poses"):
        check_render_inputs(scene, broken)


def test_inputs_that_passed_are_checked_again_only_once_changed_in_place(monkeypatch):
    """A scene and cameras that passed are not read again (a scene rendered view after view waits once);
    a non-finite value or a negative focal length written in place afterwards is still caught."""
    scene, cams = hard_scene(0, n=5), make_cameras(EYES[:1])
    check_render_inputs(scene, cams)
    reads = _device_reads(monkeypatch)
    check_render_inputs(scene, cams)
    assert reads == []
    scene.sh[2, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="scene.sh has non-finite"):
        render(scene, cams, backend="torch")
    assert reads == ["tolist"]
    scene.sh[2, 1, 0] = 0.0
    cams.intrinsics[0, 1, 1] *= -1
    with pytest.raises(ValueError, match="focal"):
        check_render_inputs(scene, cams)


def test_inference_tensors_are_checked_at_every_render():
    """Tensors made under torch.inference_mode (ComfyUI runs its nodes so) have no version counter: they
    render, and a value written in place between renders is still caught."""
    with torch.inference_mode():
        scene, cams = hard_scene(0, n=5), make_cameras(EYES[:1])
        assert scene.sh.is_inference()
        first = render(scene, cams, backend="torch").rgb
        torch.testing.assert_close(render(scene, cams, backend="torch").rgb, first, rtol=0, atol=0)
        scene.sh[2, 1, 0] = float("nan")
        with pytest.raises(ValueError, match="scene.sh has non-finite"):
            render(scene, cams, backend="torch")


def test_bad_arguments_rejected():
    scene = hard_scene(0, n=5, degree=1)
    cams = make_cameras(EYES[:1])
    for degree in (2, -1, 0.5, True):  # 0.5 evaluated the degree-1 terms, True was degree 1
        with pytest.raises(ValueError, match=f"^render: sh_degree must be an int in 0..1 for this scene, got {degree!r}$"):
            render(scene, cams, sh_degree=degree)
    with pytest.raises(ValueError, match="backend"):
        render(scene, cams, backend="vulkan")
    with pytest.raises(ValueError, match="gsplat"):
        render(scene, cams, backend="gsplat")
    with pytest.raises(ValueError, match="background"):
        render(scene, cams, background=torch.zeros(4))
    bad = CameraSet(cams.world_to_cam, cams.intrinsics * torch.tensor([-1.0, 1, 1])[:, None], 40, 32, ["x"])
    with pytest.raises(ValueError, match="focal"):
        render(scene, bad)
    for row, column in [(0, 1), (1, 0), (2, 0), (2, 1), (2, 2)]:  # skew, a scaled last row: ignored, rendered wrong
        k = cams.intrinsics.clone()
        k[0, row, column] += 0.5
        with pytest.raises(ValueError, match=r"intrinsics must be pinhole matrices \[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"):
            render(scene, CameraSet(cams.world_to_cam, k, 40, 32, ["x"]))
    with pytest.raises(ValueError, match="background has non-finite values"):
        render(scene, cams, background=torch.tensor([0.0, float("nan"), 0.0]))
    for near_plane in (-1.0, float("nan"), float("inf"), "0.01", None):  # -1 drew the Gaussians behind the camera
        with pytest.raises(ValueError, match=f"near_plane must be a finite number >= 0, got {near_plane!r}"):
            render(scene, cams, near_plane=near_plane)


def test_cameras_of_no_views_render_no_views():
    """Cameras of no views (e.g. an empty subset) stopped with torch.stack's "expects a non-empty TensorList"."""
    scene, cams = hard_scene(0, n=5), make_cameras(EYES[:1]).subset([])
    out = render(scene, cams, return_depth=True)
    assert [tuple(x.shape) for x in (out.rgb, out.alpha, out.depth)] == [(0, 32, 40, 3), (0, 32, 40, 1), (0, 32, 40, 1)]
    assert render(scene, cams).depth is None


def test_bear_scene_reproduces_held_out_photos(shared_data):
    """The fitted bear scene at full resolution matches its held-out photos (every 8th view)."""
    from artnvg_core.cameras import load_cameras
    from artnvg_core.formats import read_ply
    from artnvg_core.images import load_image

    bear = shared_data / "scenes" / "bear"
    scene = read_ply(bear / "scene.ply")
    cameras = load_cameras(bear / "transforms.json")
    held_out = cameras.subset(range(0, len(cameras), 8))
    psnrs = []
    for i in range(len(held_out)):
        view = held_out.subset([i])
        with torch.no_grad():
            image = render(scene, view, backend="torch").rgb[0].clamp(0, 1)
        photo = load_image(view.image_paths[0])
        psnrs.append(float(-10 * torch.log10(((image - photo) ** 2).mean())))
    assert len(psnrs) == 12
    assert sum(psnrs) / len(psnrs) >= 21.0, psnrs


def _assert_matches_brute_force(scene, cams, tolerance=1e-4):
    s = scene.to(dtype=torch.float64)
    out = render(scene, cams, backend="torch")
    for c in range(len(cams)):
        rgb, alpha, _ = brute_force_render(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh,
                                           cams.world_to_cam[c], cams.intrinsics[c], 40, 32)
        assert np.abs(out.rgb[c].numpy() - rgb).max() <= tolerance
        assert np.abs(out.alpha[c, ..., 0].numpy() - alpha).max() <= tolerance


@pytest.mark.parametrize("seed", [0])
def test_quaternions_of_any_norm_render_as_normalised(seed):
    """Fuzz: every quaternion times 10^k, k in -40..38 (float32's whole range, 1e-13 and 1e30 included)."""
    scene = hard_scene(seed, n=30)
    g = torch.Generator().manual_seed(seed)
    exponents = torch.randint(-40, 39, (len(scene), 1), generator=g).double()
    exponents[:2, 0] = torch.tensor([-13.0, 30.0])
    quats = (scene.quats.double() * 10.0**exponents).float()
    assert torch.isfinite(quats).all() and (quats != 0).any(-1).all()
    unnormalised = GaussianScene(scene.means, quats, scene.log_scales, scene.opacity_logits, scene.sh)
    cams = make_cameras(EYES[:2])
    _assert_matches_brute_force(unnormalised, cams)
    assert torch.allclose(render(unnormalised, cams).rgb, render(scene, cams).rgb, atol=1e-4)


def test_zero_quaternion_is_the_identity_rotation():
    from artnvg_core.cameras import quat_to_rotmat

    assert torch.equal(quat_to_rotmat(torch.zeros(2, 4)), torch.eye(3).expand(2, 3, 3))


@pytest.mark.parametrize("huge", [(40.0, 42.0, 45.0), (30.0, 25.0, -3.0), (88.7, 88.7, 88.7)])
def test_huge_log_scales_match_float64_and_keep_gradients_finite(huge):
    """Gaussians far larger than the view (log-scales up to float32's exp limit, 88.7) cover it at
    their opacity; a float64 evaluation of the same Gaussians agrees, gradients stay finite."""
    scene = hard_scene(0, n=20)
    log_scales = scene.log_scales.clone()
    log_scales[[0, 5]] = torch.tensor(huge)
    params = dict(scene.tensors(), log_scales=log_scales)
    cams = make_cameras(EYES[:2])
    _assert_matches_brute_force(GaussianScene(**params), cams)
    params = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    out = render(GaussianScene(**params), cams, return_depth=True, backend="torch")
    (out.rgb.sum() + out.depth.sum()).backward()
    for name, p in params.items():
        assert torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("log_scale", [100.0, 1e4, 3e38])
def test_log_scales_beyond_exp_range_render_as_the_limit(log_scale):
    """exp(log-scale) overflows float32 above 88.7; such a Gaussian renders as one at 88.7 would."""
    scene = hard_scene(1, n=10)
    limit, beyond = scene.log_scales.clone(), scene.log_scales.clone()
    limit[3], beyond[3] = 88.7, log_scale
    cams = make_cameras(EYES)
    expected = render(GaussianScene(**dict(scene.tensors(), log_scales=limit)), cams)
    got = render(GaussianScene(**dict(scene.tensors(), log_scales=beyond)), cams)
    assert torch.equal(got.rgb, expected.rgb) and torch.equal(got.alpha, expected.alpha)
    assert (got.alpha > 0.3).all()  # the huge Gaussian covers every view


@pytest.mark.parametrize("value", [3e38, -3e38, 1e20])
def test_huge_sh_gives_finite_images_and_gradients(value):
    """Finite SH up to float32's limit: finite renders and gradients; renders clamped to [0, 1]
    equal those of SH just below the colour cap (a capped channel already saturates its pixel)."""
    scene = hard_scene(2, n=20)
    sh = scene.sh.clone()
    sh[:4] = value
    sh[4:6, 1:] = -value
    params = {k: v.clone().requires_grad_(True) for k, v in dict(scene.tensors(), sh=sh).items()}
    cams = make_cameras(EYES)
    out = render(GaussianScene(**params), cams, return_depth=True, backend="torch")
    assert torch.isfinite(out.rgb).all()
    (out.rgb.clamp(0, 1).sum() + out.depth.sum()).backward()
    for name, p in params.items():
        assert torch.isfinite(p.grad).all(), name
    if value == 1e20:  # float64 agrees once both are clamped to [0, 1]
        s = GaussianScene(**dict(scene.tensors(), sh=sh)).to(dtype=torch.float64)
        for c in range(len(cams)):
            rgb, _, _ = brute_force_render(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh,
                                           cams.world_to_cam[c], cams.intrinsics[c], 40, 32)
            assert np.abs(out.rgb[c].detach().clamp(0, 1).numpy() - np.clip(rgb, 0, 1)).max() <= 1e-4


def test_cameras_of_another_dtype_than_the_scene_render_as_the_scenes():
    """A float64 scene (the oracle) from a loader's float32 cameras stopped with torch's 'expected m1 and m2 to have
    the same dtype' from inside the projection."""
    scene, cams = hard_scene(0), make_cameras(EYES)
    cams64 = CameraSet(cams.world_to_cam.double(), cams.intrinsics.double(), cams.width, cams.height, cams.names)
    scene64 = scene.to(dtype=torch.float64)
    assert torch.equal(render(scene64, cams, backend="torch").rgb, render(scene64, cams64, backend="torch").rgb)
    assert torch.equal(render(scene, cams64, backend="torch").rgb, render(scene, cams, backend="torch").rgb)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_scenes_render_as_their_float32_copies(dtype):
    """float16 stopped with "value cannot be converted to type c10::Half without overflow" (the footprints'
    2^31 px cap, the colours' cap); bfloat16 rendered with its depths, pixel positions and radii rounded to
    8 bits, 0.7 off the float64 render of its own values at worst."""
    scene = hard_scene(1, n=60).to(dtype=dtype)
    cams = make_cameras(EYES[:2])
    params = {k: v.clone().requires_grad_() for k, v in scene.tensors().items()}
    out = render(GaussianScene(**params), cams, return_depth=True)
    expected = render(scene.to(dtype=torch.float32), cams, return_depth=True)
    for got, want in zip((out.rgb, out.alpha, out.depth), (expected.rgb, expected.alpha, expected.depth)):
        assert got.dtype == torch.float32 and torch.equal(got, want)
    out.rgb.sum().backward()
    for name, p in params.items():
        assert p.grad.dtype == dtype and torch.isfinite(p.grad).all(), name


def test_cpu_renders_beyond_half_the_memory_available_are_refused_before_any_work(monkeypatch):
    """A 16384x16384 view (CameraSet's largest) of a capture needs about 44 GiB on the CPU: the process was killed
    for memory; render now refuses it as the render nodes and the command line refuse theirs."""
    import artnvg_core.raster as raster

    monkeypatch.setattr(raster, "available_memory", lambda: 2**30)
    monkeypatch.setattr(raster, "project", lambda *args, **kwargs: pytest.fail("projected"))
    cams = make_cameras(EYES[:2], width=4096, height=2048)
    with pytest.raises(ValueError, match=r"^render: 2 views of 4096x2048 pixels, all their images held at once, need "
                                         r"1\.5 GiB, more than half the 1\.0 GiB of memory available now"):
        render(hard_scene(0, n=5), cams)
