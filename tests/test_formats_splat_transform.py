"""Scenes exchanged with PlayCanvas splat-transform (the converter behind SuperSplat) load upright both
ways, for every format both tools read and write; its .spz files hold the PLY's axes (``spz_axes="ply"``).

The exchange tests need splat-transform 3.7: ``npm install @playcanvas/splat-transform@3.7.0`` in a folder
outside the project, then ``SPLAT_TRANSFORM=<folder>/node_modules/.bin/splat-transform`` (or the command
on PATH); without it they are skipped. The axes option's own round trip needs nothing.
"""

import gzip
import os
import shutil
import struct
import subprocess

import numpy as np
import pytest
import torch

from artnvg_core.formats import load_scene, save_scene
from artnvg_core.formats.spz import read_spz, write_spz
from artnvg_core.stylize import DemoInputs
from tests.test_formats_splat import quat_error
from tests.test_formats_spz import payload_arrays, version_4

FLIP = torch.tensor([1.0, -1, -1])


def test_spz_axes_ply_reads_and_writes_the_plys_axes_and_a_files_own_record_wins(tmp_path):
    scene = load_scene(DemoInputs().scene).select(slice(0, None, 40))
    write_spz(scene, tmp_path / "ply_axes.spz", axes="ply")
    _, arrays = payload_arrays(tmp_path / "ply_axes.spz")
    fixed = np.frombuffer(arrays["positions"], np.uint8).reshape(-1, 3, 3).astype(np.int64)
    stored = fixed[..., 0] | fixed[..., 1] << 8 | fixed[..., 2] << 16
    stored = np.where(stored >= 1 << 23, stored - (1 << 24), stored) / 4096
    np.testing.assert_allclose(stored, scene.means.numpy(), atol=2.0**-12)  # as they are: no flip
    as_ply = load_scene(tmp_path / "ply_axes.spz", spz_axes="ply")
    write_spz(scene, tmp_path / "rub.spz")
    as_rub = read_spz(tmp_path / "rub.spz")
    steps = {"means": 2.0**-12, "sh": 1 / 8}  # one rounding step (halves round up: -x and x may differ by one)
    for name, value in as_rub.tensors().items():  # the two conventions undo each other
        if name != "quats":
            torch.testing.assert_close(getattr(as_ply, name), value, rtol=0, atol=steps.get(name, 0), msg=name)
    assert quat_error(as_ply.quats, as_rub.quats) <= 0.002  # up to the sign of q
    torch.testing.assert_close(read_spz(tmp_path / "ply_axes.spz").means, as_rub.means * FLIP, rtol=0, atol=2.0**-12)
    header, arrays = payload_arrays(tmp_path / "rub.spz")
    record = struct.pack("<II", 0xADBE0002, 0) + struct.pack("<III", 0xADBE0003, 4, 4)  # names RUB
    (tmp_path / "named.spz").write_bytes(version_4(header, arrays, record))
    assert torch.equal(read_spz(tmp_path / "named.spz", axes="ply").means, as_rub.means)
    with pytest.raises(ValueError, match="spz_axes: expected one of rub, ply, got 'up'"):
        load_scene(tmp_path / "rub.spz", spz_axes="up")
    save_scene(scene, tmp_path / "saved.spz", spz_axes="ply")
    assert gzip.decompress((tmp_path / "saved.spz").read_bytes()) == gzip.decompress(
        (tmp_path / "ply_axes.spz").read_bytes())


def _splat_transform() -> str | None:
    return os.environ.get("SPLAT_TRANSFORM") or shutil.which("splat-transform")


def _convert(source, target) -> None:
    subprocess.run([_splat_transform(), "-q", "-w", str(source), str(target)], check=True, capture_output=True,
                   timeout=300)


def _nearest(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[N] distance from each point of ``a`` to the nearest point of ``b`` (orders may differ)."""
    return torch.cdist(a.double(), b.double()).min(1).values


needs_splat_transform = pytest.mark.skipif(_splat_transform() is None, reason="splat-transform not installed "
                                           "(npm install @playcanvas/splat-transform@3.7.0; SPLAT_TRANSFORM=...)")


@needs_splat_transform
@pytest.mark.parametrize("theirs", ["p.ply", "c.compressed.ply", "s.spz"])
def test_their_files_load_upright_here(tmp_path, theirs):
    """Each Gaussian of the source lies within its format's quantisation of one in their file; their .spz
    needs spz_axes="ply" (read by the format's rule it comes back with y and z flipped)."""
    source = load_scene(DemoInputs().scene).select(slice(0, None, 40))
    save_scene(source, tmp_path / "source.ply")
    _convert(tmp_path / "source.ply", tmp_path / theirs)
    options = {"spz_axes": "ply"} if theirs.endswith(".spz") else {}
    back = load_scene(tmp_path / theirs, **options)
    assert len(back) == len(source)
    extent = float((source.means.max(0).values - source.means.min(0).values).max())
    assert _nearest(source.means, back.means).max() < 2e-3 * extent, theirs
    if theirs.endswith(".spz"):
        assert _nearest(source.means, load_scene(tmp_path / theirs).means * FLIP).max() < 2e-3 * extent
        assert _nearest(source.means, load_scene(tmp_path / theirs).means).median() > 1e-2 * extent


@needs_splat_transform
@pytest.mark.parametrize("ours, options", [("o.ply", {}), ("o.splat", {}), ("o.ksplat", {}),
                                           ("o.spz", {"spz_axes": "ply"})])
def test_our_files_load_upright_there(tmp_path, ours, options):
    """Ours converted to PLY by splat-transform hold the source's positions; a .spz written in the PLY's
    axes is what it reads upright."""
    source = load_scene(DemoInputs().scene).select(slice(0, None, 40))
    save_scene(source, tmp_path / ours, **options)
    _convert(tmp_path / ours, tmp_path / "back.ply")
    back = load_scene(tmp_path / "back.ply")
    extent = float((source.means.max(0).values - source.means.min(0).values).max())
    assert len(back) == len(source) and _nearest(source.means, back.means).max() < 2e-3 * extent, ours
