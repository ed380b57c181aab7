"""Cameras from the scene alone: robust frame, detected up, views that see the scene, bad input."""

import math

import pytest
import torch

from artnvg_core.__main__ import main
from artnvg_core.cameras import load_cameras, orbit_cameras, parse_up, scene_frame
from artnvg_core.formats import load_scene
from artnvg_core.raster import render
from artnvg_core.scene import GaussianScene
from artnvg_core.stylize import DemoInputs


def blob(means, seed=0):
    """Gaussians of scale 0.05 and opacity 0.5 at ``means`` [N, 3]."""
    n = len(means)
    g = torch.Generator().manual_seed(seed)
    return GaussianScene(means, torch.randn(n, 4, generator=g), torch.full((n, 3), math.log(0.05)),
                         torch.zeros(n), 0.3 * torch.randn(n, 1, 3, generator=g))


@pytest.mark.parametrize("name", ["bear", "face", "garden"])
def test_shared_scene_views_see_the_scene_and_up_matches_the_capture(shared_data, name):
    folder = shared_data / "scenes" / name
    scene = load_scene(folder / "scene.ply")
    capture = load_cameras(folder / "transforms.json")  # withheld from the rig; used only to check it
    capture_up = -capture.world_to_cam[:, 1, :3].double().mean(0)
    frame = scene_frame(scene)
    assert float(frame.up @ capture_up / capture_up.norm()) > 0.95, frame.up_source
    cameras = orbit_cameras(scene, 8, width=48, height=48)
    assert torch.isfinite(cameras.world_to_cam).all()
    with torch.no_grad():
        alpha = render(scene, cameras.subset([0, 5])).alpha[..., 0]
    assert (alpha.mean((1, 2)) > 0.6).all()  # the views are filled by the scene
    assert (alpha[:, 20:28, 20:28].mean((1, 2)) > 0.9).all()  # the subject sits in the middle
    # every view looks at the centre, from the subject-framing distance, with the scene's up above
    distances = (cameras.centers.double() - frame.center).norm(dim=1)
    assert torch.allclose(distances, torch.full_like(distances, frame.radius / math.sin(math.radians(25))))
    assert (-cameras.world_to_cam[:, 1, :3].double() @ frame.up > 0.8).all()


def test_far_floaters_and_a_sky_shell_do_not_move_the_frame():
    g = torch.Generator().manual_seed(1)
    ground = torch.cat([torch.rand(3000, 2, generator=g) * 4 - 2, 0.02 * torch.randn(3000, 1, generator=g)], 1)
    statue = torch.rand(1000, 3, generator=g) * torch.tensor([0.6, 0.6, 1.5])
    scene = blob(torch.cat([ground, statue]))
    frame = scene_frame(scene)
    assert frame.up_source == "ground normal" and float(frame.up[2]) > 0.99  # +z, the statue's side
    sky = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=1) * 1000  # 7 % of the weight
    floaters = torch.tensor([[3e5, 0.0, 0.0], [0.0, -2e5, 7e4]])
    noisy = blob(torch.cat([ground, statue, sky, floaters]))
    noisy.log_scales[4000:4300] = math.log(50.0)  # huge sky splats count no more than ordinary ones
    again = scene_frame(noisy)
    assert (again.center - frame.center).norm() < 0.1 and abs(again.radius - frame.radius) < 0.25 * frame.radius
    assert float(again.up @ frame.up) > 0.99


def test_counts_rings_size_and_fov():
    scene = blob(torch.randn(500, 3, generator=torch.Generator().manual_seed(2)))
    cameras = orbit_cameras(scene, 7, fov_deg=60, width=64, height=32, up="+z", elevations_deg=(0, 45, -20))
    assert len(cameras) == 7 and (cameras.width, cameras.height) == (64, 32)
    assert cameras.names[0] == "orbit_0000"
    assert float(cameras.intrinsics[0, 0, 0]) == pytest.approx(32 / math.tan(math.radians(30)))
    frame = scene_frame(scene, up="+z")
    heights = (cameras.centers.double() - frame.center)[:, 2]
    distance = float((cameras.centers[0].double() - frame.center).norm())
    # the vertical half angle (15.5 deg) is the smaller one: the sphere fits it
    assert distance == pytest.approx(frame.radius / math.sin(math.atan(16 / float(cameras.intrinsics[0, 0, 0]))))
    elevations = sorted({round(math.degrees(math.asin(h / distance))) for h in heights.tolist()})
    assert elevations == [-20, 0, 45]


def test_up_override_and_names():
    assert parse_up("auto") is None and parse_up(None) is None
    assert parse_up("-y").tolist() == [0.0, -1.0, 0.0] and parse_up("z").tolist() == [0.0, 0.0, 1.0]
    assert torch.allclose(parse_up([0, 3, 4]), torch.tensor([0, 0.6, 0.8], dtype=torch.float64))
    for bad in ("up", "+w", [0, 0, 0], [1, float("nan"), 0], [1, 2]):
        with pytest.raises(ValueError, match="up"):
            parse_up(bad)


def test_bad_scenes_raise_instead_of_nan_cameras():
    empty = blob(torch.zeros(0, 3))
    with pytest.raises(ValueError, match="no Gaussians"):
        orbit_cameras(empty)
    nan = blob(torch.full((10, 3), float("nan")))
    with pytest.raises(ValueError, match="finite"):
        orbit_cameras(nan)
    point = blob(torch.ones(10, 3) * 2.5)
    with pytest.raises(ValueError, match="one point"):
        orbit_cameras(point)
    some_nan = blob(torch.cat([torch.full((5, 3), float("nan")), torch.randn(50, 3)]))
    assert torch.isfinite(orbit_cameras(some_nan, 4).world_to_cam).all()
    for kwargs in ({"count": 0}, {"fov_deg": 180}, {"elevations_deg": (90,)}, {"distance_factor": 0}):
        with pytest.raises(ValueError, match="orbit_cameras"):
            orbit_cameras(some_nan, **kwargs)


def test_cli_stylize_and_render_without_cameras(tmp_path):
    demo = DemoInputs()
    out = tmp_path / "stylized.ply"
    assert main(["stylize", str(demo.scene), "--style", str(demo.style), "--out", str(out), "--stylizer", "nnfm",
                 "--iters", "2", "--orbit-views", "3", "--orbit-size", "32", "--device", "cpu"]) == 0
    assert len(load_scene(out)) == len(load_scene(demo.scene))
    assert main(["render", str(out), "--out", str(tmp_path / "renders"), "--orbit-views", "2", "--orbit-size", "24x16",
                 "--up=-x", "--device", "cpu"]) == 0
    assert sorted(p.name for p in (tmp_path / "renders").iterdir()) == ["orbit_0000.png", "orbit_0001.png"]
    assert main(["render", str(out), "--out", str(tmp_path / "r"), "--orbit-size", "0x3"]) == 2
