"""INRIA PLY files: read/write bit-exactly, Mip-Splatting's filter_3D, structure errors, corrupt bytes."""

from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

import artnvg_core.formats.ply as ply_module
from artnvg_core.formats import load_scene
from artnvg_core.formats.ply import read_ply, write_ply
from artnvg_core.scene import GaussianScene, validate_scene

FORMATS = ["binary_little_endian", "binary_big_endian", "ascii"]
BYTE_ORDER = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}


# --------------------------------------------------------------------------- helpers


def random_scene(n: int, degree: int, seed: int = 0) -> GaussianScene:
    """A valid float32 scene whose first rows hold awkward float32 values."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    scene = GaussianScene(
        means=torch.randn(n, 3, generator=g) * 10,
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, k, 3, generator=g),
    )
    finfo = torch.finfo(torch.float32)
    awkward = torch.tensor([0.0, -0.0, finfo.smallest_normal / 8, 1 / 3, finfo.max, -finfo.tiny, 2.0**-149])
    scene.means[0] = awkward[:3]
    scene.log_scales[1] = awkward[3:6]
    scene.opacity_logits[2] = awkward[6]
    scene.sh.view(-1)[: len(awkward)] = awkward
    return scene


def write_reference_ply(
    path: Path,
    scene: GaussianScene,
    fmt: str = "binary_little_endian",
    *,
    normals: bool = True,
    extra: bool = False,
    shuffle_seed: int | None = None,
    float_type: str = "f4",
    drop: tuple[str, ...] = (),
) -> None:
    """Write ``scene`` with plyfile, naming every INRIA property one coefficient at a time."""
    n, k = scene.sh.shape[:2]
    columns = {name: scene.means[:, i] for i, name in enumerate("xyz")}
    if normals:
        columns.update({name: torch.randn(n) for name in ("nx", "ny", "nz")})
    columns.update({f"f_dc_{c}": scene.sh[:, 0, c] for c in range(3)})
    for c in range(3):  # channel-major: all R coefficients, then G, then B
        for j in range(k - 1):
            columns[f"f_rest_{c * (k - 1) + j}"] = scene.sh[:, 1 + j, c]
    columns["opacity"] = scene.opacity_logits
    columns.update({f"scale_{i}": scene.log_scales[:, i] for i in range(3)})
    columns.update({f"rot_{i}": scene.quats[:, i] for i in range(4)})
    columns = {name: value.double().numpy() for name, value in columns.items() if name not in drop}
    types = {name: float_type for name in columns}
    if extra:
        columns["red"], types["red"] = np.arange(n, dtype=np.uint8), "u1"
        columns["confidence"], types["confidence"] = np.linspace(0, 1, n), "f8"
    names = list(columns)
    if shuffle_seed is not None:
        np.random.default_rng(shuffle_seed).shuffle(names)
    table = np.empty(n, dtype=[(name, types[name]) for name in names])
    for name in names:
        table[name] = columns[name]
    elements = [PlyElement.describe(table, "vertex")]
    if extra:
        faces = np.empty(2, dtype=[("vertex_indices", "O")])
        faces["vertex_indices"] = [np.array([0, 1, 2], dtype=np.int32), np.array([2, 1, 0], dtype=np.int32)]
        elements.append(PlyElement.describe(faces, "face"))
    PlyData(elements, text=fmt == "ascii", byte_order=BYTE_ORDER[fmt]).write(str(path))


def assert_same_bits(actual: GaussianScene, expected: GaussianScene) -> None:
    for name, value in expected.tensors().items():
        got = getattr(actual, name)
        assert got.dtype == torch.float32, name
        assert got.shape == value.shape, name
        assert torch.equal(got.view(torch.int32), value.float().view(torch.int32)), name


# --------------------------------------------------------------------------- PLY round trips


@pytest.mark.parametrize("normals", [True, False])
@pytest.mark.parametrize("degree", range(4))
@pytest.mark.parametrize("fmt", FORMATS)
def test_reference_ply_reads_and_round_trips_bit_exactly(tmp_path, fmt, degree, normals):
    scene = random_scene(9, degree, seed=degree)
    source = tmp_path / "source.ply"
    write_reference_ply(source, scene, fmt, normals=normals)

    loaded = read_ply(source)
    assert loaded.sh_degree == degree
    assert_same_bits(loaded, scene)
    for binary in (True, False):
        target = tmp_path / f"written_{binary}.ply"
        write_ply(loaded, target, binary=binary)
        assert_same_bits(read_ply(target), scene)
        assert_same_bits(read_ply(target), read_ply(source))


@pytest.mark.parametrize("fmt", FORMATS)
def test_extra_properties_elements_and_shuffled_order_are_accepted(tmp_path, fmt):
    scene = random_scene(6, 3, seed=4)
    source = tmp_path / "shuffled.ply"
    write_reference_ply(source, scene, fmt, extra=True, shuffle_seed=7)
    order = [p.name for p in PlyData.read(str(source))["vertex"].properties]
    assert order[:3] != ["x", "y", "z"] and "red" in order  # really shuffled, really extra
    assert_same_bits(read_ply(source), scene)


def test_hand_written_ascii_ply_maps_f_rest_channel_major(tmp_path):
    # Degree 1: K - 1 = 3 coefficients per channel; f_rest_{3c + j} -> sh[:, 1 + j, c].
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(9)),
             "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = [
        "1 2 3 10 11 12 100 101 102 103 104 105 106 107 108 -1.5 -1 -2 -3 0.5 0.25 0.125 2",
        "4 5 6 20 21 22 200 201 202 203 204 205 206 207 208 2.5 -4 -5 -6 1 0 0 0",
    ]
    text = "\n".join(["ply", "format ascii 1.0", "comment hand written", "element vertex 2",
                      *(f"property float {name}" for name in names), "end_header", *rows]) + "\n"
    path = tmp_path / "hand.ply"
    path.write_text(text)

    scene = read_ply(path)
    assert scene.sh_degree == 1
    for g, base in enumerate((100, 200)):
        for c in range(3):
            for j in range(3):
                assert scene.sh[g, 1 + j, c] == base + 3 * c + j
    assert scene.sh[0, 1].tolist() == [100, 103, 106]  # first coefficient of R, G, B
    assert scene.sh[1, 0].tolist() == [20, 21, 22]
    assert scene.means.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert scene.quats[0].tolist() == [0.5, 0.25, 0.125, 2]  # rot_0 is w
    assert scene.log_scales[1].tolist() == [-4, -5, -6]
    assert scene.opacity_logits.tolist() == [-1.5, 2.5]


def test_written_ply_has_the_inria_layout(tmp_path):
    scene = random_scene(5, 2)
    for binary, fmt in ((True, "binary_little_endian"), (False, "ascii")):
        path = tmp_path / f"{fmt}.ply"
        write_ply(scene, path, binary=binary)
        ply = PlyData.read(str(path))
        assert (ply.text, ply.byte_order) == ((False, "<") if binary else (True, "="))
        vertex = ply["vertex"]
        expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
                    *(f"f_rest_{i}" for i in range(24)), "opacity",
                    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        assert [p.name for p in vertex.properties] == expected
        assert all(vertex.data.dtype[name] == np.dtype("<f4" if binary else "f4") for name in expected)
        assert not vertex.data["nx"].any()
        np.testing.assert_array_equal(vertex.data["f_rest_8"], scene.sh[:, 1, 1].numpy())  # G, coefficient 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ascii.ply", "binary_little_endian.ply"]


def test_write_ply_converts_float64_and_grad_tensors(tmp_path):
    scene = random_scene(4, 1).map(lambda t: t.double().requires_grad_())
    write_ply(scene, tmp_path / "out.ply")
    assert_same_bits(read_ply(tmp_path / "out.ply"), scene.map(lambda t: t.detach().float()))


def test_float64_ply_is_rounded_to_float32(tmp_path):
    scene = random_scene(5, 1).map(lambda t: t.double() * (1 + 1e-12))  # not float32-representable
    path = tmp_path / "double.ply"
    write_reference_ply(path, scene, float_type="f8")
    assert_same_bits(read_ply(path), scene.map(lambda t: t.float()))


def test_float64_overflowing_float32_is_rejected(tmp_path):
    scene = random_scene(5, 0).map(lambda t: t.double())
    scene.log_scales[3, 1] = 1e300
    path = tmp_path / "huge.ply"
    write_reference_ply(path, scene, float_type="f8")
    message = r"huge\.ply: log_scales: 1 of 5 Gaussians has non-finite values \(first at index 3\)"
    with pytest.raises(ValueError, match=message):
        read_ply(path)


# --------------------------------------------------------------------------- PLY structure errors


@pytest.mark.parametrize("missing", ["x", "f_dc_1", "opacity", "scale_2", "rot_0"])
def test_missing_property_is_named(tmp_path, missing):
    path = tmp_path / "incomplete.ply"
    write_reference_ply(path, random_scene(3, 1), drop=(missing,))
    with pytest.raises(ValueError, match=rf"incomplete\.ply: element 'vertex' lacks property {missing}$"):
        read_ply(path)


def test_point_cloud_is_named_as_one_not_as_a_scene_missing_properties(tmp_path):
    """A capture's sparse points (nerfstudio's sparse_pc.ply: x y z and colours), picked for the scene: the
    message says what the file is and what to pick instead."""
    path = tmp_path / "sparse_pc.ply"
    path.write_text("\n".join(["ply", "format ascii 1.0", "element vertex 2", *(f"property float {n}" for n in "xyz"),
                               *(f"property uchar {c}" for c in ("red", "green", "blue")), "end_header",
                               "0 0 0 10 20 30", "1 2 3 40 50 60"]) + "\n")
    with pytest.raises(ValueError, match=r"sparse_pc\.ply: a point cloud or mesh, not a Gaussian scene: .* "
                                         r"expected a trained 3DGS scene"):
        read_ply(path)


def test_f_rest_count_that_is_no_sh_degree_is_rejected(tmp_path):
    path = tmp_path / "rest10.ply"
    write_reference_ply(path, random_scene(3, 1))
    data = PlyData.read(str(path))["vertex"].data
    table = np.empty(len(data), dtype=data.dtype.descr + [("f_rest_9", "<f4")])
    for name in data.dtype.names:
        table[name] = data[name]
    PlyData([PlyElement.describe(table, "vertex")]).write(str(path))
    with pytest.raises(ValueError, match=r"rest10\.ply: f_rest_\*: found 10 properties, expected 0, 9, 24 or 45"):
        read_ply(path)


def test_gap_in_f_rest_numbering_names_the_missing_property(tmp_path):
    path = tmp_path / "gap.ply"
    write_reference_ply(path, random_scene(3, 1))
    path.write_bytes(path.read_bytes().replace(b"property float f_rest_8\n", b"property float f_rest_9\n"))
    with pytest.raises(ValueError, match=r"gap\.ply: element 'vertex' lacks property f_rest_8"):
        read_ply(path)


def test_file_without_vertex_element_is_rejected(tmp_path):
    path = tmp_path / "points.ply"
    write_reference_ply(path, random_scene(3, 0))
    path.write_bytes(path.read_bytes().replace(b"element vertex", b"element points"))
    with pytest.raises(ValueError, match=r"points\.ply: no 'vertex' element \(found \['points'\]\)"):
        read_ply(path)


def test_list_property_in_place_of_a_scalar_is_rejected(tmp_path):
    path = tmp_path / "list.ply"
    text = "\n".join(["ply", "format ascii 1.0", "element vertex 1", "property list uchar float x",
                      *(f"property float {n}" for n in ["y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                                                         "scale_0", "scale_1", "scale_2",
                                                         "rot_0", "rot_1", "rot_2", "rot_3"]),
                      "end_header", "2 1 2 0 0 0 0 0 0 0 0 0 1 0 0 0"]) + "\n"
    path.write_text(text)
    with pytest.raises(ValueError, match=r"list\.ply: property x is a list"):
        read_ply(path)


# --------------------------------------------------------------------------- validation


def _set(field: str, index, value: float):
    def apply(scene: GaussianScene) -> None:
        getattr(scene, field)[index] = value
    return apply


@pytest.mark.parametrize(
    ("field", "corrupt", "problem"),
    [
        ("means", _set("means", ([2, 5], 1), float("nan")), "non-finite values"),
        ("log_scales", _set("log_scales", ([2, 5], 0), float("inf")), "non-finite values"),
        ("opacity_logits", _set("opacity_logits", [2, 5], -float("inf")), "non-finite values"),
        ("sh", _set("sh", ([2, 5], 3, 2), float("nan")), "non-finite values"),
        ("quats", _set("quats", ([2, 5], 3), float("nan")), "non-finite values"),
        ("quats", _set("quats", [2, 5], 0.0), "a zero norm"),
    ],
)
@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_invalid_gaussians_are_rejected_naming_file_field_count_and_index(tmp_path, fmt, field, corrupt, problem):
    scene = random_scene(8, 1)
    corrupt(scene)
    path = tmp_path / "bad.ply"
    write_reference_ply(path, scene, fmt)
    message = rf"bad\.ply: {field}: 2 of 8 Gaussians have {problem} \(first at index 2\); pass drop_invalid=True"
    with pytest.raises(ValueError, match=message):
        read_ply(path)
    with pytest.raises(ValueError, match=message):
        load_scene(path)


def test_drop_invalid_removes_and_reports_exactly_the_bad_gaussians(tmp_path, caplog):
    scene = random_scene(10, 2)
    scene.means[1, 0] = float("nan")
    scene.quats[4] = 0.0
    scene.sh[4, 7, 1] = float("inf")  # same Gaussian twice: counted once
    scene.log_scales[6, 2] = -float("inf")
    path = tmp_path / "some_bad.ply"
    write_reference_ply(path, scene)
    keep = torch.tensor([i not in (1, 4, 6) for i in range(10)])

    with caplog.at_level("WARNING", logger="artnvg_core.scene"):
        loaded = read_ply(path, drop_invalid=True)
    assert_same_bits(loaded, scene.select(keep))
    assert "some_bad.ply: dropped 3 invalid Gaussians of 10" in caplog.text
    assert "means: 1 with non-finite values" in caplog.text and "quats: 1 with a zero norm" in caplog.text

    cleaned, dropped = validate_scene(scene, "memory", drop_invalid=True)
    assert dropped == 3
    assert_same_bits(cleaned, scene.select(keep))


# --------------------------------------------------------------------------- corrupt bytes


def _read_expecting_value_error_only(path: Path, data: bytes, case: str) -> bool:
    """Read ``data`` as a PLY; True when it parsed, False on ValueError, test failure otherwise."""
    path.write_bytes(data)
    try:
        read_ply(path)
    except ValueError:
        return False
    except Exception as error:  # noqa: BLE001 - any other type is the bug under test
        pytest.fail(f"{case}: {type(error).__name__} escaped: {error}")
    return True


@pytest.mark.filterwarnings("ignore:loadtxt:UserWarning")  # plyfile on empty text lists
@pytest.mark.parametrize("fmt", FORMATS)
def test_fuzzed_bytes_raise_only_value_error(tmp_path, fmt):
    source = tmp_path / "source.ply"
    write_reference_ply(source, random_scene(3, 1), fmt, extra=True)
    original = source.read_bytes()
    header_length = original.index(b"end_header\n") + len(b"end_header\n")
    rng = np.random.default_rng(BYTE_ORDER[fmt].encode()[0])
    path = tmp_path / "fuzzed.ply"

    for case in range(300):
        data = bytearray(original)
        span = header_length if case % 2 else len(data)  # half the flips aimed at the header
        for _ in range(rng.integers(1, 4)):
            position = int(rng.integers(0, span))
            data[position] = int(rng.integers(0, 256)) if case % 3 else data[position] ^ (1 << int(rng.integers(0, 8)))
        _read_expecting_value_error_only(path, bytes(data), f"flip case {case}")

    for length in sorted(set(rng.integers(0, len(original) - 1, 150).tolist()) | set(range(header_length + 1))):
        parsed = _read_expecting_value_error_only(path, original[:length], f"truncated to {length} bytes")
        assert not (parsed and length <= header_length), f"header truncated to {length} bytes was accepted"


@pytest.mark.filterwarnings("ignore:loadtxt:UserWarning")  # plyfile on empty text lists
@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize(
    ("old", "new"),
    [
        (b"element vertex 3\n", b"element vertex 99999999999999999999\n"),
        (b"element vertex 3\n", b"element vertex -3\n"),
        (b"element vertex 3\n", b"element vertex three\n"),
        (b"element vertex 3\n", b"element vertex 4\n"),
        (b" 1.0\n", b" 2.0\n"),
        (b"property float x\n", b"property list uchar float x\n"),
        (b"property float x\n", b"property flaot x\n"),
        (b"property float x\n", b"property float \xff\n"),
        (b"property float y\n", b"property float x\n"),
        (b"ply\n", b"plx\n"),
        (b"end_header\n", b"end_headr\n"),
    ],
)
def test_corrupt_headers_raise_value_error(tmp_path, fmt, old, new):
    path = tmp_path / "corrupt.ply"
    write_reference_ply(path, random_scene(3, 1), fmt, normals=False)
    data = path.read_bytes()
    assert old in data
    path.write_bytes(data.replace(old, new, 1))
    with pytest.raises(ValueError, match=r"corrupt\.ply: "):
        read_ply(path)


def test_an_element_without_properties_or_declared_twice_is_refused(tmp_path):
    """Found by fuzzing: an 'element vertex N' line alone, or repeated, made a vertex element without
    properties, whose rows of no bytes numpy refused with a message naming no file."""
    path = tmp_path / "elements.ply"
    write_reference_ply(path, random_scene(3, 1), "binary_little_endian")
    repeated = path.read_bytes().replace(b"end_header\n", b"element vertex 3\nend_header\n", 1)
    alone = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n"
    for data, problem in ((alone, "declares no properties"), (repeated, "is declared twice")):
        path.write_bytes(data)
        with pytest.raises(ValueError, match=rf"elements\.ply: not a readable PLY file \(element 'vertex' {problem}\)"):
            read_ply(path)


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("declared", [1, 2])
def test_header_count_smaller_than_the_data_is_an_error(tmp_path, fmt, declared):
    path = tmp_path / "short_count.ply"
    write_reference_ply(path, random_scene(3, 1), fmt)
    path.write_bytes(path.read_bytes().replace(b"element vertex 3\n", f"element vertex {declared}\n".encode(), 1))
    with pytest.raises(ValueError, match=rf"short_count\.ply: the header's element counts \(vertex {declared}\) "
                                         "disagree with the data size"):
        read_ply(path)


@pytest.mark.parametrize("fmt", FORMATS)
def test_trailing_bytes_after_the_last_element_are_an_error(tmp_path, fmt):
    path = tmp_path / "trailing.ply"
    write_reference_ply(path, random_scene(3, 1), fmt, extra=True)
    read_ply(path)
    path.write_bytes(path.read_bytes() + (b"3 0 1 2\n" if fmt == "ascii" else b"\0" * 7))
    with pytest.raises(ValueError, match=r"trailing\.ply: the header's element counts \(vertex 3, face 2\)"):
        read_ply(path)


def test_empty_and_missing_files(tmp_path):
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.ply: not a readable PLY file"):
        read_ply(tmp_path / "empty.ply")
    with pytest.raises(ValueError, match=r"absent\.ply: scene file not found"):
        read_ply(tmp_path / "absent.ply")


# --------------------------------------------------------------------------- atomic write


def test_failed_write_leaves_no_partial_target_and_no_temporary_file(tmp_path, monkeypatch):
    def fail_mid_write(stream, table, binary):
        stream.write(b"partial rows")
        raise OSError("disk full")

    monkeypatch.setattr(ply_module, "_write_ply_body", fail_mid_write)
    existing = tmp_path / "existing.ply"
    existing.write_bytes(b"previous content")
    for binary in (True, False):
        with pytest.raises(OSError, match="disk full"):
            write_ply(random_scene(4, 1), existing, binary=binary)
        with pytest.raises(OSError, match="disk full"):
            write_ply(random_scene(4, 1), tmp_path / "new.ply", binary=binary)
    assert existing.read_bytes() == b"previous content"
    assert [p.name for p in tmp_path.iterdir()] == ["existing.ply"]


def test_write_replaces_an_existing_file(tmp_path):
    path = tmp_path / "scene.ply"
    path.write_bytes(b"old")
    scene = random_scene(4, 0)
    write_ply(scene, path)
    assert_same_bits(read_ply(path), scene)
    assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]


# --------------------------------------------------------------------------- real data


def test_bear_scene_loads_and_round_trips_exactly(shared_data, tmp_path):
    path = shared_data / "scenes" / "bear" / "scene.ply"
    scene = read_ply(path)
    assert len(scene) == 100_000 and scene.sh_degree == 3
    assert all(torch.isfinite(t).all() for t in scene.tensors().values())

    raw = PlyData.read(str(path))["vertex"].data
    np.testing.assert_array_equal(scene.sh[:, 1, 1].numpy(), raw["f_rest_15"])  # G, coefficient 1
    np.testing.assert_array_equal(scene.sh[:, 15, 2].numpy(), raw["f_rest_44"])  # B, coefficient 15
    np.testing.assert_array_equal(scene.quats[:, 0].numpy(), raw["rot_0"])

    write_ply(scene, tmp_path / "bear.ply")
    assert_same_bits(read_ply(tmp_path / "bear.ply"), scene)


# --------------------------------------------------------------------------- bounded by the file's size


def _peak_bytes(read) -> int:
    """Peak bytes traced (Python and numpy allocations) while ``read()`` runs, whatever it raises."""
    import tracemalloc

    tracemalloc.start()
    try:
        read()
    except ValueError:
        pass
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_huge_declared_element_is_refused_without_building_its_rows(tmp_path, fmt):
    path = tmp_path / "declared.ply"
    write_reference_ply(path, random_scene(3, 0), fmt, normals=False)
    header, _, body = path.read_bytes().partition(b"end_header\n")
    path.write_bytes(header + b"element face 3000000\nproperty list uchar int vertex_indices\nend_header\n" + body)
    assert _peak_bytes(lambda: read_ply(path)) < 1 << 22  # plyfile built the 3M rows: 24 MB of pointers alone
    with pytest.raises(ValueError, match=r"declared\.ply: (element 'face': 3,000,000 rows need at least [36],000,000 "
                       r"bytes, but the file has \d+ left|the header's element counts \(vertex 3, face 3000000\))"):
        read_ply(path)


def test_a_header_beyond_its_bound_is_refused(tmp_path):
    path = tmp_path / "long_header.ply"
    write_reference_ply(path, random_scene(3, 0), normals=False)
    comments = b"comment " + b"x" * 70 + b"\n"
    path.write_bytes(path.read_bytes().replace(b"ply\n", b"ply\n" + comments * (2**21 // len(comments)), 1))
    with pytest.raises(ValueError, match=r"long_header\.ply: not a readable PLY file \(no end_header line within the "
                       r"first [\d,]+ bytes: the header is truncated or far longer than a scene's"):
        read_ply(path)


@pytest.mark.parametrize("fmt", FORMATS)
def test_list_elements_are_skipped_by_their_byte_count_before_and_after_the_vertices(tmp_path, fmt):
    scene = random_scene(5, 1)
    path = tmp_path / "mesh.ply"
    write_reference_ply(path, scene, fmt)
    table = PlyData.read(str(path), mmap=False)["vertex"].data
    uneven = np.empty(4, dtype=[("material", "u1"), ("corners", "O"), ("weight", "f8")])
    uneven["material"], uneven["weight"] = [1, 2, 3, 4], [0.5, 1.5, 2.5, 3.5]
    uneven["corners"] = [np.arange(n, dtype=np.int16) for n in (3, 0, 5, 4)]  # lengths differ: one pass over them
    even = np.empty(3, dtype=[("vertex_indices", "O")])
    even["vertex_indices"] = [np.array([0, 1, 2], np.uint32)] * 3  # same lengths: one strided look
    elements = [PlyElement.describe(uneven, "polygon"), PlyElement.describe(table, "vertex"),
                PlyElement.describe(even, "face")]
    PlyData(elements, text=fmt == "ascii", byte_order=BYTE_ORDER[fmt]).write(str(path))
    assert_same_bits(read_ply(path), scene)
    data = path.read_bytes()
    path.write_bytes(data + (b"1 0 0.5\n" if fmt == "ascii" else b"\0"))
    with pytest.raises(ValueError, match=r"mesh\.ply: the header's element counts \(polygon 4, vertex 5, face 3\) "
                       r"disagree with the data size: the file holds (1 byte more|13 data lines for 12 records)"):
        read_ply(path)
    path.write_bytes(data.replace(b"element polygon 4", b"element polygon 5"))
    with pytest.raises(ValueError, match=r"mesh\.ply: "):
        read_ply(path)



def test_an_ascii_ply_is_parsed_a_chunk_of_rows_at_a_time_with_progress_and_a_stop(tmp_path, monkeypatch):
    """Lines cut across blocks (of 100 bytes, shorter than a row), blank and CRLF lines, a list element after the
    vertices and no final newline read as the whole text does; the parse reports each chunk of 16 rows of all
    elements and stops between them, before the rows after the stop are parsed."""
    from artnvg_core.formats import common, ply_data
    from artnvg_core.progress import Cancelled

    scene = random_scene(40, 1)
    path = tmp_path / "text.ply"
    write_reference_ply(path, scene, "ascii")
    header, _, body = path.read_bytes().partition(b"end_header\n")
    rows = body.splitlines()
    rows[5], rows[6] = rows[5] + b"\r", b"  \n" + rows[6]  # a CRLF line, then a blank one
    path.write_bytes(header.replace(b"end_header", b"")
                     + b"element face 10\nproperty list uchar int vertex_indices\nend_header\n"
                     + b"\n".join(rows + [b"3 0 1 2"] * 10))
    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 16)
    monkeypatch.setattr(ply_data, "TEXT_BLOCK_BYTES", 100)
    parse, parsed = ply_data._text_rows, []
    monkeypatch.setattr(ply_data, "_text_rows", lambda *args: parsed.append(len(args[2])) or parse(*args))
    steps = []
    ply = ply_data.read_ply_header(path)
    ply_data.read_ply_elements(path, ply, ("vertex",), progress=lambda step, total, info: steps.append((step, total)))
    assert steps == [(0, 50), (16, 50), (32, 50), (40, 50), (50, 50)]  # the vertices in chunks, then the faces
    assert parsed == [16, 16, 8]  # the vertices' rows; the faces' lines only counted
    assert_same_bits(read_ply(path), scene)
    parsed.clear()
    with pytest.raises(Cancelled):
        read_ply(path, should_stop=lambda: len(parsed) == 2)
    assert parsed == [16, 16]


def test_an_ascii_plys_parse_takes_memory_for_its_values_not_its_text(tmp_path, monkeypatch):
    """Blocks of 1 MiB and chunks of 1,024 rows: the 20,000 Gaussians' float32 values (5 MB) and a few blocks' text
    and lines (11 MB), less than the 14 MB of text (the whole text's lines split at once took 6 times the file)."""
    from artnvg_core.formats import common, ply_data

    path = tmp_path / "text.ply"
    write_ply(random_scene(20000, 3), path, binary=False)
    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 1024)
    monkeypatch.setattr(ply_data, "TEXT_BLOCK_BYTES", 1 << 20)
    ply = ply_data.read_ply_header(path)
    assert _peak_bytes(lambda: ply_data.read_ply_elements(path, ply, ("vertex",))) < path.stat().st_size


def test_an_ascii_ply_line_beyond_its_bound_is_refused(tmp_path, monkeypatch):
    """A line of 1,000 bytes with no end (a binary file relabelled ascii, say) against a bound of 100: refused
    as soon as a block's text holds no end of line within the bound, not gathered to the end of the file."""
    from artnvg_core.formats import ply_data

    monkeypatch.setattr(ply_data, "MAX_LINE_BYTES", 100)
    monkeypatch.setattr(ply_data, "TEXT_BLOCK_BYTES", 64)
    path = tmp_path / "long.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n" + b"1" * 1000)
    with pytest.raises(ValueError, match=r"long\.ply: a data line longer than 100 bytes; not a PLY of numbers in text"):
        read_ply(path)
