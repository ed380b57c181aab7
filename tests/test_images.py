"""Image reading at any bit depth and size, checked before it is decoded."""

import io
import os
import struct
import tracemalloc
import zlib

import numpy as np
import pytest
from PIL import Image

from artnvg_core.images import MAX_IMAGE_PIXELS, image_size, load_image


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


def test_float_tiff_spanning_more_than_float32_is_rescaled_to_finite_values(tmp_path):
    """Found by fuzzing: finite pixels from -3e38 to 3e38 were rescaled in float32, whose max - min
    overflowed, and came out NaN."""
    Image.fromarray(np.array([[-3e38, 3e38], [0, 1.5e38]], np.float32)).save(tmp_path / "extreme.tif")
    np.testing.assert_allclose(load_image(tmp_path / "extreme.tif").numpy()[..., 0], [[0, 1], [0.5, 0.75]], atol=1e-6)


def test_corrupt_files_pillow_refuses_with_value_errors_are_named(tmp_path):
    """Found by fuzzing: Pillow raises ValueError, not only OSError, for some corrupt files, on opening them
    (a truncated PNG header) or decoding them (a TIFF of 0 rows per strip): they escaped naming no file."""
    (tmp_path / "ihdr.png").write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", bytes(10)) + _png_chunk(b"IEND", b""))
    Image.fromarray(np.zeros((4, 4), np.float32)).save(tmp_path / "strips.tif")
    data = (tmp_path / "strips.tif").read_bytes()
    rows_per_strip = data.index(struct.pack("<HHI", 278, 4, 1)) + 8  # the tag's LONG value
    (tmp_path / "strips.tif").write_bytes(data[:rows_per_strip] + bytes(4) + data[rows_per_strip + 4:])
    for name, reads in (("ihdr.png", (image_size, load_image)), ("strips.tif", (load_image,))):
        for read in reads:
            with pytest.raises(ValueError, match=rf"{name}: not a readable image \(.+\)"):
                read(tmp_path / name)


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


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_header_only(path, width, height):
    """A PNG whose header declares width x height (no pixel data): enough for Image.open."""
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header) + _png_chunk(b"IEND", b""))


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


def _peak_traced_bytes(read, path, message: str) -> int:
    """Peak bytes Python allocated (tracemalloc: Pillow's reads of the file are Python bytes) while ``read(path)``
    raised a ValueError matching ``message``."""
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=message):
            read(path)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_a_png_chunk_longer_than_the_file_is_refused_before_pillow_reserves_its_length(tmp_path):
    """A 69-byte PNG whose IDAT chunk declares 2 GB: Pillow read it as a valid 4x4 image and reserved the 2 GB on
    the way (4 GB with a length of 2**32 - 16; on Windows that memory is committed); now refused from the chunk
    table, naming the chunk, its offset and the bytes left, with no more memory than the file's."""
    rows = b"".join(b"\0" + bytes(12) for _ in range(4))
    header = struct.pack(">IIBBBBB", 4, 4, 8, 2, 0, 0, 0)
    good = b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", zlib.compress(rows))
    good += _png_chunk(b"IEND", b"")
    (tmp_path / "good.png").write_bytes(good)
    assert load_image(tmp_path / "good.png").shape == (4, 4, 3)
    idat = good.index(b"IDAT") - 4
    left = len(good) - idat - 12  # after IDAT's length, name and checksum
    for length in (2**31 - 16, 2**32 - 16):
        (tmp_path / "long.png").write_bytes(good[:idat] + struct.pack(">I", length) + good[idat + 4:])
        for read in (load_image, image_size):
            peak = _peak_traced_bytes(read, tmp_path / "long.png", rf"long\.png: PNG chunk 'IDAT' at byte 33 declares "
                                      rf"{length:,} bytes of data, more than the {left} bytes left in the file")
            assert peak < 2**20
    (tmp_path / "cut.png").write_bytes(good[:-13])  # IDAT's checksum cut short: the file ends inside the chunk
    _peak_traced_bytes(load_image, tmp_path / "cut.png", rf"cut\.png: PNG chunk 'IDAT' .* than the {left - 13} bytes left")


def test_a_tiff_strip_past_the_files_end_is_refused_before_pillow_reserves_the_distance(tmp_path):
    """A 204-byte TIFF of two strips, the second at byte 2**31: Pillow reserved the 2 GB between the strips before
    reading the first; now refused from the header's offsets, naming the format, the block and the offset."""
    stream = io.BytesIO()
    Image.fromarray(np.full((4, 4, 3), 128, np.uint8)).save(stream, format="TIFF", tiffinfo={278: 2})
    data = bytearray(stream.getvalue())
    (ifd,) = struct.unpack_from("<I", data, 4)
    entries = [struct.unpack_from("<HHII", data, ifd + 2 + 12 * i) for i in range(struct.unpack_from("<H", data, ifd)[0])]
    (offsets,) = [value for tag, _, count, value in entries if tag == 273 and count == 2]  # StripOffsets, a LONG[2]
    struct.pack_into("<I", data, offsets + 4, 2**31)
    (tmp_path / "far.tif").write_bytes(data)
    peak = _peak_traced_bytes(load_image, tmp_path / "far.tif", r"far\.tif: TIFF header: image data block 2 of 2 "
                              rf"starts at byte 2,147,483,648, past the end of the file \({len(data)} bytes\)")
    assert peak < 2**20
