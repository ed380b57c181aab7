"""``python -m artnvg_core blend``: a region blended at a strength, written in every format; refusals."""

import dataclasses
import gzip
import struct

import numpy as np
import pytest
import torch

from artnvg_core.cli.main import main
from artnvg_core.formats import load_scene, save_scene, write_ply
from artnvg_core.scene import SH_C0, GaussianScene
from artnvg_core.stylize import DemoInputs

BOX = "box:-1,-1,-1,1,1,1"


def _pair(tmp_path) -> tuple[GaussianScene, GaussianScene]:
    """1,000 Gaussians of the demo bear with SH raised to degree 3, and a recoloured copy, written as PLY."""
    original = load_scene(DemoInputs().scene).select(slice(0, None, 40))
    g = torch.Generator().manual_seed(0)
    sh = torch.cat([original.sh, 0.05 * torch.randn(len(original), 12, 3, generator=g)], 1)
    original = dataclasses.replace(original, sh=sh)
    stylized = dataclasses.replace(original, sh=sh + 0.3 * torch.randn(sh.shape, generator=g),
                                   opacity_logits=original.opacity_logits - 1)
    write_ply(original, tmp_path / "original.ply")
    write_ply(stylized, tmp_path / "stylized.ply")
    return original, stylized


def _inside(scene: GaussianScene) -> torch.Tensor:
    return (scene.means.abs() <= 1).all(1)


def test_a_region_blended_at_a_strength_is_written_exactly_as_ply(tmp_path, capsys):
    original, stylized = _pair(tmp_path)
    out = tmp_path / "blend.ply"
    assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "0.25",
                 "--region", BOX, "--out", str(out)]) == 0
    inside = _inside(original)
    assert 0 < inside.sum() < len(original)
    captured = capsys.readouterr()
    printed = captured.out
    assert f"region: {int(inside.sum()):,} of 1,000 Gaussians selected" in printed and "blended at strength 0.25" in printed
    assert "loading" not in captured.err and "saving" not in captured.err  # milliseconds each: no bar (seconds
    # for millions of Gaussians draw one: test_cli_main's test of ProgressBar's delay)
    result = load_scene(out)
    assert result.sh_degree == 3
    for name, value in result.tensors().items():
        before, after = getattr(original, name), getattr(stylized, name)
        assert torch.equal(value[~inside], before[~inside]), name
        expected = 0.75 * before[inside].double() + 0.25 * after[inside].double()
        torch.testing.assert_close(value[inside].double(), expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("suffix, degree, tolerance", [(".spz", 3, 0.02), (".ksplat", 2, 0.02), (".splat", 0, 0.02)])
def test_the_blend_is_written_in_every_format_with_the_sh_it_holds(tmp_path, suffix, degree, tolerance):
    original, stylized = _pair(tmp_path)
    exact, out = tmp_path / "blend.ply", tmp_path / f"blend{suffix}"
    for path in (exact, out):
        assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "0.5",
                     "--region", BOX, "--out", str(path)]) == 0
    reference, result = load_scene(exact), load_scene(out)
    assert result.sh_degree == degree and len(result) == len(reference)
    if suffix == ".spz":  # same order: the colours of every band, quantised
        kept = (degree + 1) ** 2
        np.testing.assert_allclose(result.sh.numpy(), reference.sh[:, :kept].numpy(), rtol=0, atol=tolerance * 8)
    # every format holds the blended base colours (SH DC), in its own order: matched by nearest position
    nearest = torch.cdist(result.means.double(), reference.means.double()).argmin(1)
    assert len(set(nearest.tolist())) == len(reference)
    colour = lambda sh: (sh[:, 0] * SH_C0 + 0.5).clamp(0, 1)  # noqa: E731
    np.testing.assert_allclose(colour(result.sh).numpy(), colour(reference.sh[nearest]).numpy(), rtol=0, atol=tolerance)


def _spz_version(path) -> int:
    """The version in a version 1-3 .spz's header (after the magic, inside its gzip stream)."""
    return struct.unpack_from("<I", gzip.decompress(path.read_bytes()), 4)[0]


def test_spz_version_2_is_written_on_request_and_reads_back_as_the_default_version_3(tmp_path):
    """--spz-version 2 (for spz-js, which reads versions 1-2 only): its header says 2, and it reads back as
    the default version 3 does, but for the rotations, whose x y z it stores in 8 bits (w >= 0 derived)."""
    _pair(tmp_path)
    for name, extra in (("v3", []), ("v2", ["--spz-version", "2"])):
        assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "0.5",
                     "--out", str(tmp_path / f"{name}.spz"), *extra]) == 0
    assert (_spz_version(tmp_path / "v3.spz"), _spz_version(tmp_path / "v2.spz")) == (3, 2)
    v3, v2 = load_scene(tmp_path / "v3.spz"), load_scene(tmp_path / "v2.spz")
    for name, value in v3.tensors().items():
        if name != "quats":
            assert torch.equal(getattr(v2, name), value), name
    a, b = (q[:, 1:] / q.norm(dim=1, keepdim=True) for q in (v2.quats.double(), v3.quats.double()))  # x y z of unit q
    error = torch.minimum((a - b).abs().amax(1), (a + b).abs().amax(1))  # q and -q are one rotation
    assert error.max() <= 0.5 / 127.5 + 0.002  # the two versions' bounds (formats/spz.py)


@pytest.mark.parametrize("extra, message", [
    (["--region", "box:1,2"], "--region: a box takes 6 finite numbers, XMIN, YMIN, ZMIN, XMAX, YMAX, ZMAX"),
    (["--region-mask", "0:mask.png"], "--region-mask needs --cameras"),
    (["--region", BOX, "--region-mask", "0:m.png", "--cameras", "t.json"], "--region or --region-mask, not both"),
])
def test_bad_regions_are_refused_before_loading(tmp_path, capsys, extra, message):
    assert main(["blend", "a.ply", "b.ply", "--strength", "0.5", "--out", str(tmp_path / "o.ply"), *extra]) == 2
    captured = capsys.readouterr()
    assert message in captured.err and "loading" not in captured.out


def test_scenes_that_do_not_correspond_are_refused_naming_both(tmp_path, capsys):
    original, _ = _pair(tmp_path)
    write_ply(original.select(slice(1, None)), tmp_path / "other.ply")
    out = tmp_path / "blend.ply"
    assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "other.ply"), "--strength", "0.5",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"cannot blend {tmp_path / 'original.ply'} and {tmp_path / 'other.ply'}" in err and "1,000 Gaussians" in err
    assert not out.exists()


@pytest.mark.parametrize("value", ["-0.1", "1.01", "nan"])
def test_strength_outside_zero_to_one_exits_2(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as exit_:
        main(["blend", "a.ply", "b.ply", "--strength", value, "--out", str(tmp_path / "o.ply")])
    assert exit_.value.code == 2 and "argument --strength: expected a number from 0 to 1" in capsys.readouterr().err


def test_what_the_output_format_drops_is_printed_once_and_not_logged(tmp_path, capsys, caplog):
    _pair(tmp_path)
    with caplog.at_level("INFO"):
        assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "0.5",
                     "--out", str(tmp_path / "blend.ksplat")]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed.count("note: .ksplat holds SH up to degree 2; the degree 3 view-dependent terms are dropped") == 1
    assert printed[-1].startswith("blended at strength 0.5") and len([line for line in printed if "note" in line]) == 1
    assert not [record for record in caplog.records if "view-dependent" in record.getMessage()]


def test_what_each_scenes_read_did_is_printed_once_under_its_loading_line(tmp_path, capsys, caplog):
    """Two .spz files that name no axes: each load prints its note between its own two lines."""
    original, stylized = _pair(tmp_path)
    for name, scene in (("original", original), ("stylized", stylized)):
        save_scene(scene, tmp_path / f"{name}.spz")
    with caplog.at_level("INFO"):
        assert main(["blend", str(tmp_path / "original.spz"), str(tmp_path / "stylized.spz"), "--strength", "0.5",
                     "--out", str(tmp_path / "blend.ply")]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert [line.split()[0] for line in lines[:6]] == ["loading", "note:", "loaded"] * 2
    assert lines[1].startswith("note: the file names no axes: read in the PLY's axes (x right, y down, z forward)")
    assert lines[0].startswith(f"loading {tmp_path / 'original.spz'}")
    assert lines[3].startswith(f"loading {tmp_path / 'stylized.spz'}") and lines[4] == lines[1]
    assert captured.out.count("names no axes") == 2 and "names no axes" not in captured.err
    assert not [record for record in caplog.records if "names no axes" in record.getMessage()]
