"""nerfstudio splatfacto checkpoints: tensors, SH degree 0 colours, errors, the run's rasterize_mode."""

import pickle
import zipfile
from fractions import Fraction
from pathlib import Path

import pytest
import torch

from artnvg_core.formats import load_scene
from artnvg_core.formats.splatfacto import read_splatfacto_ckpt
from artnvg_core.scene import SH_C0, GaussianScene
from artnvg_core.tensor_files import load_failure
from tests.test_formats_ply import assert_same_bits


# --------------------------------------------------------------------------- splatfacto checkpoints

PREFIX = "_model.gauss_params."


def splatfacto_params(n: int, degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 4,
        "quats": torch.randn(n, 4, generator=g),
        "features_dc": torch.randn(n, 3, generator=g) * 4,
        "features_rest": torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g),
        "opacities": torch.randn(n, 1, generator=g),
    }


def scene_from_splatfacto(params: dict[str, torch.Tensor]) -> GaussianScene:
    """The expected scene of SH degree >= 1 splatfacto parameters, as float32."""
    return GaussianScene(
        means=params["means"].float(),
        quats=params["quats"].float(),
        log_scales=params["scales"].float(),
        opacity_logits=params["opacities"][:, 0].float(),
        sh=torch.cat([params["features_dc"][:, None], params["features_rest"]], dim=1).float(),
    )


def save_splatfacto(path: Path, params: dict[str, torch.Tensor], **extra) -> Path:
    pipeline = {PREFIX + name: value for name, value in params.items()}
    pipeline["_model.field.mlp.weight"] = torch.zeros(2, 2)  # unrelated model state
    torch.save({"step": 29999, "pipeline": pipeline, "optimizers": {}, "schedulers": {}, **extra}, path)
    return path


def test_splatfacto_degree_3_maps_every_tensor(tmp_path):
    params = splatfacto_params(11, 3)
    path = save_splatfacto(tmp_path / "step-000029999.ckpt", params)
    for scene in (read_splatfacto_ckpt(path), load_scene(path)):
        assert scene.sh_degree == 3
        assert_same_bits(scene, scene_from_splatfacto(params))


@pytest.mark.parametrize("rest", ["empty", "absent"])
def test_splatfacto_degree_0_converts_colour_logits_to_sh_dc(tmp_path, rest):
    params = splatfacto_params(9, 0)
    params["features_dc"][0] = torch.tensor([-30.0, 0.0, 30.0])
    if rest == "absent":
        del params["features_rest"]
    scene = read_splatfacto_ckpt(save_splatfacto(tmp_path / "deg0.ckpt", params))
    assert scene.sh_degree == 0 and scene.sh.dtype == torch.float32
    rendered_dc = SH_C0 * scene.sh[:, 0].double() + 0.5
    torch.testing.assert_close(rendered_dc, torch.sigmoid(params["features_dc"].double()), rtol=0, atol=1e-6)


def test_splatfacto_sparse_tensors_read_as_their_dense_values(tmp_path):
    params = splatfacto_params(7, 1)
    params["features_rest"][2:5] = 0  # mostly zero, as a sparse tensor would be saved for
    sparse = {name: value.to_sparse() for name, value in params.items()}
    scene = read_splatfacto_ckpt(save_splatfacto(tmp_path / "sparse.ckpt", sparse))
    assert_same_bits(scene, scene_from_splatfacto(params))


def test_splatfacto_half_precision_is_read_as_float32(tmp_path):
    params = {k: v.half() for k, v in splatfacto_params(5, 1).items()}
    scene = read_splatfacto_ckpt(save_splatfacto(tmp_path / "half.ckpt", params))
    assert_same_bits(scene, scene_from_splatfacto(params))


def test_splatfacto_missing_keys_are_listed(tmp_path):
    params = splatfacto_params(4, 1)
    del params["quats"], params["opacities"]
    path = save_splatfacto(tmp_path / "partial.ckpt", params)
    with pytest.raises(ValueError, match=rf"partial\.ckpt: .*lacks tensors {PREFIX}quats, {PREFIX}opacities$"):
        read_splatfacto_ckpt(path)


@pytest.mark.parametrize(
    ("name", "shape", "message"),
    [
        ("features_rest", (4, 5, 3), r"features_rest: expected shape \(4, K-1, 3\)"),
        ("scales", (4, 4), r"scales: expected shape \(4, 3\), got \(4, 4\)"),
        ("opacities", (4,), r"opacities: expected shape \(4, 1\), got \(4,\)"),
    ],
)
def test_splatfacto_wrong_shapes_are_named(tmp_path, name, shape, message):
    params = splatfacto_params(4, 1)
    params[name] = torch.zeros(shape)
    with pytest.raises(ValueError, match=rf"bad_shape\.ckpt: {PREFIX}{message}"):
        read_splatfacto_ckpt(save_splatfacto(tmp_path / "bad_shape.ckpt", params))


def test_splatfacto_invalid_values_are_rejected_or_dropped(tmp_path):
    params = splatfacto_params(6, 2)
    params["means"][3, 2] = float("nan")
    path = save_splatfacto(tmp_path / "nan.ckpt", params)
    message = r"nan\.ckpt: means: 1 of 6 Gaussians has non-finite values \(first at index 3\)"
    with pytest.raises(ValueError, match=message):
        read_splatfacto_ckpt(path)
    scene = load_scene(path, drop_invalid=True)
    assert len(scene) == 5
    assert torch.equal(scene.means, params["means"][[0, 1, 2, 4, 5]])


def test_files_that_are_not_splatfacto_checkpoints(tmp_path):
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ValueError, match=r"garbage\.ckpt: not a loadable torch checkpoint"):
        read_splatfacto_ckpt(garbage)

    unsafe = save_splatfacto(tmp_path / "unsafe.ckpt", splatfacto_params(3, 0), note=Fraction(1, 3))
    with pytest.raises(ValueError) as refused:
        read_splatfacto_ckpt(unsafe)  # weights_only refuses arbitrary pickled objects
    # said in the project's words: not torch's advice to load it with weights_only=False (which runs the
    # file's code), nor the names the file's pickle gives
    assert str(refused.value) == f"{unsafe}: not a loadable torch checkpoint ({load_failure(pickle.UnpicklingError())})"
    assert "weights_only" not in str(refused.value) and "Fraction" not in str(refused.value)

    tensor_only = tmp_path / "tensor.ckpt"
    torch.save(torch.zeros(3), tensor_only)
    with pytest.raises(ValueError, match=r"tensor\.ckpt: expected a nerfstudio checkpoint"):
        read_splatfacto_ckpt(tensor_only)

    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(save_splatfacto(tmp_path / "full.ckpt", splatfacto_params(3, 1)).read_bytes()[:300])
    with pytest.raises(ValueError, match=r"truncated\.ckpt: not a readable zip archive \(.+\); the file is truncated "
                                         "or corrupt"):  # torch.save's archive, its end cut off
        read_splatfacto_ckpt(truncated)


def test_compressed_zip_records_are_refused_before_inflating(tmp_path):
    """torch.save stores records uncompressed; one deflated record (here 64 MiB of zeros in 64 kB,
    a tensor torch.load would inflate) is refused by the zip directory alone, naming the record.
    Legacy (non-zip) checkpoints hold no compressed stream and still load."""
    path = save_splatfacto(tmp_path / "plain.ckpt", splatfacto_params(5, 1))
    bomb = tmp_path / "bomb.ckpt"
    with zipfile.ZipFile(path) as plain, zipfile.ZipFile(bomb, "w") as out:
        for record in plain.infolist():
            out.writestr(record, plain.read(record))
        out.writestr(f"{record.filename.split('/')[0]}/data/99", bytes(1 << 26), compress_type=zipfile.ZIP_DEFLATED)
    assert bomb.stat().st_size < 2**17
    with pytest.raises(ValueError, match=r"bomb\.ckpt: record '[^']*/data/99' is compressed \(67,108,864 bytes from"):
        read_splatfacto_ckpt(bomb)
    legacy = tmp_path / "legacy.ckpt"
    torch.save({"pipeline": {PREFIX + k: v for k, v in splatfacto_params(5, 1).items()}}, legacy,
               _use_new_zipfile_serialization=False)
    assert len(read_splatfacto_ckpt(legacy)) == 5


@pytest.mark.parametrize(("config", "antialiased"), [
    ("pipeline:\n  model: !!python/object:SplatfactoModelConfig\n    rasterize_mode: antialiased\n", True),
    ("pipeline:\n  model:\n    rasterize_mode: classic\n", False),
    (None, False),
])
def test_rasterize_mode_comes_from_the_runs_config(tmp_path, config, antialiased):
    models = tmp_path / "run" / "nerfstudio_models"
    models.mkdir(parents=True)
    if config is not None:
        (tmp_path / "run" / "config.yml").write_text(config)
    scene = read_splatfacto_ckpt(save_splatfacto(models / "step-000029999.ckpt", splatfacto_params(4, 1)))
    assert scene.antialiased is antialiased and scene.blur_px2 == 0.3


@pytest.mark.parametrize("layout", ["stride 0", "sparse_coo"])
def test_tensors_standing_for_more_than_the_file_holds_are_refused_before_made_dense(tmp_path, layout):
    """A 3 kB checkpoint whose means, scales, ... are stride-0 (or sparse, all zero) tensors of 2^20
    Gaussians would be 58 MB dense: refused naming the cap (4x the file, 16 MiB at least) and the
    layouts; 2^16 such Gaussians (3.7 MB, under the floor) load."""
    widths = {"means": 3, "scales": 3, "quats": 4, "features_dc": 3, "opacities": 1}

    def save(n: int) -> Path:
        def tensor(width: int) -> torch.Tensor:
            if layout == "stride 0":
                return torch.tensor([[0.5] * width]).expand(n, width)
            return torch.sparse_coo_tensor(torch.zeros(2, 0, dtype=torch.long), torch.zeros(0), (n, width), check_invariants=True)

        params = {name: tensor(width) for name, width in widths.items()}
        params["quats"] = torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4)
        return save_splatfacto(tmp_path / f"{n}.ckpt", params)

    path = save(2**20)
    assert path.stat().st_size < 4000
    needed = 4 * 2**20 * 14
    with pytest.raises(ValueError, match=rf"{2**20}\.ckpt: _model\.gauss_params\.\*: the Gaussian tensors take "
                       rf"{needed:,} bytes as dense float32, more than the cap of 4x .*\(16,777,216 bytes\).*"
                       rf"means \({2**20}, 3\) \({layout}\)"):
        read_splatfacto_ckpt(path)
    assert len(read_splatfacto_ckpt(save(2**16))) == 2**16


def test_a_checkpoints_gaussians_are_copied_out_of_it_with_one_bar_and_a_stop_between_chunks(tmp_path, monkeypatch):
    """Mapped (torch.load's mmap), then copied a chunk of 16 Gaussians at a time: the bar fills once over the copy and
    the check; a stop during the copy ends it there; the scene holds no page of the file (rewritten in place after
    the load, as by a trainer saving its next checkpoint over it, the scene keeps its values)."""
    from artnvg_core import scene
    from artnvg_core.formats import common, splatfacto
    from artnvg_core.progress import Cancelled
    from tests.test_formats import assert_one_bar

    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 16)
    monkeypatch.setattr(scene, "CHECKED_ROWS", 16)
    params = splatfacto_params(100, 1)
    path, calls = save_splatfacto(tmp_path / "run.ckpt", params), []
    loaded = load_scene(path, progress=lambda *call: calls.append(call))
    assert_one_bar(calls, path.stat().st_size, splatfacto.READ_STAGES)
    read_end = path.stat().st_size * 0.12 / 0.30
    assert len([step for step, _, _ in calls if 0 < step < read_end]) > 20  # 6 tensors of 7 chunks
    calls.clear()
    with pytest.raises(Cancelled):
        load_scene(path, progress=lambda *call: calls.append(call), should_stop=lambda: len(calls) == 10)
    assert len(calls) == 10 and calls[-1][0] < read_end  # stopped within the copy
    data = bytearray(path.read_bytes())
    for value in params.values():  # every stored float of the Gaussians made 0
        start = data.find(value.numpy().tobytes())
        assert start > 0
        data[start:start + value.numel() * 4] = bytes(value.numel() * 4)
    with open(path, "r+b") as stream:
        stream.write(data)
    assert_same_bits(loaded, scene_from_splatfacto(params))
