"""antimatter15 .splat: record layout, round trip within the stated quantisation, corrupt files."""

import numpy as np
import pytest
import torch

from artnvg_core.formats.splat import RECORD, read_splat, write_splat
from artnvg_core.scene import SH_C0
from tests.test_formats_ply import random_scene


def plain_scene(n: int, degree: int, seed: int = 0):
    """A random scene inside every format's range (random_scene's first rows hold extreme values)."""
    return random_scene(n + 3, degree, seed).select(slice(3, None))


def quat_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest component difference of the unit quaternions, q and -q being one rotation."""
    a, b = (torch.nn.functional.normalize(q.double(), dim=1) for q in (a, b))
    return float(torch.minimum((a - b).abs().amax(1), (a + b).abs().amax(1)).max())


def assert_only_value_errors(read, path, data: bytes, case: str) -> None:
    """Read ``data`` from ``path``: any result or a ValueError naming the file, nothing else."""
    path.write_bytes(data)
    try:
        read(path)
    except ValueError as error:
        assert path.name in str(error), f"{case}: {error}"
    except Exception as error:  # noqa: BLE001 - any other type is the bug under test
        pytest.fail(f"{case}: {type(error).__name__} escaped: {error}")


def test_round_trip_stays_within_the_stated_quantisation(tmp_path, caplog):
    scene = plain_scene(2000, 2)
    path = tmp_path / "scene.splat"
    write_splat(scene, path)
    assert path.stat().st_size == 32 * 2000
    back = read_splat(path)
    assert back.sh_degree == 0 and "the degree 1-2 view-dependent terms are dropped" in caplog.text
    assert torch.equal(back.means, scene.means)
    assert (back.log_scales - scene.log_scales).abs().max() <= 1e-6
    colour = (SH_C0 * scene.sh[:, 0].double() + 0.5).clamp(0, 1)
    assert ((SH_C0 * back.sh[:, 0].double() + 0.5) - colour).abs().max() <= 0.5 / 255 + 1e-7
    opacity = torch.sigmoid(scene.opacity_logits.double())
    assert (torch.sigmoid(back.opacity_logits.double()) - opacity).abs().max() <= 0.5 / 255 + 1e-7
    assert quat_error(back.quats, scene.quats) <= 1.5 / 128


def test_record_layout_by_hand(tmp_path):
    record = np.zeros(1, RECORD)
    record["position"] = [1.5, -2, 3]
    record["scale"] = [0.5, 1, 2]
    record["rgba"] = [255, 0, 128, 64]
    record["rotation"] = [128, 255, 128, 128]  # w 0, x 127/128: a half turn about x
    path = tmp_path / "one.splat"
    path.write_bytes(record.tobytes())
    scene = read_splat(path)
    assert scene.means.tolist() == [[1.5, -2, 3]]
    torch.testing.assert_close(scene.log_scales, torch.log(torch.tensor([[0.5, 1, 2]])))
    torch.testing.assert_close(SH_C0 * scene.sh[0, 0] + 0.5, torch.tensor([1, 0, 128 / 255]))
    torch.testing.assert_close(torch.sigmoid(scene.opacity_logits), torch.tensor([64 / 255]))
    assert quat_error(scene.quats, torch.tensor([[0.0, 1, 0, 0]])) == 0


def test_end_bytes_give_finite_logits_that_write_back_to_the_same_bytes(tmp_path):
    records = np.zeros(2, RECORD)
    records["scale"] = 1
    records["rotation"] = [255, 128, 128, 128]
    records["rgba"][:, 3] = [0, 255]
    path = tmp_path / "ends.splat"
    path.write_bytes(records.tobytes())
    scene = read_splat(path)
    assert torch.isfinite(scene.opacity_logits).all()
    write_splat(scene, tmp_path / "again.splat")
    assert np.fromfile(tmp_path / "again.splat", RECORD)["rgba"][:, 3].tolist() == [0, 255]


def test_bad_records_name_the_field(tmp_path):
    records = np.zeros(3, RECORD)
    records["scale"] = 1
    records["rotation"] = [255, 128, 128, 128]
    records["scale"][1, 2] = -1
    records["rotation"][2] = 128  # zero quaternion
    path = tmp_path / "bad.splat"
    path.write_bytes(records.tobytes())
    with pytest.raises(ValueError, match=r"bad\.splat: scale: 1 of 3 Gaussians has a scale that is not a positive"):
        read_splat(path)
    assert len(read_splat(path, drop_invalid=True)) == 1
    records["scale"][1, 2] = 1
    path.write_bytes(records.tobytes())
    with pytest.raises(ValueError, match=r"bad\.splat: quats: 1 of 3 Gaussians has a zero norm \(first at index 2\)"):
        read_splat(path)  # named as what it is (was: as non-finite values)
    for size in (0, 31, 33, 95):
        path.write_bytes(records.tobytes()[:size] if size < 96 else b"")
        with pytest.raises(ValueError, match=rf"bad\.splat: file size {size} bytes is not a positive multiple"):
            read_splat(path)


def test_scales_beyond_float32_are_refused_before_writing(tmp_path):
    scene = plain_scene(4, 0)
    scene.log_scales[2, 1] = 89.0
    with pytest.raises(ValueError, match=r"big\.splat: not written: log_scales: 1 of 4 .*\(first at index 2\)"):
        write_splat(scene, tmp_path / "big.splat")
    assert list(tmp_path.iterdir()) == []


def test_fuzzed_and_truncated_files_raise_only_value_error(tmp_path):
    write_splat(plain_scene(8, 0), tmp_path / "source.splat")
    original = (tmp_path / "source.splat").read_bytes()
    rng = np.random.default_rng(1)
    for case in range(100):
        data = bytearray(original)
        for position in rng.integers(0, len(data), 4):
            data[position] = int(rng.integers(0, 256))
        assert_only_value_errors(read_splat, tmp_path / "fuzzed.splat", bytes(data), f"case {case}")
    for length in range(0, len(original), 7):
        assert_only_value_errors(read_splat, tmp_path / "cut.splat", original[:length], f"{length} bytes")
