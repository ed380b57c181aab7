"""Image reading at any bit depth and size, output-path checks, files written together or not at all."""

import os
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from artnvg_core.fileio import (
    MAX_IMAGE_PIXELS,
    check_output_file,
    check_output_folder,
    image_size,
    load_image,
    refuse_overwrites,
    write_atomically,
    written_together,
)


@pytest.mark.parametrize("seed", range(3))
def test_16_bit_greyscale_png_is_scaled_by_65535(tmp_path, seed):
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 65536, size=(rng.integers(1, 40), rng.integers(1, 40)), dtype=np.uint16)
    Image.fromarray(values).save(tmp_path / "grey16.png")
    image = load_image(tmp_path / "grey16.png").numpy()
    assert image.shape == (*values.shape, 3) and image.dtype == np.float32
    for channel in range(3):
        np.testing.assert_allclose(image[..., channel], values / 65535.0, rtol=0, atol=1e-7)


def test_float_tiff_kept_in_unit_range_else_rescaled(tmp_path):
    rng = np.random.default_rng(0)
    unit = rng.random((17, 23), dtype=np.float32)
    Image.fromarray(unit).save(tmp_path / "unit.tif")
    assert np.array_equal(load_image(tmp_path / "unit.tif").numpy()[..., 1], unit)
    wide = unit * 400 - 100
    Image.fromarray(wide).save(tmp_path / "wide.tif")
    np.testing.assert_allclose(load_image(tmp_path / "wide.tif").numpy()[..., 2],
                               (wide - wide.min()) / (wide.max() - wide.min()), atol=1e-6)
    flat = np.full((4, 4), 7.0, np.float32)
    Image.fromarray(flat).save(tmp_path / "flat.tif")
    assert (load_image(tmp_path / "flat.tif") == 0).all()
    unit[3, 4] = np.nan
    Image.fromarray(unit).save(tmp_path / "nan.tif")
    with pytest.raises(ValueError, match="nan.tif.*NaN"):
        load_image(tmp_path / "nan.tif")


@pytest.mark.parametrize("mode", ["L", "P", "RGBA", "LA", "1", "CMYK", "RGB"])
def test_8_bit_modes_match_pillows_rgb(tmp_path, mode):
    rng = np.random.default_rng(1)
    rgb = Image.fromarray(rng.integers(0, 256, (9, 13, 3), dtype=np.uint8))
    image = rgb.convert(mode)
    path = tmp_path / f"x.{'jpg' if mode == 'CMYK' else 'png'}"
    image.save(path, **({"quality": 100} if mode == "CMYK" else {}))
    with Image.open(path) as stored:
        expected = np.asarray(stored.convert("RGB"), np.float32) / 255
    assert np.array_equal(load_image(path).numpy(), expected)


def test_max_side_on_a_16_bit_image_stays_in_unit_range(tmp_path):
    values = np.zeros((60, 90), np.uint16)
    values[::2] = 65535  # stripes: Lanczos overshoots, the result is clamped
    Image.fromarray(values).save(tmp_path / "stripes.png")
    image = load_image(tmp_path / "stripes.png", max_side=30)
    assert image.shape == (20, 30, 3) and image.min() >= 0 and image.max() <= 1


def _png_header_only(path, width, height):
    """A PNG whose header declares width x height (no pixel data): enough for Image.open."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IEND", b""))


@pytest.mark.parametrize("width, height", [(40000, 40000), (10000, 9000), (2**31 - 1, 2)])
def test_huge_images_refused_before_decoding_with_their_size(tmp_path, width, height):
    assert width * height > MAX_IMAGE_PIXELS
    path = tmp_path / "huge.png"
    _png_header_only(path, width, height)
    with pytest.raises(ValueError, match=rf"huge.png: image .*({width}x{height}|{width * height} pixels)"):
        load_image(path)


def test_pixel_budget_is_read_from_the_header_before_decoding(tmp_path):
    """9400 x 9400 lies under Pillow's own limit (89 MP) and once decoded to 3.1 GB: refused from its
    header by the stated 64 MP budget, naming the file, the field and the cap; image_size reads the
    header alone."""
    assert 9400 * 9400 < Image.MAX_IMAGE_PIXELS
    _png_header_only(tmp_path / "big.png", 9400, 9400)
    for read in (load_image, image_size):
        with pytest.raises(ValueError, match=r"big\.png: image size: 9400x9400 pixels, more than the 64,000,000 "
                           r"pixels \(e\.g\. 8000x8000\) decoded at most"):
            read(tmp_path / "big.png")
    _png_header_only(tmp_path / "wide.png", 8000, 8000)
    assert image_size(tmp_path / "wide.png") == (8000, 8000)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_a_fifo_or_folder_is_refused_without_reading(tmp_path):
    """A read of a FIFO waits for a writer for ever: refused from its file type, as is a folder."""
    os.mkfifo(tmp_path / "style.png")
    (tmp_path / "folder.png").mkdir()
    for name, kind in [("style.png", r"FIFO \(named pipe\)"), ("folder.png", "folder")]:
        for read in (load_image, image_size):
            with pytest.raises(ValueError, match=rf"{name}: image file is a {kind}, not a regular file"):
                read(tmp_path / name)
    with pytest.raises(ValueError, match=r"gone\.png: image file not found"):
        load_image(tmp_path / "gone.png")


def test_output_file_checks(tmp_path):
    for bad, message in [("", "empty"), ("  ", "empty"), (tmp_path, "is a folder")]:
        with pytest.raises(ValueError, match=f"--out: .*{message}"):
            check_output_file(bad, "--out")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="--out: cannot write .*file is a file, not a folder"):
        check_output_file(tmp_path / "file" / "sub" / "a.ply", "--out")
    with pytest.raises(ValueError, match="--out: .*exists and is not a folder"):
        check_output_folder(tmp_path / "file", "--out")
    assert check_output_file(tmp_path / "new" / "deeper" / "a.ply", "--out") == tmp_path / "new" / "deeper" / "a.ply"
    assert check_output_folder(tmp_path / "renders", "--out") == tmp_path / "renders"
    assert sorted(os.listdir(tmp_path)) == ["file"]  # checking created nothing


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="needs a user that read-only folders stop")
def test_read_only_folder_refused(tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(ValueError, match="not writable"):
            check_output_file(folder / "a.ply", "--out")
    finally:
        folder.chmod(0o700)


def test_written_together_all_or_nothing(tmp_path):
    a, b = tmp_path / "out" / "a.ply", tmp_path / "out" / "a.contact.png"
    with pytest.raises(RuntimeError, match="boom"):
        with written_together(a, b) as (ta, tb):
            assert ta.suffix == ".ply" and tb.suffix == ".png" and ta.parent == a.parent
            ta.write_text("new a")
            raise RuntimeError("boom")
    assert os.listdir(tmp_path / "out") == []
    with written_together(a, b) as (ta, tb):
        ta.write_text("a")
        tb.write_text("b")
    assert a.read_text() == "a" and b.read_text() == "b" and sorted(os.listdir(a.parent)) == [b.name, a.name]
    b.unlink()
    b.mkdir()  # a folder where the second file goes: neither is replaced
    with pytest.raises(ValueError, match="folder"):
        with written_together(a, b) as (ta, tb):
            ta.write_text("a2")
            tb.write_text("b2")
    assert a.read_text() == "a" and b.is_dir() and sorted(os.listdir(a.parent)) == [b.name, a.name]


def test_written_together_names_the_paths_in_a_refusal_from_the_block(tmp_path):
    a, b = tmp_path / "a.ply", tmp_path / "a.contact.png"
    with pytest.raises(ValueError) as refused:
        with written_together(a, b) as (ta, tb):
            raise ValueError(f"{ta}: not written: no Gaussians; {tb} neither")
    assert str(refused.value) == f"{a}: not written: no Gaussians; {b} neither"
    with pytest.raises(ValueError, match="^unrelated$"):
        with written_together(a, b):
            raise ValueError("unrelated")
    assert os.listdir(tmp_path) == []


def test_outputs_that_are_inputs_or_each_other_are_refused(tmp_path):
    """By resolved path (.., symlinks) and, for files that exist, by device and inode (hard links)."""
    scene, style = tmp_path / "scene.ply", tmp_path / "style.png"
    scene.write_text("s")
    style.write_text("i")
    os.link(scene, tmp_path / "hard.ply")
    os.symlink(style, tmp_path / "soft.png")
    (tmp_path / "sub").mkdir()
    inputs = [("SCENE", scene), ("--style", style), ("--cameras", None)]
    refuse_overwrites([("--out", tmp_path / "out.ply"), ("sheet", tmp_path / "out.contact.png")], inputs)
    cases = [
        ([("--out", scene)], r"--out: .*scene\.ply is the same file as SCENE .*scene\.ply: the run would write over "
                             r"its own input"),
        ([("--out", tmp_path / "sub" / ".." / "scene.ply")], "same file as SCENE"),
        ([("--out", tmp_path / "hard.ply")], r"hard\.ply is the same file as SCENE .*scene\.ply"),
        ([("--out", tmp_path / "x.ply"), ("sheet", tmp_path / "soft.png")], r"sheet: .*soft\.png is the same file as "
                                                                             r"--style .*style\.png"),
        ([("job 1 --out", tmp_path / "a.png"), ("job 2 sheet", tmp_path / "sub" / ".." / "a.png")],
         r"job 2 sheet: .* is the same file as job 1 --out .*a\.png: the run would write over another output"),
    ]
    for outputs, message in cases:
        with pytest.raises(ValueError, match=message):
            refuse_overwrites(outputs, inputs)


def test_a_full_disk_is_named_by_the_file_being_written(tmp_path):
    """The error names the user's path, never the hidden temporary file, and keeps its errno and type."""
    def full(stream):
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match=r"\[Errno 28\] No space left on device: '.*scene\.ply'") as error:
        write_atomically(tmp_path / "scene.ply", full)
    assert error.value.errno == 28
    with pytest.raises(PermissionError, match=r"\[Errno 13\] Permission denied: '.*a\.ply'"):
        with written_together(tmp_path / "a.ply", tmp_path / "b.png") as (first, _):
            raise PermissionError(13, "Permission denied", str(first))
    assert list(tmp_path.iterdir()) == []


def test_output_names_are_checked_with_their_temporary_before_any_work(tmp_path):
    from artnvg_core.fileio import check_output_file, check_output_folder

    assert check_output_file(tmp_path / ("a" * 222 + ".ply"), "--out") == tmp_path / ("a" * 222 + ".ply")
    with pytest.raises(ValueError, match=r"--out: the file name a{40}\.\.\. is 234 bytes long; it may have at most "
                       r"226 here \(the file system allows 255, and the file is first written under a temporary name "
                       r"29 bytes longer\)"):
        check_output_file(tmp_path / ("a" * 230 + ".ply"), "--out")
    with pytest.raises(ValueError, match=r"--out: the name b{40}\.\.\. is 256 bytes long; this file system allows 255"):
        check_output_folder(tmp_path / ("b" * 256) / "views", "--out")
    assert list(tmp_path.iterdir()) == []


def test_temporaries_of_writers_that_died_are_swept_and_the_living_ones_kept(tmp_path):
    import subprocess
    import sys

    from artnvg_core.fileio import temporary_path, write_atomically

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    target = tmp_path / "scene.ply"
    left = tmp_path / f".scene.{int(dead.stdout)}.0123abcd.partial.ply"  # a writer killed while it wrote
    living = temporary_path(target)  # this process: still writing
    other = tmp_path / f".notes.{int(dead.stdout)}.txt"  # not a temporary's name
    for path in (left, living, other):
        path.write_bytes(b"half")
    write_atomically(target, lambda stream: stream.write(b"whole"))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([living.name, other.name, "scene.ply"])


def test_sigterm_while_writing_leaves_no_temporary(tmp_path):
    import signal

    from artnvg_core.cli.common import terminate_as_interrupt
    from artnvg_core.fileio import write_atomically

    def write(stream):
        stream.write(b"half")
        os.kill(os.getpid(), signal.SIGTERM)

    with pytest.raises(KeyboardInterrupt), terminate_as_interrupt() as received:
        write_atomically(tmp_path / "scene.ply", write)
    assert received == [signal.SIGTERM] and list(tmp_path.iterdir()) == []
