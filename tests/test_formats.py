"""The extension dispatch of load_scene / save_scene, and the writers' shared refusals."""

import os
import re

import pytest
import torch

from artnvg_core.formats import READERS, SAVE_SUFFIXES, load_scene, save_scene
from tests.test_formats_ply import assert_same_bits, random_scene


def test_load_and_save_dispatch_by_suffix_in_any_case(tmp_path):
    scene = random_scene(4, 2)
    upper = tmp_path / "SCENE.PLY"
    save_scene(scene, upper)
    assert_same_bits(load_scene(upper), scene)
    assert_same_bits(load_scene(str(upper)), scene)
    for suffix in (".spz", ".SPLAT"):
        save_scene(scene.select(slice(3, None)), tmp_path / f"scene{suffix}")  # rows 0-2 exceed their ranges
        assert load_scene(tmp_path / f"scene{suffix}").sh_degree == (2 if suffix == ".spz" else 0)

    (tmp_path / "scene.obj").write_bytes(b"v 0 0 0\n")
    with pytest.raises(ValueError, match=r"scene\.obj: unsupported scene file type '\.obj'; expected \.ply .*\.ckpt"):
        load_scene(tmp_path / "scene.obj")
    with pytest.raises(ValueError, match=r"missing\.ckpt: scene file not found; expected \.ply"):
        load_scene(tmp_path / "missing.ckpt")
    for folder in (tmp_path / "capture", tmp_path / "capture.ply"):  # a folder with any name is named as one
        folder.mkdir()
        with pytest.raises(ValueError, match=rf"^{folder}: scene file is a folder, not a regular file; expected \.ply "
                                             r"\(INRIA 3DGS or compressed PLY\), \.splat, \.spz, \.ksplat or \.ckpt"):
            load_scene(folder)
    with pytest.raises(ValueError, match=r"scene\.ckpt: cannot write scene file type '\.ckpt'; expected one of"):
        save_scene(scene, tmp_path / "scene.ckpt")


@pytest.mark.parametrize("suffix", SAVE_SUFFIXES)
def test_every_writer_keeps_a_file_it_may_not_overwrite(tmp_path, suffix):
    scene = random_scene(4, 0).select(slice(3, None))  # within every format's ranges
    taken = tmp_path / f"scene{suffix}"
    taken.write_bytes(b"another writer's")
    with pytest.raises(FileExistsError, match=re.escape(str(taken))):
        save_scene(scene, taken, overwrite=False)
    assert taken.read_bytes() == b"another writer's" and list(tmp_path.iterdir()) == [taken]
    save_scene(scene, tmp_path / f"new{suffix}", overwrite=False)
    assert len(load_scene(tmp_path / f"new{suffix}")) == 1


@pytest.mark.parametrize(("option", "value"), [("spz_version", 4), ("spz_version", "2"), ("spz_axes", "up")])
def test_a_bad_spz_option_is_refused_by_name_before_writing(tmp_path, option, value):
    with pytest.raises(ValueError, match=rf"{option}: expected one of .*, got {value!r}"):
        save_scene(random_scene(4, 1), tmp_path / "scene.spz", **{option: value})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", SAVE_SUFFIXES)
@pytest.mark.parametrize(("field", "value"), [("means", float("nan")), ("log_scales", float("inf")),
                                              ("sh", -float("inf")), ("quats", 0.0)])
def test_writers_refuse_invalid_scenes_before_writing(tmp_path, suffix, field, value):
    scene = random_scene(6, 1)
    getattr(scene, field)[4] = value
    path = tmp_path / f"bad{suffix}"
    problem = "a zero norm" if value == 0 else "non-finite values"
    with pytest.raises(ValueError, match=rf"bad\{suffix}: not written: {field}: 1 of 6 Gaussians has {problem} "
                                         r"\(first at index 4\)"):
        save_scene(scene, path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", SAVE_SUFFIXES)
def test_writers_refuse_an_empty_scene_before_writing(tmp_path, suffix):
    """Before any format's own work (the .spz writer's choice of fractional bits needs a Gaussian)."""
    path = tmp_path / f"empty{suffix}"
    with pytest.raises(ValueError, match=rf"empty\{suffix}: not written: the scene contains no Gaussians$"):
        save_scene(random_scene(4, 1).select(slice(0, 0)), path)
    assert list(tmp_path.iterdir()) == []


def test_float64_beyond_float32_is_refused_not_written_as_inf(tmp_path):
    scene = random_scene(3, 0).map(lambda t: t.double())
    scene.sh[1, 0, 0] = 1e300
    with pytest.raises(ValueError, match=r"huge\.ply: not written: sh: 1 of 3 .*non-finite"):
        save_scene(scene, tmp_path / "huge.ply")
    assert torch.isfinite(scene.sh).all()


def test_a_scene_whose_content_is_not_its_extensions_format_says_what_it_starts_with(tmp_path):
    """A .splat renamed .ply was reported as a PLY header with no end_header in its first MiB."""
    scene = random_scene(8, 0).select(slice(3, None))  # rows 0-2 exceed the .splat's and the .spz's ranges
    for suffix in (".splat", ".spz", ".ply"):
        save_scene(scene, tmp_path / f"scene{suffix}")
    (tmp_path / "scene.splat").rename(tmp_path / "splat.ply")
    (tmp_path / "scene.spz").rename(tmp_path / "spz.ply")
    (tmp_path / "scene.ply").rename(tmp_path / "ply.spz")
    (tmp_path / "empty.ply").write_bytes(b"")
    for name, message in [
            ("splat.ply", r"not a \.ply file \(it starts with bytes ([0-9a-f]{2} ){7}[0-9a-f]{2}, no format's signature; a "
                          r"headerless antimatter15 \.splat or a \.ksplat cannot be recognized by its content: if it is "
                          r"one, rename it \.splat or \.ksplat\)"),
            ("spz.ply", r"not a \.ply file \(it starts with bytes 1f 8b .*: a gzip stream, as an SPZ file of version 1-3\); "
                        r"rename it \.spz"),
            ("ply.spz", r"not a \.spz file \(it starts with bytes 70 6c 79 0a .*: a PLY header\); rename it \.ply"),
            ("empty.ply", r"not a \.ply file \(it is empty, no format's signature;")]:
        with pytest.raises(ValueError, match=rf"^{re.escape(str(tmp_path / name))}: {message}"):
            load_scene(tmp_path / name)


@pytest.mark.parametrize("suffix", [".splat", ".ksplat", ".ckpt"])
@pytest.mark.parametrize("renamed", [".ply", ".spz"])
def test_a_scene_renamed_to_a_format_without_a_signature_says_what_it_starts_with_when_refused(tmp_path, suffix,
                                                                                               renamed):
    """A PLY renamed .splat was reported as 'not a multiple of the 32-byte record' alone: a format with no
    signature is read as it is named (a .splat's floats may start with any bytes), and the reader's refusal then
    says what the file starts with."""
    save_scene(random_scene(8, 0).select(slice(3, None)), tmp_path / f"scene{renamed}")
    (tmp_path / f"scene{renamed}").rename(tmp_path / f"scene{suffix}")
    what = {".ply": "a PLY header", ".spz": "a gzip stream, as an SPZ file of version 1-3"}[renamed]
    with pytest.raises(ValueError, match=rf"scene\{suffix}: .+; it starts with {what}: if it is one, rename it "
                                         rf"\{renamed}$"):
        load_scene(tmp_path / f"scene{suffix}")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
@pytest.mark.parametrize("suffix", [".ply", ".spz", ".splat", ".ksplat", ".ckpt"])
def test_a_fifo_is_refused_by_every_reader_without_reading(tmp_path, suffix):
    os.mkfifo(tmp_path / f"pipe{suffix}")
    with pytest.raises(ValueError, match=rf"pipe\{suffix}: scene file is a FIFO \(named pipe\), not a regular file"):
        load_scene(tmp_path / f"pipe{suffix}")
    with pytest.raises(ValueError, match=rf"pipe\{suffix}: scene file is a FIFO"):
        READERS[suffix](tmp_path / f"pipe{suffix}")
