"""Scenes exchanged with PlayCanvas splat-transform (the converter behind SuperSplat) and spz-js load upright
both ways with default settings, for every format each tool reads and writes. The tools are pinned in
tests/npm/package.json and installed on first use (tests/npm_tools.py); without node and npm these tests
are skipped."""

import pytest
import torch

from artnvg_core.cli.main import main
from artnvg_core.formats import load_scene, save_scene
from artnvg_core.stylize import DemoInputs
from tests.npm_tools import splat_transform, spz_js

FLIP = torch.tensor([1.0, -1, -1])  # the PLY's axes <-> RUB


def _source():
    return load_scene(DemoInputs().scene).select(slice(0, None, 40))


def _nearest(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[N] distance from each point of ``a`` to the nearest point of ``b`` (orders may differ)."""
    return torch.cdist(a.double(), b.double()).min(1).values


def _extent(scene) -> float:
    return float((scene.means.max(0).values - scene.means.min(0).values).max())


def _assert_upright(source, back, label) -> None:
    """Each Gaussian of ``source`` lies within a format's quantisation of one of ``back``."""
    assert len(back) == len(source), label
    assert _nearest(source.means, back.means).max() < 2e-3 * _extent(source), label


@pytest.mark.parametrize("theirs", ["p.ply", "c.compressed.ply", "s.spz"])
def test_splat_transforms_files_load_upright_here(tmp_path, npm_tools, theirs):
    """Its .spz (version 4, no coordinate-system record) is read by default in the PLY's axes; read as RUB,
    the format's description, the same Gaussians come back upside down, which this check tells apart."""
    source = _source()
    save_scene(source, tmp_path / "source.ply")
    splat_transform(tmp_path / "source.ply", tmp_path / theirs)
    _assert_upright(source, load_scene(tmp_path / theirs), theirs)
    if theirs.endswith(".spz"):
        assert (tmp_path / theirs).read_bytes()[:4] == b"NGSP"
        upside_down = load_scene(tmp_path / theirs, spz_axes="rub").means
        assert _nearest(source.means, upside_down * FLIP).max() < 2e-3 * _extent(source)
        assert _nearest(source.means, upside_down).median() > 1e-2 * _extent(source)


@pytest.mark.parametrize("ours", ["o.ply", "o.splat", "o.ksplat", "o.spz"])
def test_our_files_load_upright_in_splat_transform(tmp_path, npm_tools, ours):
    """Ours, written with default settings, converted to PLY by splat-transform hold the source's positions."""
    source = _source()
    save_scene(source, tmp_path / ours)
    splat_transform(tmp_path / ours, tmp_path / "back.ply")
    _assert_upright(source, load_scene(tmp_path / "back.ply"), ours)


def test_spz_js_files_load_upright_here_and_ours_there(tmp_path, npm_tools):
    """spz-js writes version 2 in the PLY's axes and reads versions 1-2 only: its .spz loads upright here by
    default, and ours written through the command line with --spz-version 2 (default axes) converts back to
    the source's PLY there. Opacities stay below 254.5 / 255: spz-js writes a stored 255 to its PLY as an
    infinite logit."""
    source = _source()
    source.opacity_logits.clamp_(max=4.0)
    save_scene(source, tmp_path / "source.ply")
    spz_js(tmp_path / "source.ply", tmp_path / "theirs.spz")
    _assert_upright(source, load_scene(tmp_path / "theirs.spz"), "spz-js .spz")
    ply = str(tmp_path / "source.ply")  # blended with itself at strength 1: the scene, written as given
    assert main(["blend", ply, ply, "--strength", "1", "--out", str(tmp_path / "ours.spz"), "--spz-version", "2"]) == 0
    spz_js(tmp_path / "ours.spz", tmp_path / "back.ply")
    _assert_upright(source, load_scene(tmp_path / "back.ply"), "our .spz through spz-js")
