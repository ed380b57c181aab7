"""GaussianScene: shapes, render settings, validation."""

import re

import pytest
import torch

from artnvg_core.scene import GaussianScene, describe_invalid, validate_scene
from tests.test_formats_ply import random_scene


def test_map_and_select_keep_the_render_settings():
    scene = GaussianScene(**random_scene(5, 1).tensors(), blur_px2=0.1, antialiased=True)
    for derived in (scene.map(lambda t: t * 1), scene.select(slice(0, 2)), scene.to(dtype=torch.float64)):
        assert (derived.blur_px2, derived.antialiased, derived.classic) == (0.1, True, False)
    assert random_scene(3, 0).classic
    assert set(scene.tensors()) == {"means", "quats", "log_scales", "opacity_logits", "sh"}


@pytest.mark.parametrize("blur", [-0.1, float("nan"), float("inf"), "0.3", True])
def test_bad_blur_is_rejected(blur):
    with pytest.raises(ValueError, match="GaussianScene.blur_px2: expected a finite number >= 0"):
        GaussianScene(**random_scene(3, 0).tensors(), blur_px2=blur)


@pytest.mark.parametrize("antialiased", ["no", 0, None])
def test_antialiased_other_than_a_bool_is_rejected(antialiased):
    """"no" was taken as true: the opacities compensated for a filter the scene was not trained with."""
    with pytest.raises(ValueError, match=f"GaussianScene.antialiased: expected True or False, got {antialiased!r}"):
        GaussianScene(**random_scene(3, 0).tensors(), antialiased=antialiased)


@pytest.mark.parametrize("field, value, expected", [
    ("means", lambda t: t.long(), "a floating-point torch.Tensor, got torch.int64"),
    ("sh", lambda t: t.numpy(), "a floating-point torch.Tensor, got ndarray"),
    ("sh", lambda t: t.double(), "the means' dtype and device (torch.float32 on cpu), got torch.float64 on cpu"),
    ("quats", lambda t: t.to("meta"), "the means' dtype and device (torch.float32 on cpu), got torch.float32 on meta"),
])
def test_tensors_of_another_kind_dtype_or_device_are_rejected(field, value, expected):
    """An integer scene rendered silently through integer cameras; float64 means beside float32 SH stopped
    deep in the compositing with torch's "expected scalar type Float but found Double"."""
    tensors = random_scene(3, 1).tensors()
    tensors[field] = value(tensors[field])
    with pytest.raises(ValueError, match=re.escape(f"GaussianScene.{field}: expected {expected}")):
        GaussianScene(**tensors)


def test_select_takes_masks_indices_and_slices_and_refuses_others():
    """A mask of another length, float indices and indices out of range stopped with torch's IndexError; uint8
    indices were taken for a mask."""
    scene = random_scene(6, 1)
    picked = {"mask": [True, False] * 3, "indices": torch.tensor([-6, 5, 5]),
              "uint8": torch.tensor([1, 0], dtype=torch.uint8),
              "list": [4], "none": [], "slice": slice(1, 3)}
    expected = {"mask": [0, 2, 4], "indices": [0, 5, 5], "uint8": [1, 0], "list": [4], "none": [], "slice": [1, 2]}
    for name, index in picked.items():
        assert torch.equal(scene.select(index).sh, scene.sh[expected[name]]), name
    for index, message in [(torch.tensor([True, False]), r"a boolean mask must have shape \(6,\), got torch.bool of shape \(2,\)"),
                           (torch.tensor([1.0, 0.0]), "expected a boolean mask \\[N\\], integer indices \\[K\\] or a slice, got torch.float32"),
                           (torch.tensor(3), "expected .* got torch.int64 of shape \\(\\)"),
                           ([6], r"indices must lie in -6..5 for 6 Gaussians"), ([-7, 0], "indices must lie in -6..5")]:
        with pytest.raises(ValueError, match="GaussianScene.select: " + message):
            scene.select(index)


def test_validate_scene_passes_a_valid_scene_through():
    scene = random_scene(6, 3)
    checked, dropped = validate_scene(scene, "memory")
    assert dropped == 0 and checked is scene


def test_scene_with_no_valid_gaussians_is_an_error():
    scene = random_scene(3, 0)
    scene.opacity_logits[:] = float("nan")
    with pytest.raises(ValueError, match="memory: all 3 Gaussians are invalid"):
        validate_scene(scene, "memory", drop_invalid=True)
    with pytest.raises(ValueError, match="memory: the scene contains no Gaussians"):
        validate_scene(scene.select(torch.zeros(3, dtype=torch.bool)), "memory")


def test_counts_in_the_messages_agree_with_one(caplog):
    """Once '1 of 4 Gaussians have a zero norm', 'all 1 Gaussians are invalid' and 'dropped 1 of 40000 invalid
    Gaussians' (as if all 40,000 were invalid)."""
    bad = torch.tensor([False, True, False, False])
    assert describe_invalid("quats", bad, "have a zero norm") == "quats: 1 of 4 Gaussians has a zero norm (first at index 1)"
    assert describe_invalid("x", torch.ones(2, dtype=torch.bool), "lie outside") == "x: 2 of 2 Gaussians lie outside (first at index 0)"
    one = random_scene(3, 0).select(slice(0, 1))
    one.means[:] = float("nan")
    with pytest.raises(ValueError, match=r"^memory: its one Gaussian is invalid \(means: 1 with non-finite values\)$"):
        validate_scene(one, "memory", drop_invalid=True)
    scene = random_scene(1200, 0)
    scene.means[7] = float("nan")
    with caplog.at_level("WARNING", logger="artnvg_core.scene"):
        assert validate_scene(scene, "memory", drop_invalid=True)[1] == 1
    assert "memory: dropped 1 invalid Gaussian of 1,200 (means: 1 with non-finite values)" in caplog.text


def test_the_dropped_gaussians_are_told_to_notes_once_or_else_logged(caplog):
    scene = random_scene(50, 1)
    scene.means[3, 1] = float("nan")
    scene.quats[9] = 0.0
    scene.sh[9, 2, 0] = float("inf")  # the same Gaussian: dropped once
    notes = []
    with caplog.at_level("INFO"):
        kept, dropped = validate_scene(scene, "memory", drop_invalid=True, notes=notes.append)
        assert caplog.records == []
        validate_scene(scene, "memory", drop_invalid=True)
    note = ("dropped 2 invalid Gaussians of 50 (means: 1 with non-finite values; sh: 1 with non-finite values; "
            "quats: 1 with a zero norm)")
    assert (len(kept), dropped, notes) == (48, 2, [note])
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [("WARNING", f"memory: {note}")]
    validate_scene(random_scene(5, 0), "memory", drop_invalid=True, notes=notes.append)
    assert notes == [note]  # none for a scene that is whole


def test_validation_in_chunks_finds_what_the_whole_check_finds_and_stops_between_them(monkeypatch):
    from artnvg_core import scene as scene_module
    from artnvg_core.progress import Cancelled
    from artnvg_core.scene import invalid_gaussians

    scene = random_scene(100, 1)
    scene.sh[37, 2, 1] = float("nan")
    scene.quats[99] = 0
    scene.means[0, 2] = float("inf")
    whole = invalid_gaussians(scene)
    monkeypatch.setattr(scene_module, "CHECKED_ROWS", 16)
    chunked = invalid_gaussians(scene)
    assert [(name, problem) for name, problem, _ in chunked] == [(name, problem) for name, problem, _ in whole]
    for (_, _, a), (_, _, b) in zip(chunked, whole):
        assert torch.equal(a, b)
    assert [int(bad.nonzero()[0, 0]) for _, _, bad in chunked if bad.any()] == [0, 37, 99]
    calls = []
    with pytest.raises(Cancelled):
        validate_scene(scene, "scene.ply", should_stop=lambda: calls.append(1) or len(calls) == 3)
    assert len(calls) == 3  # asked before each chunk of 16: stopped before the third
