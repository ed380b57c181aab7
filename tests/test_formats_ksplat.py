"""mkkellogg .ksplat: level-0 round trip, levels 1 and 2 written by hand from SplatBuffer.js's layout,
ComfyUI core's level-0 writer's layout, corrupt files."""

import struct

import numpy as np
import pytest
import torch

from artnvg_core.formats import common, load_scene, save_scene
from artnvg_core.formats.ksplat import read_ksplat, write_ksplat
from artnvg_core.scene import SH_C0
from tests.test_formats_ply import assert_same_bits
from tests.test_formats_splat import assert_only_value_errors, plain_scene, quat_error


def header(sections: int, splats: int, level: int, sh_range=(0.0, 0.0)) -> bytes:
    """SplatBuffer's 4096-byte header, field by field."""
    head = bytearray(4096)
    head[0], head[1] = 0, 1
    struct.pack_into("<IIII", head, 4, sections, sections, splats, splats)
    struct.pack_into("<H", head, 20, level)
    struct.pack_into("<ff", head, 36, *sh_range)
    return bytes(head)


def section_header(count, bucket_size=0, buckets=0, block=0.0, scale_range=0, storage=0, full=0, partial=0,
                   degree=0) -> bytes:
    """SplatBuffer's 1024-byte section header, field by field."""
    head = bytearray(1024)
    struct.pack_into("<IIIIf", head, 0, count, count, bucket_size, buckets, block)
    struct.pack_into("<H", head, 20, 12 if buckets else 0)
    struct.pack_into("<IIIIIH", head, 24, scale_range, storage, full, partial, 0, 0)
    struct.pack_into("<H", head, 40, degree)
    return bytes(head)


def test_level_0_round_trip_is_exact_but_for_colour_and_opacity_bytes(tmp_path, caplog):
    for degree in (0, 1, 2, 3):
        scene = plain_scene(300, degree, seed=degree)
        path = tmp_path / f"d{degree}.ksplat"
        save_scene(scene, path)
        assert path.stat().st_size == 4096 + 1024 + 300 * (44 + 4 * {0: 0, 1: 9, 2: 24, 3: 24}[degree])
        back = load_scene(path)
        kept = min(degree, 2)
        assert back.sh_degree == kept and ("the degree 3 view-dependent terms are dropped" in caplog.text) == (degree == 3)
        assert torch.equal(back.means, scene.means)
        assert (back.log_scales - scene.log_scales).abs().max() <= 1e-6
        assert quat_error(back.quats, scene.quats) <= 1e-6
        assert torch.equal(back.sh[:, 1:], scene.sh[:, 1 : (kept + 1) ** 2])
        colour = (SH_C0 * scene.sh[:, 0].double() + 0.5).clamp(0, 1)
        assert ((SH_C0 * back.sh[:, 0].double() + 0.5) - colour).abs().max() <= 0.5 / 255 + 1e-7
        opacity = torch.sigmoid(scene.opacity_logits.double())
        assert (torch.sigmoid(back.opacity_logits.double()) - opacity).abs().max() <= 0.5 / 255 + 1e-7


def test_comfyui_cores_level_0_layout(tmp_path):
    """As ComfyUI's GaussianToFile3D writes it: header, one section, 44-byte records
    (centre, linear scale, rotation w x y z as float32, RGBA bytes), zeros for SH range."""
    rows = np.zeros(2, [("f", "<f4", 10), ("c", "u1", 4)])
    rows["f"][0] = [1, 2, 3, 0.5, 1, 2, 0, 1, 0, 0]  # a half turn about x
    rows["f"][1] = [-1, 0, 4, 1, 1, 1, 1, 0, 0, 0]
    rows["c"] = [[255, 0, 128, 64], [10, 20, 30, 255]]
    path = tmp_path / "core.ksplat"
    path.write_bytes(header(1, 2, 0) + section_header(2, storage=88) + rows.tobytes())
    scene = read_ksplat(path)
    assert scene.means.tolist() == [[1, 2, 3], [-1, 0, 4]] and scene.sh_degree == 0
    torch.testing.assert_close(scene.log_scales[0], torch.log(torch.tensor([0.5, 1, 2])))
    assert quat_error(scene.quats, torch.tensor([[0.0, 1, 0, 0], [1, 0, 0, 0]])) == 0
    torch.testing.assert_close(SH_C0 * scene.sh[:, 0] + 0.5, torch.tensor([[1, 0, 128 / 255], [10 / 255, 20 / 255, 30 / 255]]))
    torch.testing.assert_close(torch.sigmoid(scene.opacity_logits), torch.tensor([64 / 255, 1 - 0.25 / 255]))


@pytest.mark.parametrize("level", [1, 2])
def test_levels_1_and_2_with_buckets_written_by_hand(tmp_path, monkeypatch, level):
    """Three Gaussians, SH degree 1, in a full bucket of 2 and a partly filled one of 1 (bucket
    centres (10, 0, 0) and (0, -5, 0), block size 4, range 32767); positions as SplatBuffer
    quantises them, scales and rotations as float16, SH float16 (level 1) or bytes in the header's
    range -2..2 (level 2)."""
    centres = np.array([[10, 0, 0], [0, -5, 0]], "<f4")
    means = np.array([[10.5, -0.25, 1], [9, 1, -1.5], [0.75, -5, 0.125]])
    bucket = np.array([0, 0, 1])
    scale_range, block = 32767, 4.0
    fixed = np.clip(np.round((means - centres[bucket]) * (scale_range / (block / 2))) + scale_range, 0, 2 * scale_range)
    sh = np.array([[0.5, -1, 0.25, 1, 0, -0.5, 2, -2, 0]] * 3)  # R's three coefficients, then G's, then B's
    record = [("center", "<u2", 3), ("scale", "<f2", 3), ("rotation", "<f2", 4), ("rgba", "u1", 4),
              ("sh", "<f2" if level == 1 else "u1", 9)]
    rows = np.zeros(3, record)
    rows["center"], rows["scale"], rows["rotation"] = fixed, [[0.5, 0.25, 2]] * 3, [[0, 0, 1, 0]] * 3
    rows["rgba"] = [128, 128, 128, 200]
    rows["sh"] = sh if level == 1 else np.floor((sh + 2) / 4 * 255)
    data = struct.pack("<I", 1) + centres.tobytes() + rows.tobytes()  # partly filled bucket lengths, centres, records
    path = tmp_path / f"l{level}.ksplat"
    path.write_bytes(header(1, 3, level, (-2.0, 2.0)) + section_header(3, 2, 2, block, 0, len(data), 1, 1, 1) + data)
    scene = read_ksplat(path)
    np.testing.assert_allclose(scene.means.numpy(), means, atol=block / 2 / scale_range)
    np.testing.assert_allclose(scene.log_scales.numpy(), np.log([[0.5, 0.25, 2]] * 3), atol=1e-6)
    assert quat_error(scene.quats, torch.tensor([[0.0, 0, 1, 0]] * 3)) == 0
    expected = sh.reshape(3, 3, 3).transpose(0, 2, 1)  # [N, coefficient, channel]
    np.testing.assert_allclose(scene.sh[:, 1:].numpy(), expected, atol=0 if level == 1 else 4 / 255)
    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 2)  # the second chunk starts in the partly filled bucket
    assert_same_bits(read_ksplat(path), scene)


def test_corrupt_headers_name_the_field(tmp_path):
    save_scene(plain_scene(5, 1), tmp_path / "good.ksplat")
    good = (tmp_path / "good.ksplat").read_bytes()
    path = tmp_path / "bad.ksplat"
    cases = [
        (bytes([1]) + good[1:], r"version: 1\.1 is not a supported"),
        (good[:20] + struct.pack("<H", 3) + good[22:], "compressionLevel: 3, expected 0, 1 or 2"),
        (good[:4] + struct.pack("<I", 9) + good[8:], "maxSectionCount: 9 section headers do not fit"),
        (good[:-1], r"section 0: its counts need \d+ bytes, the file holds \d+"),
        (good + b"\0", "the file holds 1 byte after its last section"),
        (good[:4096 + 40] + struct.pack("<H", 3) + good[4096 + 42 :],
         "section 0: sphericalHarmonicsDegree: 3, expected 0, 1 or 2"),
        (good[:4096] + struct.pack("<I", 6) + good[4100:], "section 0: splatCount: 6, more than its maxSplatCount 5"),
    ]
    for data, message in cases:
        path.write_bytes(data)
        with pytest.raises(ValueError, match=rf"bad\.ksplat: {message}"):
            read_ksplat(path)


def test_scales_beyond_float32_are_refused_before_writing(tmp_path):
    scene = plain_scene(4, 0)
    scene.log_scales[1, 0] = -88.0
    with pytest.raises(ValueError, match=r"tiny\.ksplat: not written: log_scales: 1 of 4 .*\.ksplat"):
        write_ksplat(scene, tmp_path / "tiny.ksplat")
    assert list(tmp_path.iterdir()) == []


def test_fuzzed_and_truncated_files_raise_only_value_error(tmp_path):
    save_scene(plain_scene(6, 2), tmp_path / "source.ksplat")
    original = (tmp_path / "source.ksplat").read_bytes()
    rng = np.random.default_rng(2)
    for case in range(60):
        data = bytearray(original)
        for position in rng.integers(0, 4096 + 1024 + 64, 3):  # the headers and the first records
            data[position] = int(rng.integers(0, 256))
        assert_only_value_errors(read_ksplat, tmp_path / "fuzzed.ksplat", bytes(data), f"case {case}")
    for length in list(range(0, 5200, 97)) + list(range(5200, len(original), 13)):
        assert_only_value_errors(read_ksplat, tmp_path / "cut.ksplat", original[:length], f"{length} bytes")


def _level_1_file(lengths: list[int], full: int = 0, bucket_size: int = 2, buckets: int = 1, count: int = 1) -> bytes:
    """A level-1, SH degree 0 file of ``count`` zero records and ``buckets`` bucket centres at the
    origin, whose section header gives ``full`` full buckets of ``bucket_size`` and partly filled
    buckets of ``lengths``."""
    rows = np.zeros(count, [("center", "<u2", 3), ("scale", "<f2", 3), ("rotation", "<f2", 4), ("rgba", "u1", 4)])
    rows["scale"], rows["rotation"] = 1, [1, 0, 0, 0]
    data = np.asarray(lengths, "<u4").tobytes() + bytes(12 * buckets) + rows.tobytes()
    return header(1, count, 1) + section_header(count, bucket_size, buckets, 4.0, 0, len(data), full, len(lengths)) + data


def test_bucket_lengths_are_checked_against_the_count_before_any_array_of_their_size(tmp_path):
    """A 5 kB file whose one partly filled bucket claims 2^24 Gaussians for a count of 1 is refused
    naming the field, with numpy's allocations under 1 MB (the lengths once made a 2^24-entry index)."""
    import tracemalloc

    path = tmp_path / "buckets.ksplat"
    path.write_bytes(_level_1_file([1]))
    assert len(read_ksplat(path)) == 1
    cases = [([2**24], 0, r"lengths adding up to 16777216\) hold 16,777,216 Gaussians, not its splatCount 1"),
             ([0], 0, r"hold 0 Gaussians, not its splatCount 1"),
             ([1], 1, r"fullBucketCount 1 \+ partiallyFilledBucketCount 1 is more than its bucketCount 1")]
    for lengths, full, message in cases:
        path.write_bytes(_level_1_file(lengths, full))
        assert path.stat().st_size < 6000
        tracemalloc.start()
        try:
            with pytest.raises(ValueError, match=rf"buckets\.ksplat: section 0: .*{message}"):
                read_ksplat(path)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 2**20, peak


def test_bucket_centres_of_another_size_than_three_floats_are_refused(tmp_path):
    """Found by fuzzing: a bucketStorageSizeBytes of 0 with a large bucketCount made the read of the bucket
    centres (3 float32 each, as SplatBuffer.js reads them) run past the file: numpy's error named no file."""
    data = bytearray(_level_1_file([1]))
    struct.pack_into("<I", data, 4096 + 12, 1000)  # bucketCount
    struct.pack_into("<H", data, 4096 + 20, 0)  # bucketStorageSizeBytes
    path = tmp_path / "centres.ksplat"
    path.write_bytes(data)
    with pytest.raises(ValueError, match=r"centres\.ksplat: section 0: bucketStorageSizeBytes: 0, expected 12"):
        read_ksplat(path)
