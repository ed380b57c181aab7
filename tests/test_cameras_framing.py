"""Where a scene is and which way is up, from the Gaussians alone: a robust frame, an explicit up."""

import math

import pytest
import torch

from artnvg_core.cameras import parse_up, scene_frame
from artnvg_core.scene import GaussianScene


def blob(means, seed=0):
    """Gaussians of scale 0.05 and opacity 0.5 at ``means`` [N, 3]."""
    n = len(means)
    g = torch.Generator().manual_seed(seed)
    return GaussianScene(means, torch.randn(n, 4, generator=g), torch.full((n, 3), math.log(0.05)),
                         torch.zeros(n), 0.3 * torch.randn(n, 1, 3, generator=g))


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


@pytest.mark.parametrize("far", [1e12, 3e38])
def test_floaters_past_a_billion_times_the_subject_do_not_become_its_radius(far):
    """Two floaters 1e12 (or 3e38, float32's limit) away took the radius for theirs: a subject radius under 1e-9 of
    the farthest distance was taken for "the weight at the centre itself", and the views were placed that far out
    (non-finite float32 poses at 3e38)."""
    g = torch.Generator().manual_seed(2)
    subject = torch.rand(1000, 3, generator=g) - 0.5
    frame = scene_frame(blob(subject), up="+z")
    again = scene_frame(blob(torch.cat([subject, torch.tensor([[far, 0.0, 0.0], [0.0, -far, far]])])), up="+z")
    assert (again.center - frame.center).norm() < 0.01 and abs(again.radius - frame.radius) < 0.01 * frame.radius


def test_floaters_under_the_ground_do_not_turn_up_down():
    """Up is the ground normal's side the mass reaches further to (a statue), even when a few floaters deep under the
    ground (2.4 % of the weight) outweigh the statue in the heights' third moment."""
    g = torch.Generator().manual_seed(1)
    ground = torch.cat([torch.rand(3000, 2, generator=g) * 4 - 2, 0.02 * torch.randn(3000, 1, generator=g)], 1)
    statue = torch.rand(1000, 3, generator=g) * torch.tensor([0.6, 0.6, 1.5])
    below = torch.cat([torch.rand(100, 2, generator=g) * 2 - 1, torch.full((100, 1), -1.8)], 1)
    for scene in (blob(torch.cat([ground, statue, below])), blob(-torch.cat([ground, statue, below]))):
        frame = scene_frame(scene)
        assert frame.up_source == "ground normal"
        assert float(frame.up @ scene.means[3000:4000].mean(0).double()) > 0  # towards the statue, either way round
        assert abs(float(frame.up[2])) > 0.99

def test_up_override_and_names():
    assert parse_up("auto") is None and parse_up(None) is None
    assert parse_up("-y").tolist() == [0.0, -1.0, 0.0] and parse_up("z").tolist() == [0.0, 0.0, 1.0]
    assert torch.allclose(parse_up([0, 3, 4]), torch.tensor([0, 0.6, 0.8], dtype=torch.float64))
    assert torch.allclose(parse_up(" 0, 3,4 "), parse_up([0, 3, 4]))  # text, as --up and the node's input take it
    for bad in ("up", "+w", "0, x, 1", "1, 2", "nan, 0, 1", [0, 0, 0], [1, float("nan"), 0], [1, 2]):
        with pytest.raises(ValueError, match="^up: expected"):
            parse_up(bad, "up")
