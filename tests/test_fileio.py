"""Output-path checks, files written whole, and together or not at all."""

import os
from pathlib import Path

import pytest

from artnvg_core.fileio import (
    check_output_file,
    check_output_folder,
    refuse_overwrites,
    require_regular_file,
    write_atomically,
    written_together,
)


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


@pytest.mark.parametrize("hard_links", [True, False], ids=["hard links", "no hard links (FAT)"])
def test_a_new_file_never_goes_over_one_that_took_its_name_while_it_was_written(tmp_path, monkeypatch, hard_links):
    """overwrite=False: a rival that writes the name while this file is written keeps its file, this one is
    refused (FileExistsError naming the name) and leaves nothing behind; the name shows the whole file or none."""
    if not hard_links:
        def no_link(source, target, **_):
            raise PermissionError(1, "Operation not permitted", source, None, target)
        monkeypatch.setattr(os, "link", no_link)
    target = tmp_path / "scene.ply"

    def write_while_rival_writes(stream):
        assert not target.exists()  # no placeholder, empty or partial, at the name while this file is written
        stream.write(b"ours")
        target.write_bytes(b"rival")

    with pytest.raises(FileExistsError, match=r"scene\.ply") as refused:
        write_atomically(target, write_while_rival_writes, overwrite=False)
    assert refused.value.filename == str(target)
    assert target.read_bytes() == b"rival" and list(tmp_path.iterdir()) == [target]
    (tmp_path / "link.ply").symlink_to(tmp_path / "nowhere.ply")  # a dangling link holds its name too
    with pytest.raises(FileExistsError):
        write_atomically(tmp_path / "link.ply", lambda stream: stream.write(b"ours"), overwrite=False)
    assert not (tmp_path / "nowhere.ply").exists()
    write_atomically(tmp_path / "free.ply", lambda stream: stream.write(b"ours"), overwrite=False)
    assert (tmp_path / "free.ply").read_bytes() == b"ours"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["free.ply", "link.ply", "scene.ply"]


def test_an_input_file_that_cannot_be_opened_is_named_with_what_it_is(tmp_path, monkeypatch):
    locked = tmp_path / "locked.ply"
    locked.write_bytes(b"ply\n")
    opened = Path.open

    def refuse_locked(self, *args, **kwargs):  # chmod 000 stops no root, which runs these tests in CI
        if self == locked:
            raise PermissionError(13, "Permission denied", str(self))
        return opened(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", refuse_locked)
    with pytest.raises(ValueError, match=r"locked\.ply: scene file cannot be read \(Permission denied\)$"):
        require_regular_file(locked, "scene file")
