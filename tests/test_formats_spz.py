"""Niantic SPZ: versions 1-4, the axes of files with and without a record, round trip within the stated
quantisation, corrupt files."""

import dataclasses
import gzip
import json
import re
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
import zstandard

from artnvg_core.formats import spz
from artnvg_core.formats.spz import read_spz, write_spz
from artnvg_core.raster.sh import sh_to_color
from child_process import child_env
from tests.test_formats_splat import assert_only_value_errors, plain_scene, quat_error

FLIP = torch.tensor([1.0, -1, -1])  # RDF <-> RUB
ARRAYS = ("positions", "alphas", "colors", "scales", "rotations", "sh")


def payload_arrays(path) -> tuple[tuple, dict[str, bytes]]:
    """The legacy header fields and attribute arrays of a version 3 file we wrote."""
    data = gzip.decompress(path.read_bytes())
    header = struct.unpack_from("<IIIBBBB", data)
    n, degree = header[2], header[3]
    sizes = [9 * n, n, 3 * n, 3 * n, 4 * n, n * ((degree + 1) ** 2 - 1) * 3]
    arrays, offset = {}, 16
    for name, size in zip(ARRAYS, sizes):
        arrays[name], offset = data[offset : offset + size], offset + size
    assert offset == len(data)
    return header, arrays


def version_4(header: tuple, arrays: dict[str, bytes], extension: bytes = b"") -> bytes:
    """The same Gaussians in the version 4 container (32-byte header, TOC, one zstd stream per array)."""
    _, _, n, degree, bits, flags, _ = header
    streams = [zstandard.ZstdCompressor().compress(a) for a in arrays.values() if a]
    toc = 32 + len(extension)
    head = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, n, degree, bits, flags | (2 if extension else 0),
                       len(streams), toc)
    sizes = b"".join(struct.pack("<QQ", len(s), len(a)) for s, a in zip(streams, (a for a in arrays.values() if a)))
    return head + extension + sizes + b"".join(streams)


def test_round_trip_stays_within_the_stated_quantisation(tmp_path):
    scene = plain_scene(3000, 3)
    scene.sh[:, 1:] = scene.sh[:, 1:].clamp(-1, 0.99)
    scene.sh[:, 0] = scene.sh[:, 0].clamp(-3.3, 3.3)
    scene.log_scales.clamp_(-10, 5.9)
    path = tmp_path / "scene.spz"
    write_spz(scene, path)
    back = read_spz(path)
    assert back.sh_degree == 3 and not back.antialiased
    assert (back.means - scene.means).abs().max() <= 2.0**-13
    assert (back.log_scales - scene.log_scales).abs().max() <= 1 / 32 + 1e-6
    assert (back.sh[:, 0] - scene.sh[:, 0]).abs().max() <= 0.5 / (0.15 * 255) + 1e-6
    assert (back.sh[:, 1:4] - scene.sh[:, 1:4]).abs().max() <= 4.5 / 128 + 1e-6
    assert (back.sh[:, 4:] - scene.sh[:, 4:]).abs().max() <= 8.5 / 128 + 1e-6
    opacity = torch.sigmoid(scene.opacity_logits.double())
    assert (torch.sigmoid(back.opacity_logits.double()) - opacity).abs().max() <= 0.5 / 255 + 1e-7
    assert quat_error(back.quats, scene.quats) <= 0.002
    assert len(path.read_bytes()) < 0.25 * 3000 * 62 * 4  # far smaller than the float32 PLY


def stored_means(path) -> np.ndarray:
    """[N, 3] positions as a version 3 file we wrote holds them (12 fractional bits)."""
    fixed = np.frombuffer(payload_arrays(path)[1]["positions"], np.uint8).reshape(-1, 3, 3).astype(np.int64)
    fixed = fixed[..., 0] | fixed[..., 1] << 8 | fixed[..., 2] << 16
    return np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed) / 4096


def test_file_holds_the_plys_axes_or_rub_on_request_and_colours_are_the_same_from_flipped_directions(tmp_path):
    scene = plain_scene(200, 3)
    write_spz(scene, tmp_path / "ply.spz")
    write_spz(scene, tmp_path / "rub.spz", axes="rub")
    assert payload_arrays(tmp_path / "ply.spz")[0][:2] == (0x5053474E, 3)
    np.testing.assert_allclose(stored_means(tmp_path / "ply.spz"), scene.means.numpy(), atol=2.0**-12)
    np.testing.assert_allclose(stored_means(tmp_path / "rub.spz"), scene.means.numpy() * [1, -1, -1], atol=2.0**-12)
    # SH that SPZ stores exactly (multiples of 1/8 in [-0.875, 0.875]): the coefficients a RUB file holds, seen
    # along the RUB direction, give the PLY's colour along the RDF direction; a PLY-axes file holds them as they
    # are; both read back exactly
    scene.sh[:, 1:] = torch.randint(-7, 8, scene.sh[:, 1:].shape, generator=torch.Generator().manual_seed(0)) / 8
    held = {}
    for axes in ("rub", "ply"):
        write_spz(scene, tmp_path / f"{axes}.spz", axes=axes)
        sh = np.frombuffer(payload_arrays(tmp_path / f"{axes}.spz")[1]["sh"], np.uint8).reshape(200, 15, 3)
        held[axes] = torch.cat([scene.sh[:, :1], (torch.from_numpy(sh.astype(np.float32)) - 128) / 128], 1)
        assert torch.equal(read_spz(tmp_path / f"{axes}.spz", axes=axes).sh[:, 1:], scene.sh[:, 1:])
    directions = torch.nn.functional.normalize(torch.randn(200, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    torch.testing.assert_close(sh_to_color(held["rub"], directions * FLIP, 3), sh_to_color(scene.sh, directions, 3))
    assert torch.equal(held["ply"], scene.sh)


def test_version_4_zstd_container_reads_as_version_3(tmp_path):
    scene = plain_scene(300, 2)
    write_spz(scene, tmp_path / "v3.spz")
    header, arrays = payload_arrays(tmp_path / "v3.spz")
    v3 = read_spz(tmp_path / "v3.spz")
    (tmp_path / "v4.spz").write_bytes(version_4(header, arrays))
    v4 = read_spz(tmp_path / "v4.spz")
    for name, value in v3.tensors().items():
        assert torch.equal(getattr(v4, name), value), name
    # an extension record naming RUB axes (after another record): read with the RUB flip whatever axes says
    record = struct.pack("<III", 0xADBE0003, 4, 4)
    (tmp_path / "rub.spz").write_bytes(version_4(header, arrays, struct.pack("<II", 0xADBE0002, 0) + record))
    for axes in spz.AXES:
        torch.testing.assert_close(read_spz(tmp_path / "rub.spz", axes=axes).means, v3.means * FLIP)
    # one naming RDF: read as it is, even when asked for RUB
    (tmp_path / "rdf.spz").write_bytes(version_4(header, arrays, struct.pack("<III", 0xADBE0003, 4, 6)))
    assert torch.equal(read_spz(tmp_path / "rdf.spz", axes="rub").means, v3.means)


def test_versions_1_and_2_and_the_antialiased_flag(tmp_path):
    n = 3
    positions = np.array([[1, -2, 0.5]] * n, "<f2").tobytes()
    rotations = bytes([128, 128, 255] * n)  # x y z = (0.004, 0.004, 1): a half turn about z
    body = positions + bytes([255] * n) + bytes([128] * 3 * n) + bytes([160] * 3 * n) + rotations
    path = tmp_path / "v1.spz"
    path.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 1, n, 0, 0, 1, 0) + body))
    scene = read_spz(path)
    assert scene.antialiased
    torch.testing.assert_close(scene.means, torch.tensor([[1.0, -2, 0.5]] * n))  # the PLY's axes: as stored
    torch.testing.assert_close(read_spz(path, axes="rub").means, torch.tensor([[1.0, 2, -0.5]] * n))  # RUB -> RDF
    torch.testing.assert_close(scene.log_scales, torch.full((n, 3), 0.0))
    assert quat_error(scene.quats, torch.tensor([[0.0, 0, 0, 1]] * n)) < 0.01
    assert torch.sigmoid(scene.opacity_logits).min() > 0.998


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda h: h[:4] + struct.pack("<I", 9) + h[8:], "version: 9 is not a supported SPZ version"),
        (lambda h: h[:8] + struct.pack("<I", 0) + h[12:], "numPoints: 0 is not a valid Gaussian count"),
        (lambda h: h[:8] + struct.pack("<I", 9) + h[12:],
         "numPoints: 9 Gaussians of SH degree 1: the stream holds more than the 261 bytes expected"),
        (lambda h: h[:8] + struct.pack("<I", 11) + h[12:],
         "numPoints: 11 Gaussians of SH degree 1: 319 bytes expected, the stream ends after 290"),
        (lambda h: h[:12] + bytes([5]) + h[13:], "shDegree: 5 is above SPZ's maximum 4"),
        (lambda h: h[:12] + bytes([2]) + h[13:], "numPoints: 10 Gaussians of SH degree 2: 440 bytes expected"),
        (lambda h: b"XGSP" + h[4:], "magic: 0x50534758, expected 0x5053474e"),
    ],
)
def test_corrupt_legacy_headers_name_the_field(tmp_path, change, message):
    write_spz(plain_scene(10, 1), tmp_path / "good.spz")
    data = gzip.decompress((tmp_path / "good.spz").read_bytes())
    path = tmp_path / "corrupt.spz"
    path.write_bytes(gzip.compress(change(data[:16]) + data[16:]))
    with pytest.raises(ValueError, match=rf"corrupt\.spz: {message}"):
        read_spz(path)


@pytest.mark.parametrize(
    ("offset", "value", "message"),
    [
        (15, b"\x05", r"numStreams: 5, expected 6 for SH degree 1"),
        (16, struct.pack("<I", 4000), r"tocByteOffset: 4000 puts the table outside"),
        (8, struct.pack("<I", 11), r"positions stream: \d+ bytes uncompressed, expected 99"),
    ],
)
def test_corrupt_version_4_headers_name_the_field(tmp_path, offset, value, message):
    write_spz(plain_scene(10, 1), tmp_path / "good.spz")
    data = bytearray(version_4(*payload_arrays(tmp_path / "good.spz")))
    data[offset : offset + len(value)] = value
    path = tmp_path / "corrupt.spz"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"corrupt\.spz: {message}"):
        read_spz(path)


LIMIT_12 = (2**23 - 1) / 4096  # the largest |coordinate| SPZ holds at 12 fractional bits


def with_far(scene, means: list, log_scales: list):
    """``scene`` and, after it, copies of its first rows placed at ``means`` with ``log_scales``."""
    far = scene.select(slice(0, len(means))).map(torch.clone)
    far.means[:], far.log_scales[:] = torch.tensor(means), torch.tensor(log_scales)
    return dataclasses.replace(scene, **{name: torch.cat([value, getattr(far, name)])
                                         for name, value in scene.tensors().items()})


def rows(path, count: int) -> dict[str, bytes]:
    """The first ``count`` Gaussians' bytes in each array of a version 3 file we wrote."""
    _, arrays = payload_arrays(path)
    total = len(arrays["alphas"])
    return {name: data[: len(data) // total * count] for name, data in arrays.items()}


def test_up_to_one_in_a_thousand_far_gaussians_are_moved_onto_the_12_bit_range_along_their_rays(tmp_path):
    """Two floaters (at the shared bear's farthest distance, and one past 2^23) among 2,000: the file keeps 12
    fractional bits and every other Gaussian's bytes; each floater keeps its direction from the origin and its
    apparent size from there (log-scales shifted by the log of the distance ratio; 7 lands inside SPZ's
    [-10, 5.9])."""
    scene = plain_scene(2000, 1)
    floaters = [[343035.0, -2.0, 1.0], [-5000.0, 3000.0, 1e7]]
    far = with_far(scene, floaters, [[7.0, 4.0, 3.0], [0.0, 1.0, 2.0]])
    write_spz(scene, tmp_path / "near.spz")
    notes = []
    write_spz(far, tmp_path / "far.spz", notes=notes.append)
    assert notes == [
        "2 Gaussians beyond SPZ's range at 12 fractional bits (|coordinate| up to 2048) moved onto it along their "
        "rays from the origin, their sizes scaled alike (the same direction and apparent size from there); the "
        "farthest from |coordinate| 1e+07"]
    assert payload_arrays(tmp_path / "far.spz")[0][4] == 12
    assert rows(tmp_path / "far.spz", 2000) == rows(tmp_path / "near.spz", 2000)
    back = read_spz(tmp_path / "far.spz")
    original = torch.tensor(floaters, dtype=torch.float64)
    ratio = LIMIT_12 / original.abs().amax(1, keepdim=True)
    moved = back.means[2000:].double()
    assert moved.abs().amax(1).tolist() == [LIMIT_12, LIMIT_12]
    assert (moved - original * ratio).abs().max() <= 2.0**-13
    expected = (far.log_scales[2000:].double() + ratio.log()).clamp(-10, 5.9)
    assert expected[0].tolist() == pytest.approx([7 + float(ratio[0].log()), 4 + float(ratio[0].log()),
                                                  3 + float(ratio[0].log())])
    assert (back.log_scales[2000:].double() - expected).abs().max() <= 1 / 32 + 1e-6


def test_more_far_gaussians_give_up_fractional_bits_instead(tmp_path):
    """Beyond one in a thousand, the far Gaussians are the scene (all near 1e5: 6 bits) or one is among too few
    others to be moved (one of 20 at the bear's farthest |coordinate|: 4 bits), and nothing is moved."""
    everywhere_far = plain_scene(300, 0)
    everywhere_far.means += 1e5
    one_of_20 = with_far(plain_scene(19, 0), [[343035.0, -2.0, 1.0]], [[0.0, 0.0, 0.0]])
    notes = []
    for name, scene, bits in (("everywhere", everywhere_far, 6), ("one_of_20", one_of_20, 4)):
        write_spz(scene, tmp_path / f"{name}.spz", notes=notes.append)
        assert payload_arrays(tmp_path / f"{name}.spz")[0][4] == bits, name
        back = read_spz(tmp_path / f"{name}.spz")
        assert (back.means.double() - scene.means.double()).abs().max() <= 2.0 ** -(bits + 1), name
        assert (back.log_scales - scene.log_scales.clamp(-10, 5.9)).abs().max() <= 1 / 32 + 1e-6, name
    assert notes == []


@pytest.mark.parametrize(("count", "huge"), [(19, 1), (1998, 3)])
def test_more_than_one_in_a_thousand_gaussians_past_2_to_the_23_are_refused(tmp_path, count, huge):
    """A |coordinate| of 2^23 fits no fractional bits: refused by the writer and by the geometry check made
    before a finetune, unless the Gaussians so far are few enough to be moved (the first test's 1e7)."""
    from artnvg_core.formats import check_geometry_writable

    scene = with_far(plain_scene(count, 0), [[2.0**23, 0.0, 0.0]] * huge, [[0.0, 0.0, 0.0]] * huge)
    message = (rf"huge\.spz: not written: means: {huge} Gaussians? of {count + huge:,} with a \|coordinate\| of 2\^23 "
               rf"or more \(up to 8\.38861e\+06\), beyond SPZ's 24-bit fixed point at any fractional bits; at most "
               rf"{(count + huge) // 1000} \(one in 1,000, rounded down\) may be moved onto its range")
    for check in (write_spz, check_geometry_writable):
        with pytest.raises(ValueError, match=message):
            check(scene, tmp_path / "huge.spz")
    assert not (tmp_path / "huge.spz").exists()


def test_fuzzed_and_truncated_files_raise_only_value_error(tmp_path):
    write_spz(plain_scene(12, 1), tmp_path / "source.spz")
    v3 = (tmp_path / "source.spz").read_bytes()
    v4 = version_4(*payload_arrays(tmp_path / "source.spz"))
    raw = gzip.decompress(v3)
    rng = np.random.default_rng(2)
    for name, original in (("v3", v3), ("v4", v4), ("raw", raw)):
        for case in range(60):
            data = bytearray(original)
            span = 48 if case % 2 else len(data)  # half the flips aimed at the header
            for position in rng.integers(0, span, 3):
                data[position] = int(rng.integers(0, 256))
            if name == "raw":
                data = bytearray(gzip.compress(bytes(data)))
            assert_only_value_errors(read_spz, tmp_path / "fuzzed.spz", bytes(data), f"{name} case {case}")
        for length in range(0, len(original), max(1, len(original) // 40)):
            path = tmp_path / "cut.spz"
            assert_only_value_errors(read_spz, path, original[:length], f"{name} cut to {length}")
            if name != "raw" and length < len(original):
                with pytest.raises(ValueError, match=r"cut\.spz: "):
                    read_spz(path)


def test_antialiased_flag_round_trips(tmp_path):
    scene = dataclasses.replace(plain_scene(5, 0), antialiased=True)
    write_spz(scene, tmp_path / "aa.spz")
    assert payload_arrays(tmp_path / "aa.spz")[0][5] == 1
    assert read_spz(tmp_path / "aa.spz").antialiased


BOMB_BYTES = 2**31  # what each bomb inflates to: 2 GiB


def gzip_bomb(prefix: bytes, zeros: int) -> bytes:
    """A valid gzip member of ``prefix`` then ``zeros`` zero bytes, about zeros / 1000 bytes long: the
    deflate block of 1 MiB of zeros after a full flush is the same every time, so it is made once
    and repeated."""
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = compressor.compress(prefix) + compressor.flush(zlib.Z_FULL_FLUSH)
    block = compressor.compress(bytes(1 << 20)) + compressor.flush(zlib.Z_FULL_FLUSH)
    assert zeros % (1 << 26) == 0
    crc, chunk = zlib.crc32(prefix), bytes(1 << 26)
    for _ in range(zeros >> 26):
        crc = zlib.crc32(chunk, crc)
    body = head + block * (zeros >> 20) + compressor.flush(zlib.Z_FINISH)
    return b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xff" + body + struct.pack("<II", crc, (len(prefix) + zeros) & 0xFFFFFFFF)


def zstd_of_zeros(total: int) -> bytes:
    """One zstd frame of ``total`` zero bytes whose header declares that size."""
    compressor = zstandard.ZstdCompressor(level=1).compressobj(size=total)
    chunk = bytes(1 << 26)
    return b"".join([compressor.compress(chunk) for _ in range(total >> 26)] + [compressor.flush()])


LOAD_AND_MEASURE = """
import json, resource, sys, time
from artnvg_core.formats import load_scene
def peak():  # this process's own high-water mark: ru_maxrss would carry the forking parent's over exec
    try:
        status = open("/proc/self/status").read()
        return int(status.split("VmHWM:")[1].split()[0]) * 1024
    except (OSError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
before, start = peak(), time.perf_counter()
try:
    load_scene(sys.argv[1])
    message = None
except ValueError as error:
    message = str(error)
seconds = time.perf_counter() - start
print(json.dumps({"message": message, "seconds": seconds, "peak": peak(), "growth": peak() - before}))
"""


@pytest.mark.parametrize("version", [3, 4])
def test_a_decompression_bomb_is_refused_quickly_in_little_memory(tmp_path, version):
    """A 2 MB (gzip, version 3) or 66 kB (zstd, version 4) file with a valid header for 10 Gaussians
    whose stream inflates to 2 GiB: refused after inflating one byte past the 650 bytes the header
    implies, within 2 s and 1 GB for the whole process (measured in a fresh one, whose peak memory
    the load raises by less than 64 MiB)."""
    header = struct.pack("<IIIBBBB", 0x5053474E, 3, 10, 0, 12, 0, 0)
    path = tmp_path / "bomb.spz"
    if version == 3:
        path.write_bytes(gzip_bomb(header, BOMB_BYTES))
        expected = r"numPoints: 10 Gaussians of SH degree 0: the stream holds more than the 200 bytes expected"
    else:
        stream = zstd_of_zeros(BOMB_BYTES)
        head = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 10, 0, 12, 0, 5, 32)
        sizes = [90, 10, 30, 30, 40]
        toc = struct.pack("<QQ", len(stream), sizes[0]) + b"".join(struct.pack("<QQ", 9, s) for s in sizes[1:])
        tiny = zstandard.ZstdCompressor().compress(bytes(10))  # 9 bytes; never reached
        path.write_bytes(head + toc + stream + tiny * 4)
        expected = r"positions stream: the stream holds more than the 90 bytes expected"
    assert path.stat().st_size < 2.2e6
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run([sys.executable, "-c", LOAD_AND_MEASURE, str(path)], cwd=root, capture_output=True,
                            text=True, check=True, env=child_env())
    report = json.loads(result.stdout)
    assert report["message"] is not None and re.search(expected, report["message"]), report
    assert report["seconds"] < 2 and report["peak"] < 2**30 and report["growth"] < 2**26, report


@pytest.mark.parametrize("version", [3, 4])
def test_a_header_count_beyond_the_inflation_cap_is_refused_before_inflating(tmp_path, version):
    """A header claiming 2^31 - 1 Gaussians over a 2 MB (gzip) or 66 kB (zstd) stream of 2 GiB of
    zeros: refused from the file's size alone (64x the file at most), in a fresh process within 2 s,
    its peak memory raised by less than 64 MiB (the header's own count once set the bound: 1.8-3.4 GB)."""
    count = 2**31 - 1
    path = tmp_path / "claims.spz"
    if version == 3:
        path.write_bytes(gzip_bomb(struct.pack("<IIIBBBB", 0x5053474E, 3, count, 0, 12, 0, 0), BOMB_BYTES))
    else:
        stream = zstd_of_zeros(BOMB_BYTES)
        head = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, count, 0, 12, 0, 5, 32)
        sizes = [9 * count, count, 3 * count, 3 * count, 4 * count]
        path.write_bytes(head + b"".join(struct.pack("<QQ", len(stream), s) for s in sizes) + stream)
    size = path.stat().st_size
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run([sys.executable, "-c", LOAD_AND_MEASURE, str(path)], cwd=root, capture_output=True,
                            text=True, check=True, env=child_env())
    report = json.loads(result.stdout)
    expected = (rf"claims\.spz: numPoints: {count:,} Gaussians of SH degree 0: needs {20 * count:,} bytes inflated "
                rf"from a {size:,}-byte file, more than the cap of 64x the file's size \({max(64 * size, 2**24):,} bytes\)")
    assert report["message"] is not None and re.search(expected, report["message"]), report
    assert report["seconds"] < 2 and report["growth"] < 2**26, report


def test_the_inflation_cap_admits_real_scenes_and_states_its_bound(tmp_path, monkeypatch):
    """A real scene's file (1.3x to 4.5x inflation) loads; with the cap lowered under its ratio it is
    refused naming the cap."""
    from artnvg_core.formats import bounded

    scene = plain_scene(3000, 3, seed=4)
    write_spz(scene, tmp_path / "real.spz")
    inflated = len(gzip.decompress((tmp_path / "real.spz").read_bytes()))
    assert len(read_spz(tmp_path / "real.spz")) == 3000
    monkeypatch.setattr(bounded, "INFLATION_FLOOR", 0)
    monkeypatch.setattr(bounded, "MAX_INFLATION", 1)
    assert inflated > (tmp_path / "real.spz").stat().st_size
    with pytest.raises(ValueError, match=r"real\.spz: numPoints: 3,000 Gaussians of SH degree 3: needs .* cap of 1x"):
        read_spz(tmp_path / "real.spz")


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_versions_2_to_4_load_at_every_sh_degree(tmp_path, degree):
    """The same Gaussians as version 2 (x y z rotation bytes), 3 (gzip) and 4 (zstd; at degree 0 it has
    no SH stream, which once raised KeyError 'sh') read alike: version 4 bit for bit, version 2 but for
    its coarser rotations."""
    write_spz(plain_scene(40, degree, seed=degree), tmp_path / "v3.spz")
    header, arrays = payload_arrays(tmp_path / "v3.spz")
    v3 = read_spz(tmp_path / "v3.spz")
    assert v3.sh_degree == degree
    (tmp_path / "v4.spz").write_bytes(version_4(header, arrays))
    xyzw = v3.quats[:, [1, 2, 3, 0]].double()  # the file's axes are the PLY's
    xyzw = xyzw * torch.where(xyzw[:, 3:] < 0, -1.0, 1.0) / xyzw.norm(dim=1, keepdim=True)
    v2_arrays = dict(arrays, rotations=np.clip(np.floor((xyzw[:, :3].numpy() + 1) * 127.5 + 0.5), 0, 255).astype(np.uint8).tobytes())
    (tmp_path / "v2.spz").write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 2, *header[2:]) +
                                                    b"".join(v2_arrays.values())))
    write_spz(v3, tmp_path / "ours_v2.spz", version=2)  # our version 2 writer stores the same bytes
    assert gzip.decompress((tmp_path / "ours_v2.spz").read_bytes()) == gzip.decompress(
        (tmp_path / "v2.spz").read_bytes())
    for version in ("v4", "v2"):
        back = read_spz(tmp_path / f"{version}.spz")
        for name, value in v3.tensors().items():
            if name != "quats":
                assert torch.equal(getattr(back, name), value), (version, name)
        assert quat_error(back.quats, v3.quats) <= (0 if version == "v4" else 0.1)  # v2: w from 8-bit x y z


def test_a_legacy_files_record_after_its_arrays_names_its_axes(tmp_path):
    """Niantic's writer puts extension records after a version 1-3 file's arrays (flag 0x2)."""
    write_spz(plain_scene(50, 1), tmp_path / "plain.spz")
    data = bytearray(gzip.decompress((tmp_path / "plain.spz").read_bytes()))
    data[14] |= 0x2
    plain = read_spz(tmp_path / "plain.spz")
    for system, flip in [(4, FLIP), (6, torch.ones(3))]:  # RUB, RDF
        record = struct.pack("<II", 0xADBE0002, 0) + struct.pack("<III", 0xADBE0003, 4, system)
        (tmp_path / "named.spz").write_bytes(gzip.compress(bytes(data) + record))
        assert torch.equal(read_spz(tmp_path / "named.spz", axes="rub" if system == 6 else "ply").means,
                           plain.means * flip), system


@pytest.mark.parametrize("axes", ["ply", "rub"])
def test_auto_reads_a_real_capture_without_a_record_in_front_of_its_cameras(tmp_path, shared_data, axes, caplog):
    """Bear written in either axes with no record reads back as the PLY with its cameras; without them it is
    read in the PLY's axes, which one note says (and how to change it), logged where no caller takes it."""
    from artnvg_core.cameras import load_cameras
    from artnvg_core.formats import load_scene

    capture = shared_data / "scenes" / "bear"
    scene = load_scene(capture / "scene.ply")
    write_spz(scene, tmp_path / "bear.spz", axes=axes, notes=lambda note: None)
    notes = []
    with caplog.at_level("INFO"):
        back = load_scene(tmp_path / "bear.spz", cameras=load_cameras(capture / "transforms.json"),
                          notes=notes.append)
    assert notes == [] and [r.levelname for r in caplog.records] == ["INFO"]  # which axes the cameras chose
    kept = scene.means.abs().amax(1) < LIMIT_12  # all but its 63 floaters, which the writer moves
    assert int((~kept).sum()) == 63 and back.means.abs().max() <= LIMIT_12
    assert (back.means - scene.means)[kept].abs().max() <= 2.0**-13 * (1 + 1e-3)
    caplog.clear()
    with caplog.at_level("INFO"):
        alone = load_scene(tmp_path / "bear.spz", notes=notes.append)
        assert caplog.records == []
        load_scene(tmp_path / "bear.spz")
    note = ("the file names no axes: read in the PLY's axes (x right, y down, z forward), as splat-transform, "
            "spz-js and Niantic's ply-to-spz write; if it is upside down, read it with spz axes 'rub' (--spz-axes "
            "rub, the Load Gaussian Scene node's spz_axes)")
    assert notes == [note]
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [("WARNING", f"{tmp_path / 'bear.spz'}: {note}")]
    assert torch.equal(alone.means, back.means if axes == "ply" else back.means * FLIP)


@pytest.mark.parametrize("version", [3, 4])
def test_degree_4_sh_is_read_as_degree_3_with_a_note(tmp_path, version, caplog):
    """A degree-4 file (Niantic's library writes up to 4) reads as its degree-3 part; the note is told to the
    caller, else logged."""
    write_spz(plain_scene(30, 3), tmp_path / "d3.spz")
    header, arrays = payload_arrays(tmp_path / "d3.spz")
    extra = np.random.default_rng(0).integers(0, 256, (30, 9, 3), dtype=np.uint8)
    sh = np.concatenate([np.frombuffer(arrays["sh"], np.uint8).reshape(30, 15, 3), extra], 1)
    header, arrays = (*header[:3], 4, *header[4:]), dict(arrays, sh=sh.tobytes())
    (tmp_path / "d4.spz").write_bytes(version_4(header, arrays) if version == 4 else
                                      gzip.compress(struct.pack("<IIIBBBB", *header) + b"".join(arrays.values())))
    notes = []
    with caplog.at_level("INFO"):
        back = read_spz(tmp_path / "d4.spz", axes="ply", notes=notes.append)
        assert caplog.records == []
        read_spz(tmp_path / "d4.spz", axes="ply")
    note = "SH degree 4 read as degree 3 (the degree-4 terms are dropped)"
    assert notes == [note]
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [("WARNING", f"{tmp_path / 'd4.spz'}: {note}")]
    for name, value in read_spz(tmp_path / "d3.spz", axes="ply").tensors().items():
        assert torch.equal(getattr(back, name), value), name
