"""Load Gaussian Scene and Save Gaussian Scene on the shared bear scene, called as ComfyUI calls them: the
input folder's files or a path, every format written and read back, names checked before the graph runs."""

import gzip
import struct

import pytest
import torch

from artnvg_core.formats import read_ply, save_scene, write_ply
from node_calls import bear, call, comfy_dirs, same_scene, small_bear  # noqa: F401  (fixtures)
from nodes.node_errors import NodeInputError
from nodes.scene_nodes import LoadGaussianScene, SaveGaussianScene

def test_load_scene_from_input_folder_or_path(comfy_dirs, bear, monkeypatch):
    listed = LoadGaussianScene.INPUT_TYPES()["required"]["scene_file"]
    assert listed[0] == "COMBO" and listed[1]["options"] == ["bear/scene.ply"]
    assert LoadGaussianScene.check_files(scene_file="bear/scene.ply", drop_invalid=True) is None
    (from_list,) = call(LoadGaussianScene, scene_file="bear/scene.ply")["result"]
    (from_path,) = call(LoadGaussianScene, scene_file="", path=str(comfy_dirs / "input" / "bear" / "scene.ply"),
                        )["result"]
    assert same_scene(from_list, bear["scene"]) and same_scene(from_path, bear["scene"])
    outside = str(bear["folder"] / "scene.ply")
    assert "is outside ComfyUI's input" in LoadGaussianScene.check_files(scene_file="", path=outside)
    monkeypatch.setenv("ARTNVG_READ_ANY_PATH", "1")  # the setting that opens every path
    assert same_scene(call(LoadGaussianScene, scene_file="", path=outside)["result"][0], bear["scene"])


def test_missing_scene_names_the_input_and_the_file(comfy_dirs):
    message = LoadGaussianScene.check_files(scene_file="bear/nothing.ply")
    assert "scene_file" in message and "bear/nothing.ply" in message
    message = LoadGaussianScene.check_files(scene_file="bear/scene.ply", path="/no/such/scene.ply")
    assert "'path'" in message and "/no/such/scene.ply" in message
    with pytest.raises(NodeInputError, match=r"Load Gaussian Scene: input 'path': .*/no/such/scene\.ply"):
        call(LoadGaussianScene, scene_file="bear/scene.ply", path="/no/such/scene.ply")
    (comfy_dirs / "input" / "broken.ply").write_text("not a ply")
    with pytest.raises(NodeInputError, match=r"input 'scene_file': .*broken\.ply"):
        call(LoadGaussianScene, scene_file="broken.ply")


def test_invalid_gaussians_are_refused_naming_the_nodes_own_switch(comfy_dirs, small_bear):
    """The library's advice, 'pass drop_invalid=True', is a Python argument; the node has a drop_invalid toggle."""
    ply = comfy_dirs / "input" / "nan.ply"
    write_ply(small_bear, ply)
    data = bytearray(ply.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    data[body:body + 4] = struct.pack("<f", float("nan"))  # x of the first Gaussian
    ply.write_bytes(bytes(data))
    with pytest.raises(NodeInputError, match=r"^Load Gaussian Scene: input 'scene_file': .*nan\.ply: means: 1 of "
                                             r"[0-9,]+ Gaussians has non-finite values \(first at index 0\); turn "
                                             r"drop_invalid on to drop them$"):
        call(LoadGaussianScene, scene_file="nan.ply")
    (scene,) = call(LoadGaussianScene, scene_file="nan.ply", drop_invalid=True)["result"]
    assert len(scene) == len(small_bear) - 1


def test_save_scene_writes_numbered_plys_into_the_output_folder(comfy_dirs, small_bear):
    saved = [call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/stylized") for _ in range(2)]
    assert [s["ui"]["scenes"][0]["filename"] for s in saved] == ["stylized_00001.ply", "stylized_00002.ply"]
    assert saved[0]["ui"]["scenes"][0]["subfolder"] == "artnvg" and saved[0]["ui"]["scenes"][0]["type"] == "output"
    folder = comfy_dirs / "output" / "artnvg"
    assert sorted(p.name for p in folder.iterdir()) == ["stylized_00001.ply", "stylized_00002.ply"]
    assert same_scene(read_ply(folder / "stylized_00002.ply"), small_bear)
    size = (folder / "stylized_00002.ply").stat().st_size
    assert saved[1]["ui"]["text"] == [f"wrote output/artnvg/stylized_00002.ply ({size / 1e6:.1f} MB, "
                                      f"{len(small_bear):,} Gaussians)"]
    assert saved[1]["result"][0] == "artnvg/stylized_00002.ply"  # the path Preview Any shows and Preview 3D loads
    (folder / "stylized_00007.ply").write_bytes(b"")
    (folder / "stylized_extra_00009.ply").write_bytes(b"")  # another prefix: not counted
    call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/stylized")
    assert (folder / "stylized_00008.ply").is_file()
    for prefix in ("../escape", ""):
        with pytest.raises(NodeInputError, match="Save Gaussian Scene: input 'filename_prefix'"):
            call(SaveGaussianScene, scene=small_bear, filename_prefix=prefix)


@pytest.mark.parametrize("prefix", ["artnvg/", "artnvg\\", "artnvg/.", "artnvg/sub/..", "artnvg/ "])
def test_a_prefix_that_ends_in_a_folder_is_refused_before_the_graph_runs(tmp_path, monkeypatch, prefix):
    """'artnvg/' saved output/artnvg_00001.ply, beside the folder it named."""
    monkeypatch.chdir(tmp_path)  # the output folder: ./output
    assert SaveGaussianScene.check_files(filename_prefix=prefix) == (
        f"Save Gaussian Scene: input 'filename_prefix': '{prefix}' ends in a folder, not a file name; add one (e.g. "
        "artnvg/stylized saves artnvg/stylized_00001.ply)")
    assert SaveGaussianScene.check_files(filename_prefix="artnvg/stylized") is None
    assert not (tmp_path / "output").exists()


def test_a_prefix_refused_at_validation_is_labelled_with_that_input(tmp_path, monkeypatch):
    """ComfyUI labels a VALIDATE_INPUTS message with each input that function takes, read from the class: Save Gaussian
    Scene's messages all name filename_prefix ("filename_prefix - ...", the input the editor outlines; it was
    "node_id - ..."), its other inputs being choices that ComfyUI checks itself."""
    import inspect
    import sys
    import types

    from nodes import NODE_CLASS_MAPPINGS
    from nodes.prompt_checks import check_prompt

    monkeypatch.chdir(tmp_path)  # the output folder: ./output
    utils = types.ModuleType("comfy_execution.utils")  # ComfyUI validating node 7 of prompt p
    utils.get_executing_context = lambda: types.SimpleNamespace(prompt_id="p", node_id="7", list_index=None)
    monkeypatch.setitem(sys.modules, "comfy_execution", types.ModuleType("comfy_execution"))
    monkeypatch.setitem(sys.modules, "comfy_execution.utils", utils)
    prompt = {"7": {"class_type": "ArtNVGSaveGaussianScene", "inputs": {"scene": ["1", 0], "filename_prefix": "../x"}}}
    assert check_prompt({"prompt": prompt, "prompt_id": "p"}, NODE_CLASS_MAPPINGS)["partial_execution_targets"] == ["7"]
    assert inspect.getfullargspec(SaveGaussianScene.VALIDATE_INPUTS).args == ["cls", "filename_prefix"]
    assert SaveGaussianScene.VALIDATE_INPUTS(filename_prefix="../x").startswith(
        "Save Gaussian Scene: input 'filename_prefix': '../x' must name a file inside the output folder")


def test_save_scene_never_writes_over_a_file_another_process_saved_under_its_name(comfy_dirs, small_bear, monkeypatch):
    """Two ComfyUI processes sharing the output folder pick the same next name: the one whose file is complete
    second keeps the first one's file and takes the next number."""
    import nodes.scene_nodes as scene_nodes

    written = []

    def rival_saves_first(scene, path, **options):  # the rival claims the name between the pick and the write
        if not written:
            path.write_bytes(b"rival")
        written.append(path.name)
        return save_scene(scene, path, **options)

    monkeypatch.setattr(scene_nodes, "save_scene", rival_saves_first)
    saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/stylized")
    folder = comfy_dirs / "output" / "artnvg"
    assert (folder / "stylized_00001.ply").read_bytes() == b"rival"
    assert written == ["stylized_00001.ply", "stylized_00002.ply"]
    assert saved["result"][0] == "artnvg/stylized_00002.ply" and saved["ui"]["scenes"][0]["filename"] == "stylized_00002.ply"
    assert same_scene(read_ply(folder / "stylized_00002.ply"), small_bear)
    assert sorted(p.name for p in folder.iterdir()) == ["stylized_00001.ply", "stylized_00002.ply"]


def test_save_scene_shows_what_the_format_changes_under_the_node_and_logs_it_once(comfy_dirs, small_bear, caplog,
                                                                                  monkeypatch):
    """The bear's 3 floaters beyond an SPZ's range, moved onto it: said under the node after the file's name and
    once on the console, also when the first name was taken while the file was written (a second write)."""
    import nodes.scene_nodes as scene_nodes

    def rival_saves_first(scene, path, **options):
        if path.name.endswith("_00001.spz"):
            path.write_bytes(b"rival")
        return save_scene(scene, path, **options)

    monkeypatch.setattr(scene_nodes, "save_scene", rival_saves_first)
    with caplog.at_level("INFO"):
        saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/far", format="spz")
    file = comfy_dirs / "output" / "artnvg" / "far_00002.spz"
    note = ("3 Gaussians beyond SPZ's range at 12 fractional bits (|coordinate| up to 2048) moved onto it along their "
            "rays from the origin, their sizes scaled alike (the same direction and apparent size from there); the "
            "farthest from |coordinate| 7682.61")
    assert saved["ui"]["text"] == [f"wrote output/artnvg/far_00002.spz ({file.stat().st_size / 1e6:.1f} MB, "
                                   f"{len(small_bear):,} Gaussians)", f"note: {note}"]
    assert [(r.name, r.getMessage()) for r in caplog.records if r.levelname == "WARNING"] == [
        ("artnvg", f"Save Gaussian Scene: note: {note}")]  # progress_text: under the node, and on the console
    assert call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/near", format="ply")["ui"]["text"] == [
        f"wrote output/artnvg/near_00001.ply ({(file.parent / 'near_00001.ply').stat().st_size / 1e6:.1f} MB, "
        f"{len(small_bear):,} Gaussians)"]


def test_load_scene_reads_a_spz_naming_no_axes_in_front_of_connected_cameras(comfy_dirs, bear, small_bear, caplog):
    """A .spz in RUB with no record: read upright with the capture's cameras connected (spz_axes auto), in
    the PLY's axes without them, which a note under the node says (logged once on the console); a .spz Save
    Gaussian Scene writes reads back upright either way (compared within SPZ's 12-bit range: the writer moves the
    3 floaters beyond it)."""
    near = small_bear.means.abs().amax(1) < 2048
    assert int((~near).sum()) == 3
    save_scene(small_bear, comfy_dirs / "input" / "rub.spz", spz_axes="rub", notes=lambda note: None)
    loaded = f"loaded rub.spz ({len(small_bear):,} Gaussians, SH degree {small_bear.sh_degree})"
    read = call(LoadGaussianScene, scene_file="rub.spz", cameras=bear["cameras"])
    (with_cameras,) = read["result"]
    assert read["ui"]["text"] == [loaded]
    with caplog.at_level("INFO"):
        read = call(LoadGaussianScene, scene_file="rub.spz")
    (alone,) = read["result"]
    note = ("note: the file names no axes: read in the PLY's axes (x right, y down, z forward), as splat-transform, "
            "spz-js and Niantic's ply-to-spz write; if it is upside down, read it with spz axes 'rub' (--spz-axes "
            "rub, the Load Gaussian Scene node's spz_axes)")
    assert read["ui"]["text"] == [loaded, note]
    assert [(r.name, r.getMessage()) for r in caplog.records if r.levelname == "WARNING"] == [
        ("artnvg", f"Load Gaussian Scene: {note}")]  # progress_text: under the node, and on the console
    assert (with_cameras.means - small_bear.means)[near].abs().max() < 1e-3
    assert torch.equal(alone.means, with_cameras.means * torch.tensor([1.0, -1, -1]))
    saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="ours", format="spz")
    name = saved["ui"]["scenes"][0]["filename"]
    for cameras in (None, bear["cameras"]):
        ours = call(LoadGaussianScene, scene_file="", path=str(comfy_dirs / "output" / name), cameras=cameras)
        (ours,) = ours["result"]
        assert (ours.means - small_bear.means)[near].abs().max() < 1e-3


def test_save_scene_format_picks_spz_splat_or_ksplat_and_load_reads_them(comfy_dirs, small_bear):
    for fmt in ("spz", "splat", "ksplat"):
        saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/small", format=fmt)
        name = saved["ui"]["scenes"][0]["filename"]
        assert name == f"small_00001.{fmt}"
        (loaded,) = call(LoadGaussianScene, scene_file="", path=str(comfy_dirs / "output" / "artnvg" / name),
                         )["result"]
        degree = {"spz": small_bear.sh_degree, "splat": 0, "ksplat": min(small_bear.sh_degree, 2)}[fmt]
        assert len(loaded) == len(small_bear) and loaded.sh_degree == degree
    with pytest.raises(NodeInputError, match="Save Gaussian Scene: input 'format': expected one of"):
        call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/small", format="obj")


def test_save_scene_spz_version_reaches_the_writer(comfy_dirs, small_bear):
    """spz_version 2 (for spz-js) writes a version 2 header; 3 is the default; others are refused by name."""
    for version in ("2", "3", None):
        saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="v", format="spz",
                     **({} if version is None else {"spz_version": version}))
        header = gzip.decompress((comfy_dirs / "output" / saved["ui"]["scenes"][0]["filename"]).read_bytes())
        assert header[:8] == struct.pack("<II", 0x5053474E, int(version or 3)), version
    with pytest.raises(NodeInputError, match=r"Save Gaussian Scene: input 'spz_version': expected one of \['3', '2'\]"):
        call(SaveGaussianScene, scene=small_bear, filename_prefix="v", format="spz", spz_version="4")


def test_save_scene_refuses_a_prefix_too_long_for_its_files_before_the_graph_runs(comfy_dirs):
    fits = "artnvg/" + "s" * 200  # 200 + "_00001.ply" and the temporary's 29 bytes: 239 of 255
    assert SaveGaussianScene.check_files(filename_prefix=fits) is None
    message = SaveGaussianScene.check_files(filename_prefix="artnvg/" + "s" * 225, format="ply")
    assert message.startswith("Save Gaussian Scene: input 'filename_prefix': the saved file: the file name ssss")
    assert "is 235 bytes long; it may have at most 226 here" in message
    assert SaveGaussianScene.check_files(filename_prefix="../escape").startswith(
        "Save Gaussian Scene: input 'filename_prefix': '../escape' must name a file inside the output folder")
    assert not (comfy_dirs / "output" / "artnvg").exists()  # nothing made by a check


def test_save_scene_refuses_a_prefix_whose_folder_is_a_file_before_the_graph_runs(comfy_dirs, small_bear):
    """A prefix's folder that is a file in the output folder is refused by name before the run, and by the
    node itself, rather than failing in mkdir with a bare FileExistsError; the file is left as it was."""
    taken = comfy_dirs / "output" / "taken"
    taken.parent.mkdir()
    taken.write_bytes(b"a user's file")
    expected = f"Save Gaussian Scene: input 'filename_prefix': the saved file's folder: {taken.resolve()} exists and is not a folder"
    assert SaveGaussianScene.check_files(filename_prefix="taken/stylized") == expected
    with pytest.raises(NodeInputError) as refused:
        call(SaveGaussianScene, scene=small_bear, filename_prefix="taken/stylized")
    assert str(refused.value) == expected
    assert taken.read_bytes() == b"a user's file" and sorted(taken.parent.iterdir()) == [taken]
