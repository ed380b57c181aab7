"""Bounded decompression: exactly the size a header implies, one byte past it at most."""

import gzip
import io
import struct
import zipfile
from pathlib import Path

import pytest

from artnvg_core.formats import bounded
from artnvg_core.formats.bounded import inflate_exactly, read_at_most


class CountingReader(io.RawIOBase):
    """A stream of ``size`` zero bytes that counts the bytes handed out."""

    def __init__(self, size: int):
        self.left, self.given = size, 0

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        n = min(len(buffer), self.left)
        buffer[:n] = bytes(n)
        self.left, self.given = self.left - n, self.given + n
        return n


def test_exactly_the_implied_size_and_one_byte_past_it_at_most(monkeypatch):
    monkeypatch.setattr(bounded, "CHUNK", 1000)  # several reads per call
    where = Path("scene.spz")
    assert len(inflate_exactly(CountingReader(2500), 2500, where, "data")) == 2500
    endless = CountingReader(10**12)
    with pytest.raises(ValueError, match=r"scene\.spz: data: the stream holds more than the 2,500 bytes expected"):
        inflate_exactly(endless, 2500, where, "data")
    assert endless.given == 2501
    with pytest.raises(ValueError, match=r"scene\.spz: data: 2,500 bytes expected, the stream ends after 2,499"):
        inflate_exactly(CountingReader(2499), 2500, where, "data")
    trailing = CountingReader(10**12)
    assert len(inflate_exactly(trailing, 2500, where, "data", trailing_allowed=True)) == 2500
    assert trailing.given == 2500


def test_read_at_most_stops_at_the_limit_or_the_end():
    stream = gzip.GzipFile(fileobj=io.BytesIO(gzip.compress(b"abcdef" * 1000)))
    assert read_at_most(stream, 4) == b"abcd"
    assert read_at_most(stream, 10**9) == (b"abcdef" * 1000)[4:]


def test_a_zip_that_zipfile_cannot_read_is_refused_naming_the_file(tmp_path):
    """Found by fuzzing splatfacto checkpoints: zipfile's own errors (BadZipFile, NotImplementedError, a
    UnicodeDecodeError naming no file) escaped from the check of the records."""
    path = tmp_path / "archive.ckpt"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("\u00e9/data.pkl", b"data")
    good = path.read_bytes()
    central = good.index(b"PK\x01\x02")  # the central directory's record: version needed to extract at +6
    end = good.rindex(b"PK\x05\x06")  # the end record, after which a zip64 locator naming 2 disks
    bounded.require_stored_zip(path)
    for corrupt in (good[:central] + b"PK\x01\x03" + good[central + 4:],
                    good[:end] + struct.pack("<4sIQI", b"PK\x06\x07", 0, 0, 2) + good[end:],
                    good.replace("\u00e9".encode(), b"\xff\xfe"),
                    good[:central + 6] + b"\xff" + good[central + 7:]):
        path.write_bytes(corrupt)
        with pytest.raises(ValueError, match=r"archive\.ckpt: not a readable zip archive \(.+\); the file is "
                                             "truncated or corrupt"):
            bounded.require_stored_zip(path)


def test_a_zip_archive_is_told_by_its_first_bytes_as_torch_load_tells_it(tmp_path, monkeypatch):
    """Not by ``zipfile.is_zipfile``: Python 3.12's says False for an archive whose central directory's magic is
    damaged (3.11's True), which then passed unchecked there. A file not beginning with a local file header passes
    (torch.load reads it in its legacy format); one that does is checked, is_zipfile's answer aside."""
    monkeypatch.setattr(zipfile, "is_zipfile", lambda path: False)
    path = tmp_path / "archive.ckpt"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", b"data")
    good = path.read_bytes()
    path.write_bytes(good[:-30])  # the end record cut short
    with pytest.raises(ValueError, match=r"archive\.ckpt: not a readable zip archive"):
        bounded.require_stored_zip(path)
    path.write_bytes(b"\x80\x02" + good[2:])  # a pickle's first bytes: not an archive to torch.load
    bounded.require_stored_zip(path)
