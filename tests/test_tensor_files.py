"""Weight files read onto a device: our safetensors header parser and the chunked copy CUDA reads go
through (here into CPU tensors) against the safetensors library at every chunk size, dtype casts,
malformed files refused by name."""

import json
import struct
from fractions import Fraction

import pytest
import torch
from safetensors.torch import load_file, save_file

import artnvg_core.tensor_files as tensor_files
from artnvg_core.tensor_files import (
    READERS,
    STAGING_BYTES,
    load_failure,
    read_by_readers,
    read_tensors,
    reader_spans,
    safetensors_header,
    stream_into,
)


def _tensors() -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    return {"weight": torch.randn(5, 7, generator=generator), "half": torch.randn(3, generator=generator).half(),
            "bf16": torch.randn(2, 3, generator=generator).bfloat16(),
            "double": torch.randn(4, dtype=torch.float64, generator=generator),
            "ids": torch.arange(6, dtype=torch.int64).reshape(2, 3), "small": torch.arange(3, dtype=torch.int8),
            "flags": torch.tensor([True, False, True]), "scalar": torch.tensor(2.5), "empty": torch.zeros(0, 4)}


@pytest.fixture
def weights_file(tmp_path):
    path = tmp_path / "w.safetensors"
    save_file(_tensors(), str(path))
    return path


def test_safetensors_read_as_the_safetensors_library_reads_them(weights_file):
    expected, read = load_file(str(weights_file)), read_tensors(weights_file)
    assert read.keys() == expected.keys()
    for name, tensor in expected.items():
        assert read[name].dtype == tensor.dtype and read[name].shape == tensor.shape and torch.equal(read[name], tensor)


def test_a_dtype_converts_floating_tensors_only(weights_file):
    read = read_tensors(weights_file, dtype=torch.float16)
    for name, tensor in _tensors().items():
        wanted = tensor.to(torch.float16) if tensor.is_floating_point() else tensor
        assert read[name].dtype == wanted.dtype and torch.equal(read[name], wanted), name


def test_torch_save_files_are_read_too(tmp_path):
    path = tmp_path / "w.bin"
    torch.save(_tensors(), path)
    read = read_tensors(path, dtype=torch.bfloat16)
    assert read["ids"].dtype == torch.int64 and torch.equal(read["weight"], _tensors()["weight"].bfloat16())



def test_a_ckpt_holding_its_state_dict_under_state_dict_is_read(tmp_path):
    """PyTorch Lightning's layout, as the original Stability/CompVis .ckpt files are saved (and ComfyUI reads)."""
    path = tmp_path / "model.ckpt"
    torch.save({"state_dict": _tensors(), "global_step": 7, "epoch": 1}, path)
    read = read_tensors(path)
    assert read.keys() == _tensors().keys() and all(torch.equal(read[k], v) for k, v in _tensors().items())


@pytest.mark.parametrize("content", [b"PK\x03\x04", b"\x80\x02garbage", [torch.zeros(1)], {1: torch.zeros(1)},
                                     {"state_dict": {"w": 1}}, {"state_dict": [torch.zeros(1)]},
                                     {"model": {"w": torch.zeros(1)}}],
                         ids=["truncated zip", "garbage pickle", "a list", "an int key", "no tensors under state_dict",
                              "a list under state_dict", "another wrapper"])
def test_a_torch_file_that_is_no_readable_state_dict_is_refused_naming_it(tmp_path, content):
    """Found by fuzzing weight files: torch.load's own errors (RuntimeError, UnpicklingError, EOFError, a
    UnicodeDecodeError naming no file ...) escaped read_tensors, and a pickle of something other than names to
    tensors went on to the loaders."""
    path = tmp_path / "model.bin"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save(content, path)
    with pytest.raises(ValueError, match=r"weights '.*model\.bin': not a (readable torch file \(.+\)|state dict)"):
        read_tensors(path)


def test_a_load_failure_is_said_in_the_projects_words_when_weights_only_refuses(tmp_path):
    torch.save({"note": Fraction(1, 3)}, tmp_path / "objects.pt")
    with pytest.raises(Exception) as refused:  # torch's text: the pickle's names, and advice to run its code
        torch.load(tmp_path / "objects.pt", weights_only=True)
    assert "weights_only" in str(refused.value) and "Fraction" in str(refused.value)
    said = load_failure(refused.value)
    assert "could run code" in said and "weights_only" not in said and "Fraction" not in said
    (tmp_path / "short.pt").write_bytes(b"PK\x03\x04")
    with pytest.raises(Exception) as broken:
        torch.load(tmp_path / "short.pt", weights_only=True)
    assert load_failure(broken.value) == f"{type(broken.value).__name__}: {broken.value}"  # any other: as it is


@pytest.mark.parametrize("chunk", [1, 3, 8, 50, 1 << 20])
@pytest.mark.parametrize("cuts", [(), (5,), (37, 38, 100)])
def test_chunked_copies_land_every_byte_in_its_tensor(weights_file, chunk, cuts):
    """The copy through two staging buffers at chunk sizes below, across and above the tensors' sizes, by
    one reader or by several reading spans that cut tensors anywhere, gives each tensor its own bytes (CPU
    targets: the code CUDA reads run, with synchronous copies)."""
    start, entries = safetensors_header(weights_file)
    ordered = sorted(entries.items(), key=lambda item: item[1][2])
    targets = [(torch.full((end - begin,), 7, dtype=torch.uint8), begin) for _, (_, _, begin, end) in ordered]
    end = max(offset + len(target) for target, offset in targets)
    bounds = [0, *cuts, end]
    for span in zip(bounds, bounds[1:]) if cuts else [None]:
        with open(weights_file, "rb", buffering=0) as file:
            stream_into(file, start, targets, chunk_bytes=chunk, span=span)
    expected = load_file(str(weights_file))
    for (name, (dtype, shape, _, _)), (target, _) in zip(ordered, targets):
        assert torch.equal(target.view(dtype).view(shape), expected[name]), name


@pytest.mark.parametrize("length", [0, 1, 4097, 2 * STAGING_BYTES - 1, 5 * STAGING_BYTES + 3, 100 * STAGING_BYTES + 1])
def test_reader_spans_cover_the_data_once_cut_at_pages(length):
    spans = reader_spans(length)
    if not length:
        assert spans == []
        return
    assert [low for low, _ in spans] == [0] + [high for _, high in spans[:-1]] and spans[-1][1] == length
    assert all(low % 4096 == 0 and high > low for low, high in spans)
    assert len(spans) == min(READERS, max(1, length // (2 * STAGING_BYTES)))


def test_several_readers_fill_every_tensor(tmp_path, monkeypatch):
    """What CUDA reads run, into CPU memory: with staging buffers of a page, 72 kB of tensors are shared
    among READERS threads, whose spans cut tensors, and every tensor gets its own bytes."""
    path = tmp_path / "w.safetensors"
    generator = torch.Generator().manual_seed(1)
    save_file({f"t{i}": torch.randn(3001, generator=generator) for i in range(6)}, str(path))
    monkeypatch.setattr(tensor_files, "STAGING_BYTES", 4096)
    start, entries = safetensors_header(path)
    assert len(reader_spans(max(end for *_, end in entries.values()))) == READERS
    read, expected = read_by_readers(path, start, entries, torch.device("cpu")), load_file(str(path))
    assert read.keys() == expected.keys()
    for name, tensor in expected.items():
        assert read[name].dtype == tensor.dtype and torch.equal(read[name], tensor), name


def _write_raw(path, header: bytes, data: bytes = b"") -> None:
    path.write_bytes(struct.pack("<Q", len(header)) + header + data)


@pytest.mark.parametrize("header, data, message", [
    (None, b"", "not a safetensors file"),
    (b"{not json", b"", "header: not valid JSON"),
    (b"[1, 2]", b"", "header: expected a JSON object, got a list"),
    (json.dumps({"x": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}}).encode(), b"\0" * 4, "tensor 'x'"),
    (json.dumps({"x": {"dtype": "F32", "shape": [3], "data_offsets": [0, 8]}}).encode(), b"\0" * 8, "tensor 'x'"),
    (json.dumps({"x": {"dtype": "Q9", "shape": [2], "data_offsets": [0, 8]}}).encode(), b"\0" * 8, "tensor 'x'"),
    (json.dumps({"x": {"dtype": "F32", "shape": [-2], "data_offsets": [0, 8]}}).encode(), b"\0" * 8, "tensor 'x'"),
    # found by fuzzing: headers our check passed and the safetensors library refused with its own error type
    (json.dumps({"x": {"dtype": "F32", "shape": [True], "data_offsets": [0, 4]}}).encode(), b"\0" * 4, "tensor 'x'"),
    (json.dumps({"x": {"dtype": "F32", "shape": {}, "data_offsets": [0, 4]}}).encode(), b"\0" * 4, "tensor 'x'"),
    (json.dumps({"x": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]},
                 "y": {"dtype": "F32", "shape": [1], "data_offsets": [4, 8]}}).encode(), b"\0" * 8,
     r"tensor 'y' starts at byte 4 of the data, not 8"),
    (json.dumps({"x": {"dtype": "F32", "shape": [1], "data_offsets": [4, 8]}}).encode(), b"\0" * 8,
     r"tensor 'x' starts at byte 4 of the data, not 0"),
    (json.dumps({"x": {"dtype": "F32", "shape": [1], "data_offsets": [0, 4]}}).encode(), b"\0" * 8,
     r"the tensors' data ends at byte 4, the file's at 8"),
    (json.dumps({"__metadata__": {"format": 1}}).encode(), b"", "'__metadata__' .* not an object of strings"),
    (b'{"x": ' + b"[" * 100_000, b"", r"header: not valid JSON \(it nests too deeply\)"),
])
def test_malformed_files_are_refused_naming_the_file(tmp_path, header, data, message):
    path = tmp_path / "bad.safetensors"
    if header is None:
        path.write_bytes(struct.pack("<Q", 1 << 40))
    else:
        _write_raw(path, header, data)
    with pytest.raises(ValueError, match=f"weights '.*bad.safetensors'.*{message}"):
        read_tensors(path)


@pytest.mark.parametrize("header", [
    b'{"x": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}, "x": {"dtype": "F32", "shape": [1], '
    b'"data_offsets": [0, 4]}}',  # json.loads kept the second 'x' silently
    b'{"x": {"dtype": "F32", "shape": [2], "shape": [1], "data_offsets": [0, 8]}}',
], ids=["a tensor twice", "a field twice"])
def test_a_key_given_twice_in_the_header_is_refused_naming_the_file_and_the_key(tmp_path, header):
    path = tmp_path / "twice.safetensors"
    _write_raw(path, header, b"\0" * 8)
    key = "x" if header.count(b'"x"') == 2 else "shape"
    with pytest.raises(ValueError, match=f"^weights '.*twice.safetensors': safetensors header: key '{key}' is given twice"):
        read_tensors(path)


def test_read_ahead_asks_the_kernel_for_each_whole_file_and_skips_what_it_cannot_open(tmp_path, monkeypatch):
    import os

    from artnvg_core.tensor_files import read_ahead

    asked = []
    monkeypatch.setattr(os, "posix_fadvise", lambda fd, offset, length, advice: asked.append((offset, length, advice)),
                        raising=False)
    monkeypatch.setattr(os, "POSIX_FADV_WILLNEED", 3, raising=False)
    (tmp_path / "a.bin").write_bytes(b"x" * 10)
    (tmp_path / "b.bin").write_bytes(b"y" * 3)
    read_ahead([tmp_path / "a.bin", tmp_path / "missing.bin", tmp_path / "b.bin"])
    assert asked == [(0, 10, 3), (0, 3, 3)]


@pytest.fixture
def counted_reads(monkeypatch):
    """Every read_safetensors call's path, in order (the real read still runs); early reads forgotten after."""
    calls, read = [], tensor_files.read_safetensors

    def counting(path, device):
        calls.append(path.name)
        return read(path, device)

    monkeypatch.setattr(tensor_files, "read_safetensors", counting)
    yield calls
    tensor_files.drop_early_reads()


def test_an_early_read_is_taken_once_by_the_read_of_its_file(weights_file, counted_reads):
    import threading

    weights_file.with_name("csgo.bin").write_bytes(b"")  # not .safetensors: left to its loader
    reader = tensor_files.read_early([weights_file, weights_file.with_name("csgo.bin")], "cpu")
    taken = {}
    waiting = threading.Thread(target=lambda: taken.update(read_tensors(weights_file)))
    waiting.start()  # asks before the file is read: waits for the early read
    reader()
    waiting.join()
    assert counted_reads == ["w.safetensors"]
    expected = load_file(str(weights_file))
    assert taken.keys() == expected.keys() and all(torch.equal(taken[k], expected[k]) for k in expected)
    read_tensors(weights_file)  # taken already: read again
    assert counted_reads == ["w.safetensors", "w.safetensors"]


def test_an_early_read_of_a_changed_or_dropped_file_is_not_taken(weights_file, counted_reads):
    import os

    tensor_files.read_early([weights_file], "cpu")()
    stat = os.stat(weights_file)
    os.utime(weights_file, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # the file changed since
    read_tensors(weights_file)
    assert counted_reads == ["w.safetensors", "w.safetensors"]
    reader = tensor_files.read_early([weights_file], "cpu")
    tensor_files.drop_early_reads()
    reader()  # forgotten before it ran: reads nothing
    read_tensors(weights_file)
    assert counted_reads == ["w.safetensors"] * 3


def test_a_failed_early_read_is_read_again_by_the_loader(weights_file, monkeypatch):
    failing = [True]
    read = tensor_files.read_safetensors

    def flaky(path, device):
        if failing.pop() if failing else False:
            raise OSError("disk hiccup")
        return read(path, device)

    monkeypatch.setattr(tensor_files, "read_safetensors", flaky)
    tensor_files.read_early([weights_file], "cpu")()
    assert torch.equal(read_tensors(weights_file)["weight"], _tensors()["weight"])
