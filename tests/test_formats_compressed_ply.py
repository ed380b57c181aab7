"""PlayCanvas / SuperSplat compressed PLY: bit layout by hand, an encoded scene, corrupt files."""

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from artnvg_core.formats import load_scene
from artnvg_core.scene import SH_C0
from tests.test_formats_splat import assert_only_value_errors, plain_scene, quat_error

BOUNDS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
          "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
COLOURS = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]


def write_compressed(path, chunks: np.ndarray, packed: np.ndarray, sh: np.ndarray | None = None, colours=None,
                     packed_type: str = "<u4"):
    """A compressed PLY from chunk rows [C, 12], packed codes [N, 4] (declared ``packed_type``) and SH
    bytes [N, M] (INRIA order)."""
    names = BOUNDS + (COLOURS if colours is not None else [])
    chunk = np.empty(len(chunks), dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(BOUNDS):
        chunk[name] = chunks[:, i]
    for i, name in enumerate(COLOURS if colours is not None else []):
        chunk[name] = colours[:, i]
    vertex = np.empty(len(packed), dtype=[(name, packed_type) for name in PACKED])
    for i, name in enumerate(PACKED):
        vertex[name] = packed[:, i]
    elements = [PlyElement.describe(chunk, "chunk"), PlyElement.describe(vertex, "vertex")]
    if sh is not None:
        table = np.empty(len(sh), dtype=[(f"f_rest_{i}", "u1") for i in range(sh.shape[1])])
        for i in range(sh.shape[1]):
            table[f"f_rest_{i}"] = sh[:, i]
        elements.append(PlyElement.describe(table, "sh"))
    PlyData(elements).write(str(path))


def pack_11_10_11(t: np.ndarray) -> np.ndarray:
    q = np.round(t * [2047, 1023, 2047]).astype(np.int64)
    return q[:, 0] << 21 | q[:, 1] << 11 | q[:, 2]


def encode(scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chunk bounds, packed codes and SH bytes of ``scene`` (one chunk per 256 Gaussians)."""
    n = len(scene)
    means, log_scales = scene.means.double().numpy(), scene.log_scales.double().numpy()
    chunks, packed = [], np.zeros((n, 4), np.int64)
    for start in range(0, n, 256):
        rows = slice(start, start + 256)
        lo_p, hi_p = means[rows].min(0), means[rows].max(0)
        lo_s, hi_s = log_scales[rows].min(0), log_scales[rows].max(0)
        chunks.append(np.concatenate([lo_p, hi_p, lo_s, hi_s]))
        packed[rows, 0] = pack_11_10_11((means[rows] - lo_p) / (hi_p - lo_p))
        packed[rows, 2] = pack_11_10_11((log_scales[rows] - lo_s) / (hi_s - lo_s))
    q = torch.nn.functional.normalize(scene.quats.double(), dim=1).numpy()
    largest = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(n), largest] < 0, -1, 1)[:, None]
    code = largest.astype(np.int64)
    for i in range(4):
        ten = np.round((q[:, i] / np.sqrt(2) + 0.5) * 1023).astype(np.int64)
        code = np.where(largest != i, code << 10 | ten, code)
    packed[:, 1] = code
    rgb = np.clip(SH_C0 * scene.sh[:, 0].double().numpy() + 0.5, 0, 1)
    alpha = torch.sigmoid(scene.opacity_logits.double()).numpy()
    bytes4 = np.round(np.concatenate([rgb, alpha[:, None]], 1) * 255).astype(np.int64)
    packed[:, 3] = bytes4[:, 0] << 24 | bytes4[:, 1] << 16 | bytes4[:, 2] << 8 | bytes4[:, 3]
    rest = scene.sh[:, 1:].transpose(1, 2).reshape(n, -1).double().numpy()  # channel-major f_rest
    sh = np.clip(np.floor((rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
    return np.stack(chunks), packed, sh


def test_hand_written_record_pins_the_bit_layout(tmp_path):
    chunks = np.array([[0, 10, 20, 1, 30, 24, -5, -4, -3, -1, 0, 1]], np.float64)
    position = 2047 << 21 | 0 << 11 | 1023  # x max, y min, z 1023/2047
    rotation = 2 << 30 | 1023 << 20 | 511 << 10 | 0  # largest is rot_2; rot_0, rot_1, rot_3 from the codes
    scale = 0 << 21 | 1023 << 11 | 2047
    colour = 255 << 24 | 0 << 16 | 51 << 8 | 128
    path = tmp_path / "hand.compressed.ply"
    write_compressed(path, chunks, np.array([[position, rotation, scale, colour]]))
    scene = load_scene(path)
    torch.testing.assert_close(scene.means, torch.tensor([[1.0, 10, 20 + 4 * 1023 / 2047]]))
    torch.testing.assert_close(scene.log_scales, torch.tensor([[-5.0, 0, 1]]))
    a, b, c = (1023 / 1023 - 0.5) * np.sqrt(2), (511 / 1023 - 0.5) * np.sqrt(2), (0 - 0.5) * np.sqrt(2)
    expected = torch.tensor([[a, b, np.sqrt(max(0, 1 - a * a - b * b - c * c)), c]], dtype=torch.float32)
    torch.testing.assert_close(scene.quats, expected)
    torch.testing.assert_close(SH_C0 * scene.sh[0, 0] + 0.5, torch.tensor([1.0, 0, 0.2]))
    torch.testing.assert_close(torch.sigmoid(scene.opacity_logits), torch.tensor([128 / 255]))


def test_encoded_scene_reads_back_within_the_packing_steps(tmp_path):
    scene = plain_scene(600, 1)
    scene.sh[:, 1:] = scene.sh[:, 1:].clamp(-3.9, 3.9)
    chunks, packed, sh = encode(scene)
    path = tmp_path / "scene.ply"
    write_compressed(path, chunks, packed, sh)
    back = load_scene(path)
    assert back.sh_degree == 1 and len(back) == 600
    span = torch.from_numpy(chunks[:, 3:6] - chunks[:, :3]).repeat_interleave(256, 0)[:600]
    steps = torch.tensor([2047.0, 1023, 2047], dtype=torch.float64)
    assert ((back.means - scene.means).abs() <= span / steps * 0.51 + 1e-5).all()
    assert quat_error(back.quats, scene.quats) <= 0.002
    colour = (SH_C0 * scene.sh[:, 0] + 0.5).clamp(0, 1)
    assert ((SH_C0 * back.sh[:, 0] + 0.5) - colour).abs().max() <= 0.5 / 255 + 1e-6
    assert (back.sh[:, 1:] - scene.sh[:, 1:]).abs().max() <= 8 / 256 + 1e-6
    # per-chunk colour ranges: r g b scaled to min..max
    colours = np.tile([[0.2, 0.2, 0.2, 0.6, 0.6, 0.6]], (len(chunks), 1))
    write_compressed(path, chunks, packed, sh, colours=colours)
    scaled = load_scene(path)
    rgb = SH_C0 * scaled.sh[:, 0].double() + 0.5
    assert rgb.min() >= 0.2 - 1e-6 and rgb.max() <= 0.6 + 1e-6


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda c, p, s: (c[:1], p, s), r"element 'chunk': count 1, expected 2 \(one per 256 of the 300 vertices\)"),
        (lambda c, p, s: (c, p, s[:299]), r"element 'sh': 9 properties for 299 rows, expected 9, 24 or 45"),
        (lambda c, p, s: (c, p, s[:, :7]), r"element 'sh': 7 properties for 300 rows"),
    ],
)
def test_inconsistent_elements_name_the_element(tmp_path, mutate, message):
    path = tmp_path / "bad.ply"
    write_compressed(path, *mutate(*encode(plain_scene(300, 1))))
    with pytest.raises(ValueError, match=rf"bad\.ply: {message}"):
        load_scene(path)


def test_missing_chunk_property_is_named(tmp_path):
    chunks, packed, _ = encode(plain_scene(20, 0))
    path = tmp_path / "bad.ply"
    write_compressed(path, chunks, packed)
    path.write_bytes(path.read_bytes().replace(b"property float max_scale_z", b"property float max_scale_w"))
    with pytest.raises(ValueError, match=r"bad\.ply: element 'chunk' lacks properties max_scale_z"):
        load_scene(path)


def test_fuzzed_and_truncated_files_raise_only_value_error(tmp_path):
    chunks, packed, sh = encode(plain_scene(40, 1))
    write_compressed(tmp_path / "source.ply", chunks, packed, sh)
    original = (tmp_path / "source.ply").read_bytes()
    header = original.index(b"end_header\n") + 11
    rng = np.random.default_rng(3)
    for case in range(100):
        data = bytearray(original)
        span = header if case % 2 else len(data)
        for position in rng.integers(0, span, 3):
            data[position] = int(rng.integers(0, 256))
        assert_only_value_errors(load_scene, tmp_path / "fuzzed.ply", bytes(data), f"case {case}")
    for length in range(0, len(original), 13):
        path = tmp_path / "cut.ply"
        assert_only_value_errors(load_scene, path, original[:length], f"cut to {length}")
        with pytest.raises(ValueError, match=r"cut\.ply: "):
            load_scene(path)


@pytest.mark.parametrize("declared", ["<f8", "<f4", "<i4"])
def test_packed_columns_are_read_by_their_declared_type(tmp_path, declared):
    """packed_* declared as double, float (codes under 2^24, exact in float32) or int32 read as the
    same codes as uint32 (a float column once raised TypeError); a fractional or negative code is named."""
    scene = plain_scene(300, 1)
    chunks, packed, sh = encode(scene)
    packed &= (1 << 24) - 1  # every code exact in float32
    write_compressed(tmp_path / "u4.ply", chunks, packed, sh)
    reference = load_scene(tmp_path / "u4.ply")
    write_compressed(tmp_path / "typed.ply", chunks, packed.astype(declared), sh, packed_type=declared)
    back = load_scene(tmp_path / "typed.ply")
    for name, value in reference.tensors().items():
        assert torch.equal(getattr(back, name), value), name
    bad = packed.astype(np.float64)
    bad[7, 2] = -1.0 if declared == "<i4" else 0.5
    write_compressed(tmp_path / "bad.ply", chunks, bad.astype(declared), sh, packed_type=declared)
    with pytest.raises(ValueError, match=r"bad\.ply: element 'vertex': packed_\* values must be whole numbers from 0 "
                       r"to 2\^32 - 1 \(declared (float|int)"):
        load_scene(tmp_path / "bad.ply")


def test_decoded_in_chunks_as_whole_with_progress_and_a_stop_between_chunks(tmp_path, monkeypatch):
    """Chunks of 100 Gaussians straddle the file's 256-Gaussian chunks: the same bits as one chunk; one bar fills
    over the elements read, the decoding and the check."""
    from artnvg_core import scene
    from artnvg_core.formats import common, compressed_ply, ply
    from artnvg_core.progress import Cancelled
    from tests.test_formats import assert_one_bar
    from tests.test_formats_ply import assert_same_bits

    path = tmp_path / "scene.compressed.ply"
    chunks, packed, sh = encode(plain_scene(1000, 3))
    write_compressed(path, chunks, packed, sh, colours=np.tile([0.1, 0.0, 0.2, 0.9, 1.0, 0.8], (len(chunks), 1)))
    whole = load_scene(path)
    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 100)
    monkeypatch.setattr(scene, "CHECKED_ROWS", 100)
    calls = []
    assert_same_bits(load_scene(path, progress=lambda *call: calls.append(call)), whole)
    assert_one_bar(calls, path.stat().st_size, ply.READ_STAGES["compressed"])
    decode, decoded = compressed_ply._packed_codes, []
    monkeypatch.setattr(compressed_ply, "_packed_codes", lambda *args: decoded.append(args[2]) or decode(*args))
    with pytest.raises(Cancelled):
        load_scene(path, should_stop=lambda: len(decoded) == 4)
    assert decoded[1:] == [slice(0, 100), slice(100, 200), slice(200, 300)]  # none after the stop
