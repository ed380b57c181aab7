"""The extension dispatch of load_scene / save_scene, and the writers' shared refusals."""

import dataclasses
import os
import re
import struct
import sys

import pytest
import torch

from artnvg_core.formats import READERS, SAVE_SUFFIXES, load_scene, save_scene
from tests.test_formats_ply import assert_same_bits, random_scene
from tests.test_formats_splatfacto import save_splatfacto, splatfacto_params


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


NOTES = {  # of a degree-3 scene trained antialiased (0.3 px^2) with one far floater among 2,000 Gaussians
    ".ply": ["cannot record the scene's 2D filter (0.3 px^2 blur, antialiased); it reads back with 0.1 px^2 blur, "
             "antialiased"],
    ".spz": ["1 Gaussian beyond SPZ's range at 12 fractional bits (|coordinate| up to 2048) moved onto it along their "
             "rays from the origin, their sizes scaled alike (the same direction and apparent size from there); the "
             "farthest from |coordinate| 1e+07"],
    ".splat": ["holds SH up to degree 0; the degree 1-3 view-dependent terms are dropped",
               "cannot record the scene's 2D filter (0.3 px^2 blur, antialiased); it reads back with 0.3 px^2 blur, "
               "classic"],
    ".ksplat": ["holds SH up to degree 2; the degree 3 view-dependent terms are dropped",
                "cannot record the scene's 2D filter (0.3 px^2 blur, antialiased); it reads back with 0.3 px^2 blur, "
                "classic"],
}


@pytest.mark.parametrize("suffix", SAVE_SUFFIXES)
def test_what_a_format_changes_of_the_scene_is_told_once_to_notes_or_else_logged(tmp_path, suffix, caplog):
    """A caller that shows the user the notes (a node's text, a command's output) gets each once and nothing is
    logged; without ``notes``, each is logged once as a warning naming the file. A classic scene of degree 0
    within every range has none."""
    scene = dataclasses.replace(random_scene(2001, 3).select(slice(3, None)), antialiased=True)
    scene.means[-1] = torch.tensor([1e7, 5.0, -3.0])
    expected = [note if note[0].isdigit() else f"{suffix} {note}" for note in NOTES[suffix]]
    notes = []
    with caplog.at_level("INFO"):
        save_scene(scene, tmp_path / f"told{suffix}", notes=notes.append)
        assert notes == expected and caplog.records == []
        save_scene(scene, tmp_path / f"logged{suffix}")
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [
        ("WARNING", f"{tmp_path / f'logged{suffix}'}: {note}") for note in expected]
    save_scene(random_scene(8, 0).select(slice(3, None)), tmp_path / f"plain{suffix}", notes=notes.append)
    assert notes == expected


def _with_a_nan_at_gaussian_1(path, suffix):
    """A file of ``suffix`` holding 5 Gaussians, the second's x NaN (a byte patch where the writer refuses it)."""
    scene = random_scene(8, 1).select(slice(3, None))
    if suffix == ".ckpt":
        params = splatfacto_params(5, 1)
        params["means"][1, 0] = float("nan")
        return save_splatfacto(path, params)
    save_scene(scene, path, notes=lambda note: None)
    data = bytearray(path.read_bytes())
    first = {".splat": 0, ".ksplat": 4096 + 1024}.get(suffix)
    if first is None:  # .ply: after the header, x first in each row
        first = data.index(b"end_header\n") + len(b"end_header\n")
    row = (len(data) - first) // 5
    data[first + row : first + row + 4] = struct.pack("<f", float("nan"))
    path.write_bytes(bytes(data))
    return path


LOAD_NOTES = {  # what a load tells of the files above; a .spz (no NaN in its fixed point) of the axes it takes
    suffix: "dropped 1 invalid Gaussian of 5 (means: 1 with non-finite values)" for suffix in (".ply", ".splat",
                                                                                               ".ksplat", ".ckpt")}
LOAD_NOTES[".spz"] = ("the file names no axes: read in the PLY's axes (x right, y down, z forward), as "
                      "splat-transform, spz-js and Niantic's ply-to-spz write; if it is upside down, read it with "
                      "spz axes 'rub' (--spz-axes rub, the Load Gaussian Scene node's spz_axes)")


@pytest.mark.parametrize("suffix", READERS)
def test_what_a_read_did_to_the_scene_is_told_once_to_notes_or_else_logged(tmp_path, suffix, caplog):
    path = tmp_path / f"scene{suffix}"
    if suffix == ".spz":
        save_scene(random_scene(8, 1).select(slice(3, None)), path)
    else:
        _with_a_nan_at_gaussian_1(path, suffix)
    notes = []
    with caplog.at_level("INFO"):
        assert len(load_scene(path, drop_invalid=True, notes=notes.append)) == (5 if suffix == ".spz" else 4)
        assert notes == [LOAD_NOTES[suffix]] and caplog.records == []
        load_scene(path, drop_invalid=True)
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [("WARNING", f"{path}: {LOAD_NOTES[suffix]}")]


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


@pytest.mark.parametrize("suffix", SAVE_SUFFIXES)
def test_writers_refuse_a_missing_folder_before_their_work(tmp_path, suffix):
    """A FileNotFoundError came once the scene was encoded, from the temporary file's opening."""
    path = tmp_path / "missing" / f"scene{suffix}"
    with pytest.raises(ValueError, match=rf"scene\{suffix}: not written: its folder .*missing does not exist$"):
        save_scene(random_scene(4, 1), path)
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


# --------------------------------------------------------------------------- chunks: progress and cancellation

CHUNKED = [(".ply", {}), (".ply", {"binary": False}), (".spz", {"version": 3}), (".spz", {"version": 2}),
           (".splat", {}), (".ksplat", {})]


def write_chunked(scene, path, options: dict, **kwargs) -> None:
    """``scene`` written to ``path`` by its format's writer (which takes the options: an ASCII PLY, an SPZ version)."""
    from artnvg_core.formats import WRITERS

    WRITERS[path.suffix](scene, path, **options, **kwargs)


@pytest.mark.parametrize("degree", [0, 3])
@pytest.mark.parametrize("suffix, options", CHUNKED)
def test_chunked_reads_and_writes_give_the_whole_arrays_results(tmp_path, monkeypatch, suffix, options, degree):
    from artnvg_core.formats import common

    scene = random_scene(103, degree).select(slice(3, None))  # rows 0-2 exceed the SPZ's ranges
    whole, chunked = tmp_path / f"whole{suffix}", tmp_path / f"chunked{suffix}"
    write_chunked(scene, whole, options)
    read_whole = load_scene(whole)
    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 7)  # 100 Gaussians: 14 chunks, the last of 2
    write_chunked(scene, chunked, options)
    assert chunked.read_bytes() == whole.read_bytes()
    assert_same_bits(load_scene(chunked), read_whole)


def assert_one_bar(calls: list, whole: int, stages: dict[str, float]) -> None:
    """``calls`` (step, total, info) fill one bar of ``whole`` steps once, from 0, never going back, each stage of
    ``stages`` (a reader's READ_STAGES) its share by weight: the bar passes each stage's end (within a step's
    rounding) and moves within the last."""
    steps = [step for step, _, _ in calls]
    assert {total for _, total, _ in calls} == {whole} and [info for _, _, info in calls if info] == []
    assert steps[0] == 0 and steps[-1] == whole and steps == sorted(steps), steps
    weights = list(stages.values())
    ends = [whole * sum(weights[:i]) / sum(weights) for i in range(1, len(weights))]
    assert all(min(abs(step - end) for step in steps) <= 1 for end in ends), (ends, steps)
    assert [step for step in steps if ends[-1] + 1 < step < whole], steps


@pytest.mark.parametrize("suffix, options", CHUNKED)
def test_a_write_counts_the_gaussians_and_a_read_fills_one_bar_over_its_stages(tmp_path, monkeypatch, suffix,
                                                                                 options):
    """A write counts the scene's Gaussians (an SPZ's 6 arrays each a sixth of them: 100 Gaussians, not 600); a
    read fills one bar over the file's bytes, its
    stages (reading or inflating, decoding, checking) each a share by its measured time."""
    from artnvg_core import scene
    from artnvg_core.formats import READERS, common

    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 16)
    monkeypatch.setattr(scene, "CHECKED_ROWS", 16)
    path, calls = tmp_path / f"scene{suffix}", []
    write_chunked(random_scene(103, 1).select(slice(3, None)), path, options, progress=lambda *call: calls.append(call))
    assert {total for _, total, _ in calls} == {100} and calls[0][0] == 0 and calls[-1][0] == 100
    assert all(b[0] >= a[0] for a, b in zip(calls, calls[1:]))
    calls.clear()
    load_scene(path, progress=lambda *call: calls.append(call))
    stages = sys.modules[READERS[suffix].__module__].READ_STAGES
    assert_one_bar(calls, path.stat().st_size, stages["ascii" if "binary" in options else "binary"]
                   if suffix == ".ply" else stages)


def stop_at(call: int):
    """A ``should_stop`` that says stop on its ``call``-th call (1-based), and counts its calls."""
    def should_stop() -> bool:
        should_stop.calls += 1
        return should_stop.calls >= call
    should_stop.calls = 0
    return should_stop


@pytest.mark.parametrize("suffix, options", CHUNKED)
@pytest.mark.parametrize("call", [1, 2, 6])
def test_a_stop_ends_a_write_between_chunks_leaving_no_file(tmp_path, monkeypatch, suffix, options, call):
    from artnvg_core.formats import common
    from artnvg_core.progress import Cancelled

    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 16)
    scene, path = random_scene(103, 1).select(slice(3, None)), tmp_path / f"scene{suffix}"
    written, full = [], []
    write_chunked(scene, tmp_path / f"full{suffix}", options, progress=lambda step, total, info: full.append(step))
    (tmp_path / f"full{suffix}").unlink()
    should_stop = stop_at(call)
    with pytest.raises(Cancelled):
        write_chunked(scene, path, options, should_stop=should_stop,
                      progress=lambda step, total, info: written.append(step))
    assert should_stop.calls == call  # asked before the work, then before each chunk: no chunk after the stop
    assert written == full[: len(written)] and len(written) < len(full) and (call < 6 or len(written) > 2)
    assert os.listdir(tmp_path) == []  # no file, no temporary
    path.write_bytes(b"kept")  # a stop never touches the file it would have replaced
    with pytest.raises(Cancelled):
        write_chunked(scene, path, options, should_stop=stop_at(call))
    assert os.listdir(tmp_path) == [path.name] and path.read_bytes() == b"kept"


@pytest.mark.parametrize("suffix, options", CHUNKED)
@pytest.mark.parametrize("call", [1, 3, 9])
def test_a_stop_ends_a_read_between_chunks(tmp_path, monkeypatch, suffix, options, call):
    from artnvg_core.formats import common
    from artnvg_core.progress import Cancelled

    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 16)
    path = tmp_path / f"scene{suffix}"
    write_chunked(random_scene(103, 1).select(slice(3, None)), path, options)
    should_stop = stop_at(call)
    with pytest.raises(Cancelled):
        load_scene(path, should_stop=should_stop)
    assert should_stop.calls == call
