"""render_views: every view in chunks equals one render per view; progress, stop and the CPU copy."""

import pytest
import torch

from artnvg_core.progress import Cancelled
from artnvg_core.raster import render
from artnvg_core.raster.views import render_views

from raster_scenes import hard_scene, make_cameras

EYES = [(0.0, -0.5, -3.0), (2.5, -0.4, -1.5), (-2.5, -0.6, -1.5), (0.3, -2.9, -0.5), (1.0, 0.5, 2.8)]


@pytest.mark.parametrize("chunk", [1, 2, 8])
def test_chunks_give_each_view_as_rendered_alone(chunk):
    scene, cameras = hard_scene(seed=3), make_cameras(EYES)
    calls = []
    out = render_views(scene, cameras, chunk=chunk, depth=True, progress=lambda *a: calls.append(a))
    for view in range(len(cameras)):
        alone = render(scene, cameras.subset([view]), return_depth=True)
        assert torch.equal(out.rgb[view], alone.rgb[0].clamp(0, 1))
        assert torch.equal(out.alpha[view], alone.alpha[0]) and torch.equal(out.depth[view], alone.depth[0])
    assert out.rgb.max() <= 1 and out.rgb.min() >= 0 and not out.rgb.requires_grad
    done = [0] + list(range(chunk, len(cameras), chunk)) + [len(cameras)]  # 0: a bar shows as the first chunk starts
    assert calls == [(n, len(cameras), {}) for n in done]


def test_cameras_of_no_views_give_no_views():
    """They stopped with torch.cat's "expected a non-empty list of Tensors"."""
    calls = []
    out = render_views(hard_scene(seed=3), make_cameras(EYES).subset([]), depth=True,
                       progress=lambda *a: calls.append(a))
    assert [tuple(x.shape) for x in (out.rgb, out.alpha, out.depth)] == [(0, 32, 40, 3), (0, 32, 40, 1), (0, 32, 40, 1)]
    assert calls == [(0, 0, {}), (0, 0, {})]


def _stop_at_ask(number: int, asked: list):
    def stop() -> bool:
        asked.append(True)
        return len(asked) >= number
    return stop


def test_without_depth_and_stopped_between_views():
    scene, cameras = hard_scene(seed=4), make_cameras(EYES)
    assert render_views(scene, cameras, cpu=True).depth is None
    asked: list = []
    render(scene, cameras.subset([0]), should_stop=_stop_at_ask(10**9, asked))
    per_view = len(asked)  # before the view, then before each batch of its tiles
    asked.clear()
    with pytest.raises(Cancelled):
        render_views(scene, cameras, chunk=2, should_stop=_stop_at_ask(per_view + 1, asked))  # before the second view
    assert len(asked) == per_view + 1
    with pytest.raises(ValueError, match="chunk"):
        render_views(scene, cameras, chunk=0)


def test_one_large_view_stops_between_its_batches_of_tiles():
    scene, view = hard_scene(seed=3), make_cameras(EYES[:1], width=512, height=512, focal=450.0)
    asked: list = []
    with pytest.raises(Cancelled):
        render_views(scene, view, should_stop=_stop_at_ask(3, asked))  # before the view, then twice inside it
    assert len(asked) == 3
