"""ComfyUI core splat interop (nodes/splat_interop.py, splat_nodes.py and Save's 3D file output).

With ComfyUI's 2026 types, tests/comfy_api_standin.py stands in for ``comfy_api.latest`` (both
names of the splat type); without them (as in ComfyUI 0.3.64) the nodes say what is missing.
"""

import dataclasses
import importlib
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import nodes.scene_nodes
import nodes.splat_interop
import nodes.splat_nodes
from artnvg_core.activated import activate
from artnvg_core.formats import read_ply
from nodes.node_errors import NodeInputError
from tests import comfy_api_standin
from tests.test_activated import opacities_agree, random_scene, ulps_apart

MODULES = (nodes.splat_interop, nodes.splat_nodes, nodes.scene_nodes)  # in import order


def reload_all():
    return [importlib.reload(module) for module in MODULES]


@pytest.fixture(params=["SPLAT", "GAUSSIAN"])
def core(request, monkeypatch):
    """The node modules re-imported on a ComfyUI whose splat type is named ``request.param``."""
    api_types = comfy_api_standin.install(monkeypatch, request.param)
    interop, splat_nodes, scene_nodes = reload_all()
    yield SimpleNamespace(name=request.param, types=api_types, interop=interop, splat_nodes=splat_nodes,
                          scene_nodes=scene_nodes)
    monkeypatch.undo()
    reload_all()


def core_splat(api_types, name, scene, **changes):
    """A splat as ComfyUI's own file reader makes it: float32 exp / sigmoid of the raw values, batch of one."""
    fields = {
        "positions": scene.means[None],
        "scales": torch.exp(scene.log_scales)[None],
        "rotations": torch.nn.functional.normalize(scene.quats, dim=1)[None],
        "opacities": torch.sigmoid(scene.opacity_logits)[None, :, None],
        "sh": scene.sh[None],
    } | changes
    return getattr(api_types, name)(**fields)


def test_without_core_types_the_nodes_say_what_is_missing(tmp_path, monkeypatch):
    assert nodes.splat_interop.SPLAT_CLASS is None and nodes.splat_interop.FILE3D_CLASS is None
    for node in (nodes.splat_nodes.SceneToSplat, nodes.splat_nodes.SplatToScene):
        assert "This ComfyUI lacks it, so this node cannot run here" in node.DESCRIPTION
    with pytest.raises(NodeInputError, match="Gaussian Scene to Splat: Needs ComfyUI's core Gaussian splat type"):
        nodes.splat_nodes.SceneToSplat().convert(random_scene(n=3))
    save = nodes.scene_nodes.SaveGaussianScene
    assert save.RETURN_TYPES == ("STRING", "LOAD3D_CAMERA")
    assert "Preview Gaussian Splat; this ComfyUI lacks them, so it has no model_3d output" in save.DESCRIPTION
    monkeypatch.chdir(tmp_path)
    model_file, camera = save().save(random_scene(n=3), "artnvg/plain")["result"]
    assert model_file == "artnvg/plain_00001.ply" and camera["cameraType"] == "perspective"


def test_scene_to_splat_and_back_is_bit_exact(core):
    scene = random_scene(n=500)
    (splat,) = core.splat_nodes.SceneToSplat().convert(scene)
    assert isinstance(splat, getattr(core.types, core.name)) and splat.counts is None
    assert [tuple(t.shape) for t in (splat.positions, splat.scales, splat.rotations, splat.opacities, splat.sh)] == \
        [(1, 500, 3), (1, 500, 3), (1, 500, 4), (1, 500, 1), (1, 500, 16, 3)]
    a = activate(scene)
    assert torch.equal(splat.scales[0], a.scales) and torch.equal(splat.opacities[0, :, 0], a.opacities)
    (back,) = core.splat_nodes.SplatToScene().convert(splat)
    for name, value in scene.tensors().items():
        assert torch.equal(getattr(back, name), value), name
    assert core.splat_nodes.SceneToSplat.RETURN_TYPES == (core.name,)
    assert core.splat_nodes.SplatToScene.INPUT_TYPES()["required"]["splat"] == (core.name,)


def test_a_changed_or_core_made_splat_converts_by_the_formulas(core):
    scene = random_scene(n=500, degree=1)
    (splat,) = core.splat_nodes.SceneToSplat().convert(scene)
    splat.positions = splat.positions + 1  # as a core node would: new tensors
    (moved,) = core.splat_nodes.SplatToScene().convert(splat)
    assert torch.equal(moved.means, scene.means + 1) and torch.equal(moved.sh, scene.sh)
    made = core_splat(core.types, core.name, scene)
    (read,) = core.splat_nodes.SplatToScene().convert(made)
    assert ulps_apart(activate(read).scales, made.scales[0]).max() <= 1
    assert opacities_agree(activate(read).opacities, made.opacities[0, :, 0])
    torch.testing.assert_close(read.log_scales, scene.log_scales, rtol=0, atol=3e-7)


def test_counts_cut_the_item_and_bad_batches_are_refused(core):
    scene = random_scene(n=5, degree=0)
    convert = core.splat_nodes.SplatToScene().convert
    (cut,) = convert(core_splat(core.types, core.name, scene, counts=torch.tensor([3])))
    assert len(cut) == 3 and torch.equal(cut.means, scene.means[:3])
    cases = [
        ({"counts": torch.tensor([0])}, r"counts: 0 is not a length in 1\.\.5"),
        ({"positions": scene.means[None].expand(2, 5, 3)}, r"positions: expected a batch of one splat \(1, N, 3\), got shape \(2, 5, 3\)"),
        ({"sh": torch.zeros(1, 5, 25, 3)}, r"sh: 25 coefficients per channel .* \(SH degree above 3 is not supported\)"),
        ({"scales": -torch.ones(1, 5, 3)}, "scales: 5 of 5 Gaussians have a scale that is not positive"),
    ]
    for changes, message in cases:
        with pytest.raises(NodeInputError, match=r"^Splat to Gaussian Scene: input 'splat': " + message):
            convert(core_splat(core.types, core.name, scene, **changes))


@pytest.mark.parametrize(("blur", "antialiased"), [(0.1, True), (0.3, True), (0.1, False), (0.3, False)])
def test_render_settings_travel_with_the_splat_both_ways(core, blur, antialiased):
    scene = dataclasses.replace(random_scene(n=40, degree=1), blur_px2=blur, antialiased=antialiased)
    (splat,) = core.splat_nodes.SceneToSplat().convert(scene)
    assert splat.render_settings == {"eps2d": blur, "rasterize_mode": "antialiased" if antialiased else "classic"}
    (back,) = core.splat_nodes.SplatToScene().convert(splat)
    assert (back.blur_px2, back.antialiased) == (blur, antialiased)
    moved = core_splat(core.types, core.name, scene)  # made anew, as a core node would, keeping the attribute
    moved.render_settings = splat.render_settings
    (again,) = core.splat_nodes.SplatToScene().convert(moved)
    assert (again.blur_px2, again.antialiased) == (blur, antialiased)
    (plain,) = core.splat_nodes.SplatToScene().convert(core_splat(core.types, core.name, scene))
    assert (plain.blur_px2, plain.antialiased) == (0.3, False)  # no settings: classic


@pytest.mark.parametrize(("settings", "message"), [
    ({"eps2d": -1.0}, r"render_settings\['eps2d'\]: expected a finite number >= 0, got -1\.0"),
    ({"eps2d": float("nan")}, r"render_settings\['eps2d'\]: expected a finite number >= 0"),
    ({"rasterize_mode": "mip"}, r"render_settings\['rasterize_mode'\]: expected one of \('classic', 'antialiased'\)"),
])
def test_bad_render_settings_are_refused(core, settings, message):
    splat = core_splat(core.types, core.name, random_scene(n=5, degree=0))
    splat.render_settings = settings
    with pytest.raises(NodeInputError, match=r"^Splat to Gaussian Scene: input 'splat': " + message):
        core.splat_nodes.SplatToScene().convert(splat)


def test_save_outputs_the_written_ply_for_preview_gaussian_splat(core, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    save = core.scene_nodes.SaveGaussianScene
    assert save.RETURN_TYPES == ("STRING", "LOAD3D_CAMERA", "FILE_3D_SPLAT_ANY")
    assert save.RETURN_NAMES == ("model_file", "camera_info", "model_3d")
    scene = random_scene(n=50)
    result = save().save(scene, "artnvg/stylized")
    model_file, _, model_3d = result["result"]
    assert model_file == "artnvg/stylized_00001.ply"
    assert model_3d.format == "ply" and result["ui"]["scenes"][0]["filename"] == "stylized_00001.ply"
    written = tmp_path / "output" / "artnvg" / "stylized_00001.ply"
    assert model_3d.get_bytes() == written.read_bytes()
    copy = tmp_path / "preview.ply"  # what Preview Gaussian Splat does with it
    model_3d.save_to(str(copy))
    for name, value in read_ply(copy).tensors().items():
        assert np.array_equal(getattr(scene, name).numpy(), value.numpy()), name
    *_, spz = save().save(scene, "artnvg/stylized", "spz")["result"]
    assert spz.format == "spz" and spz.get_bytes() == (tmp_path / "output" / "artnvg" / "stylized_00001.spz").read_bytes()

    *_, ksplat = save().save(scene, "artnvg/stylized", "ksplat")["result"]
    assert ksplat.format == "ksplat"


def test_before_file3d_splat_any_each_container_is_listed(monkeypatch):
    """A ComfyUI with File3D but without FILE_3D_SPLAT_ANY: the output lists each container's type."""
    comfy_api_standin.install(monkeypatch, "SPLAT", splat_any=False)
    try:
        _, _, scene_nodes = reload_all()
        assert scene_nodes.SaveGaussianScene.RETURN_TYPES[2:] == ("FILE_3D_PLY,FILE_3D_SPZ,FILE_3D_SPLAT,FILE_3D_KSPLAT",)
    finally:
        monkeypatch.undo()
        reload_all()
