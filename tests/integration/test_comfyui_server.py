"""The pack inside a real ComfyUI server: loading, /object_info, queueing over HTTP, interrupt, errors.

Runs only when ARTNVG_COMFYUI_ROOT is set (see conftest.py). Workflows are the shipped
NNFM-only API workflow with small settings set through the queueing script's overrides.
"""

from __future__ import annotations

import importlib.util
import json
import struct
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import pytest
import torch
from test_nodes_contracts import PUBLIC_INPUTS, PUBLIC_OUTPUTS
from test_orbit import standing_blob
from test_workflows import CAMERA_FREE_API, FULL_API, NNFM_API, REGION_API, STOCK_NODES
from ws_client import WebSocket

from artnvg_core.formats import read_ply, save_scene
from artnvg_core.selection import parse_region, select_region

REPO = Path(__file__).resolve().parents[2]
FINETUNE = "6"  # node id of Finetune Gaussians in artnvg_nnfm_only_api.json
LOAD_SCENE, SAVE_SCENE = "1", "7"  # of Load Gaussian Scene and Save Gaussian Scene


def _queue_script():
    spec = importlib.util.spec_from_file_location("queue_workflow", REPO / "workflows_api" / "queue_workflow.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


queue = _queue_script()


def _get(server, path: str) -> dict:
    with urllib.request.urlopen(server.url + path, timeout=60) as response:
        return json.loads(response.read())


def _workflow(server, *overrides: str) -> dict:
    """The NNFM-only workflow on the test inputs at small settings, then ``overrides``."""
    folder = server.test_folder
    small = [
        f"Load Gaussian Scene.scene_file={folder}/scene.ply",
        f"Load Cameras.camera_source={folder}/transforms.json",
        f"Style image.image={folder}/style.jpg",
        "Render Views.scale=0.125", "Render Views.stride=12",  # 2 of the 24 demo views
        "Render Camera Path.scale=0.125", "Render Camera Path.num_frames=2",
    ]
    workflow = queue.load_api_workflow(NNFM_API)
    for assignment in [*small, *overrides]:
        queue.apply_override(workflow, assignment)
    return workflow


def _run(server, workflow: dict, on_message=None, timeout: float = 900) -> tuple[dict, list[dict]]:
    """Queue ``workflow``, follow its websocket messages until it ends; (history entry, messages)."""
    client_id = uuid.uuid4().hex
    socket = WebSocket(f"{server.url.replace('http', 'ws')}/ws?clientId={client_id}", timeout=timeout)
    try:
        prompt_id = queue.queue_prompt(server.url, workflow, client_id)
        messages = []
        while True:
            message = socket.receive_json()
            data = message.get("data", {})
            if data.get("prompt_id") != prompt_id:
                continue
            messages.append(message)
            if on_message is not None:
                on_message(message)
            if message["type"] in ("execution_success", "execution_error", "execution_interrupted"):
                break
    finally:
        socket.close()
    return queue.wait_for(server.url, prompt_id, timeout=60), messages


def _finetune_progress(messages: list[dict], node: str = FINETUNE) -> list[tuple[int, int]]:
    return [(m["data"]["value"], m["data"]["max"]) for m in messages
            if m["type"] == "progress" and m["data"].get("node") == node]


def test_pack_loads_without_import_errors(comfy_server):
    log = comfy_server.log.read_text()
    lines = [line for line in log.splitlines() if line.rstrip().endswith(f"custom_nodes/{comfy_server.pack}")]
    assert lines, f"the pack is not in the import report of {comfy_server.log}"
    assert "IMPORT FAILED" not in lines[0]
    assert "Cannot import" not in log


def _core_splat_type(info: dict) -> str | None:
    """The link type of ComfyUI's core splat, judged by its file-to-splat node; None without one (0.3.64)."""
    return next((kind for node, kind in (("File3DToSplat", "SPLAT"), ("File3DToGaussian", "GAUSSIAN")) if node in info),
                None)


def test_object_info_lists_every_node_with_its_inputs(comfy_server):
    info = _get(comfy_server, "/object_info")
    core = _core_splat_type(info)
    saved_file = ("FILE_3D_SPLAT_ANY" if "FILE_3D_SPLAT_ANY" in json.dumps(info)
                  else "FILE_3D_PLY,FILE_3D_SPZ,FILE_3D_SPLAT,FILE_3D_KSPLAT")
    with_core_types = ({"ArtNVGSaveGaussianScene": (*PUBLIC_OUTPUTS["ArtNVGSaveGaussianScene"], saved_file),
                        "ArtNVGSceneToSplat": (core,)} if core else {})
    for name, inputs in PUBLIC_INPUTS.items():
        node = info[name]
        order = node["input_order"]
        assert order.get("required", []) + order.get("optional", []) == inputs, name
        assert tuple(node["output"]) == with_core_types.get(name, PUBLIC_OUTPUTS[name]), name
        assert node["category"] == "ArtNVG" and node["display_name"]
    folder = comfy_server.test_folder
    assert f"{folder}/scene.ply" in info["ArtNVGLoadGaussianScene"]["input"]["required"]["scene_file"][1]["options"]
    assert f"{folder}/transforms.json" in info["ArtNVGLoadCameras"]["input"]["required"]["camera_source"][1]["options"]
    assert info["ArtNVGSaveGaussianScene"]["output_node"] is True
    for name, (types, outputs, display_name) in STOCK_NODES.items():  # what tests/test_workflows.py assumes
        assert set(info[name]["input"]["required"]) == set(types["required"]), name
        assert tuple(info[name]["output"]) == outputs and info[name]["display_name"] == display_name


def test_splat_nodes_say_what_this_comfyui_lacks(comfy_server):
    info = _get(comfy_server, "/object_info")
    save, to_splat, to_scene = (info[name] for name in
                                ("ArtNVGSaveGaussianScene", "ArtNVGSceneToSplat", "ArtNVGSplatToScene"))
    if _core_splat_type(info) is None:  # e.g. 0.3.64: everything as before, and the descriptions say why
        assert "This ComfyUI lacks it, so this node cannot run here" in to_splat["description"]
        assert "This ComfyUI lacks it, so this node cannot run here" in to_scene["description"]
        assert save["output"] == ["STRING", "LOAD3D_CAMERA"]
        assert "this ComfyUI lacks them, so it has no model_3d output" in save["description"]
    else:
        assert "lacks" not in to_splat["description"] + to_scene["description"] + save["description"]
        assert to_scene["input"]["required"]["splat"][0] == to_splat["output"][0] == _core_splat_type(info)


def test_nnfm_workflow_completes_and_writes_a_ply_that_loads(comfy_server):
    folder = comfy_server.test_folder
    before = set((comfy_server.output_dir / folder).glob("nnfm_*.ply"))
    # a scene file no earlier prompt loaded: ComfyUI reuses a node's output for the inputs it ran with before, and a
    # node it does not run sends no progress (the other tests load scene.ply, in any order)
    scene = comfy_server.input_dir / folder / f"scene_{uuid.uuid4().hex[:8]}.ply"
    scene.write_bytes((comfy_server.input_dir / folder / "scene.ply").read_bytes())
    try:
        entry, messages = _run(comfy_server, _workflow(
            comfy_server, "6.iterations=3", f"Save Gaussian Scene.filename_prefix={folder}/nnfm",
            f"Load Gaussian Scene.scene_file={folder}/{scene.name}"))
        size = scene.stat().st_size
    finally:
        scene.unlink()
    summary = queue.run_summary(entry)
    assert summary["status"] == "success", summary["error"]
    # 2 views rendered before the steps (one call), their content features, 3 steps, the 2 views again: each
    # stage's bar shown as it starts (0)
    progress = _finetune_progress(messages)
    assert progress == [(0, 2), (2, 2), (0, 2), (1, 2), (2, 2), (0, 3), (1, 3), (2, 3), (3, 3), (0, 2), (2, 2)], progress
    # the scene's load: one bar over the file's bytes, filled once (its read, decoding and check in turn)
    loading = _finetune_progress(messages, LOAD_SCENE)
    assert {total for _, total in loading} == {size} and loading[0][0] == 0 and loading[-1][0] == size, loading
    assert [value for value, _ in loading] == sorted(value for value, _ in loading), loading
    saved = [o for o in summary["outputs"] if o["kind"] == "scenes"]
    assert len(saved) == 1 and saved[0]["type"] == "output"
    path = comfy_server.output_dir / saved[0]["file"]
    assert path not in before
    result, original = read_ply(path), read_ply(comfy_server.input_dir / folder / "scene.ply")
    assert len(result) == len(original) and torch.equal(result.means, original.means)
    assert not torch.equal(result.sh, original.sh)  # the appearance was stylized
    previews = [o for o in summary["outputs"] if o["kind"] == "images"]
    assert len(previews) == 4  # 2 content views + 2 orbit frames


def test_what_the_format_drops_reaches_save_gaussian_scenes_text_and_the_console_once(comfy_server):
    """The test scene is of SH degree 1, a .splat of degree 0: the note follows the file's name in the node's UI
    text (the run's history) and is logged once (it is also shown under the node: progress text)."""
    folder = comfy_server.test_folder
    logged = len(comfy_server.log.read_text())
    entry, _ = _run(comfy_server, _workflow(comfy_server, "6.iterations=1", "Save Gaussian Scene.format=splat",
                                            f"Save Gaussian Scene.filename_prefix={folder}/noted"))
    assert queue.run_summary(entry)["status"] == "success"
    note = "note: .splat holds SH up to degree 0; the degree 1 view-dependent terms are dropped"
    written, *notes = entry["outputs"][SAVE_SCENE]["text"]
    assert written.startswith(f"wrote output/{folder}/noted_") and notes == [note]
    time.sleep(1)  # the log file is written by the server's process
    assert comfy_server.log.read_text()[logged:].count(note) == 1


def test_what_the_read_did_reaches_load_gaussian_scenes_text_and_the_console_once(comfy_server):
    """The test scene with one Gaussian's x made NaN, loaded with drop_invalid: the note follows the scene's size in
    the node's UI text (the run's history) and is logged once (it is also shown under the node: progress text)."""
    folder = comfy_server.test_folder
    data = (comfy_server.input_dir / folder / "scene.ply").read_bytes()
    body = data.index(b"end_header\n") + len(b"end_header\n")
    count = len(read_ply(comfy_server.input_dir / folder / "scene.ply"))
    row = (len(data) - body) // count
    invalid = comfy_server.input_dir / folder / "one_nan.ply"
    invalid.write_bytes(data[: body + row] + struct.pack("<f", float("nan")) + data[body + row + 4 :])  # x of one
    logged = len(comfy_server.log.read_text())
    try:
        entry, _ = _run(comfy_server, _workflow(comfy_server, "6.iterations=1",
                                                f"Load Gaussian Scene.scene_file={folder}/one_nan.ply",
                                                "Load Gaussian Scene.drop_invalid=true",
                                                f"Save Gaussian Scene.filename_prefix={folder}/dropped"))
    finally:
        invalid.unlink()
    assert queue.run_summary(entry)["status"] == "success"
    note = f"note: dropped 1 invalid Gaussian of {count:,} (means: 1 with non-finite values)"
    assert entry["outputs"][LOAD_SCENE]["text"] == [f"loaded one_nan.ply ({count - 1:,} Gaussians, SH degree 1)", note]
    time.sleep(1)  # the log file is written by the server's process
    assert comfy_server.log.read_text()[logged:].count("dropped 1 invalid Gaussian") == 1


def _run_saving_a_scene(server, api_workflow: Path, assignments) -> tuple:
    """Queue a shipped API workflow with ``queue_workflow``'s overrides; it must succeed and save one scene of the
    test folder's scene.ply. (workflow, run summary, the saved scene, the original scene)."""
    workflow = queue.load_api_workflow(api_workflow)
    for assignment in assignments:
        queue.apply_override(workflow, assignment)
    entry, _ = _run(server, workflow)
    summary = queue.run_summary(entry)
    assert summary["status"] == "success", summary["error"]
    (saved,) = [o for o in summary["outputs"] if o["kind"] == "scenes"]
    original = read_ply(server.input_dir / server.test_folder / "scene.ply")
    return workflow, summary, read_ply(server.output_dir / saved["file"]), original


def test_camera_free_workflow_stylizes_a_bare_scene_file(comfy_server):
    folder = comfy_server.test_folder
    _, summary, result, original = _run_saving_a_scene(comfy_server, CAMERA_FREE_API, (
        f"Load Gaussian Scene.scene_file={folder}/scene.ply", f"Style image.image={folder}/style.jpg",
        "Cameras Around Scene.count=3", "Render Views.scale=0.125", "Finetune Gaussians.iterations=3",
        "Render Camera Path.scale=0.125", "Render Camera Path.num_frames=2",
        f"Save Gaussian Scene.filename_prefix={folder}/camera_free"))
    assert torch.equal(result.means, original.means) and not torch.equal(result.sh, original.sh)
    assert len([o for o in summary["outputs"] if o["kind"] == "images"]) == 3 + 2  # content views + orbit frames



def test_a_guessed_up_is_noted_under_cameras_around_scene_in_its_terms_once(comfy_server):
    """A scene with no ground (a standing blob) and up auto: the guess is shown under the node naming its up input
    (progress text) and logged once on the console."""
    folder = comfy_server.test_folder
    standing = comfy_server.input_dir / folder / "standing.ply"
    save_scene(standing_blob().select(slice(0, None, 4)), standing)
    logged = len(comfy_server.log.read_text())
    try:
        _run_saving_a_scene(comfy_server, CAMERA_FREE_API, (
            f"Load Gaussian Scene.scene_file={folder}/standing.ply", f"Style image.image={folder}/style.jpg",
            "Cameras Around Scene.up=auto", "Cameras Around Scene.count=2", "Render Views.scale=0.125",
            "Finetune Gaussians.iterations=1", "Render Camera Path.scale=0.125", "Render Camera Path.num_frames=2",
            f"Save Gaussian Scene.filename_prefix={folder}/standing"))
    finally:
        standing.unlink()
    time.sleep(1)  # the log file is written by the server's process
    log = comfy_server.log.read_text()[logged:]
    assert log.count("Cameras Around Scene: note: the up direction is a guess") == 1
    assert "give the scene's up axis: set this node's up input to -y or another axis" in log and "up='-y'" not in log

def test_region_workflow_stylizes_and_blends_only_the_selection(comfy_server):
    folder = comfy_server.test_folder
    workflow, summary, result, original = _run_saving_a_scene(comfy_server, REGION_API, (
        f"Load Gaussian Scene.scene_file={folder}/scene.ply",
        f"Load Cameras.camera_source={folder}/transforms.json", f"Style image.image={folder}/style.jpg",
        "Render Views.scale=0.125", "Render Views.stride=12", "Finetune Gaussians.iterations=3",
        "Blend Stylization.preview_strengths=0, 1", f"Save Gaussian Scene.filename_prefix={folder}/region"))
    select = next(node for node in workflow.values() if node["class_type"] == "ArtNVGSelectGaussians")["inputs"]
    selection = select_region(original, parse_region(f"{select['mode']}:{select['bounds'].replace(' ', '')}"))
    assert 0 < selection.sum() < len(original)
    assert torch.equal(result.sh[~selection], original.sh[~selection]) and torch.equal(result.means, original.means)
    assert not torch.equal(result.sh[selection], original.sh[selection])
    assert len([o for o in summary["outputs"] if o["kind"] == "images"]) == 2 + 1  # content views + the strip


def test_interrupt_mid_finetune_stops_it_without_writing_a_ply(comfy_server):
    folder = comfy_server.output_dir / comfy_server.test_folder
    interrupted = []

    def interrupt_once_training(message):
        if not interrupted and message["type"] == "progress" and message["data"].get("node") == FINETUNE:
            queue.interrupt(comfy_server.url)
            interrupted.append(message["data"]["value"])

    entry, messages = _run(comfy_server, _workflow(
        comfy_server, "6.iterations=500", "6.seed=1",
        f"Save Gaussian Scene.filename_prefix={comfy_server.test_folder}/interrupted"),
        on_message=interrupt_once_training)
    summary = queue.run_summary(entry)
    assert interrupted and summary["status"] == "interrupted"
    assert messages[-1]["type"] == "execution_interrupted" and messages[-1]["data"]["node_id"] == FINETUNE
    assert max(value for value, _ in _finetune_progress(messages)) < interrupted[0] + 5  # stopped promptly
    assert not list(folder.glob("interrupted*")) and not list(folder.glob(".*.tmp"))


def test_a_run_past_its_timeout_is_taken_off_the_server_and_no_other(comfy_server):
    """queue_workflow --timeout gave up waiting and left the prompt running on the server. Two long runs queued: the
    second's timeout deletes it from the queue and leaves the first running; the first's interrupts it."""
    def queued() -> dict[str, list[str]]:
        listed = _get(comfy_server, "/queue")
        return {key: [item[1] for item in listed[key]] for key in ("queue_running", "queue_pending")}

    first, second = (queue.queue_prompt(comfy_server.url, _workflow(
        comfy_server, "6.iterations=2000", f"6.seed={seed}",
        f"Save Gaussian Scene.filename_prefix={comfy_server.test_folder}/timed_out")) for seed in (11, 12))
    with pytest.raises(queue.ServerError, match=f"^prompt {second} did not finish within 1 s; deleted it from the "
                                                "queue before it started$"):
        queue.wait_for(comfy_server.url, second, timeout=1)
    assert queued() == {"queue_running": [first], "queue_pending": []}
    with pytest.raises(queue.ServerError, match=f"^prompt {first} did not finish within 1 s; interrupted it$"):
        queue.wait_for(comfy_server.url, first, timeout=1)
    assert queue.run_summary(queue.wait_for(comfy_server.url, first, timeout=120))["status"] == "interrupted"
    assert queued() == {"queue_running": [], "queue_pending": []} and second not in _get(comfy_server, "/history")
    assert not list((comfy_server.output_dir / comfy_server.test_folder).glob("timed_out*"))


def test_cancel_pressed_inside_a_512_px_finetune_step_stops_it_within_the_step(comfy_server):
    """A step at 512 px takes seconds on a CPU (7 to 9 on 2 cores). Cancel pressed halfway through step 2 stops
    the node well before that step would end: the step asks for a stop inside itself (its render, the VGG's
    convolutions, NNFM's search and the backward pass), not only between steps."""
    steps, pressed, stopped = 20, [], []

    def press_cancel_halfway_through_step_two(message):
        data = message["data"]
        if message["type"] == "progress" and data.get("node") == FINETUNE and data["max"] == steps:
            pressed.append(time.monotonic())  # steps 0 and 1 reported: step 1's length
            if len(pressed) == 2:
                time.sleep((pressed[1] - pressed[0]) / 2)
                pressed.append(time.monotonic())
                queue.interrupt(comfy_server.url)
        if message["type"] == "execution_interrupted":
            stopped.append(time.monotonic())

    entry, messages = _run(comfy_server, _workflow(
        comfy_server, f"6.iterations={steps}", "Render Views.scale=1", "Render Views.stride=24",
        f"Save Gaussian Scene.filename_prefix={comfy_server.test_folder}/cancelled_mid_step"),
        on_message=press_cancel_halfway_through_step_two)
    assert queue.run_summary(entry)["status"] == "interrupted" and len(pressed) == 3 and stopped
    step, latency = pressed[1] - pressed[0], stopped[0] - pressed[2]
    assert max(value for value, _ in _finetune_progress(messages)) == 1
    assert latency < step / 4, (latency, step)  # waiting for the step's end would take about step / 2


def _refusal(server, *overrides: str) -> str:
    """The one error ComfyUI answers the NNFM workflow with ``overrides`` with (HTTP 400), for Load Gaussian Scene."""
    with pytest.raises(queue.RejectedError) as rejected:
        queue.queue_prompt(server.url, _workflow(server, *overrides))
    (error,) = rejected.value.details["node_errors"]["1"]["errors"]
    return error["details"]


def test_paths_outside_comfyuis_folders_are_refused_alike_whether_or_not_they_exist(comfy_server, tmp_path):
    outside = tmp_path / "small.ply"
    outside.write_bytes((comfy_server.input_dir / comfy_server.test_folder / "scene.ply").read_bytes())
    existing = _refusal(comfy_server, f"Load Gaussian Scene.path={outside}")
    missing = _refusal(comfy_server, f"Load Gaussian Scene.path={tmp_path / 'missing.ply'}")
    assert "is outside ComfyUI's input, output and model folders" in existing and "ARTNVG_READ_ANY_PATH" in existing
    assert missing == existing.replace(str(outside), str(tmp_path / "missing.ply"))
    climbing = "../" * len(comfy_server.input_dir.resolve().parts) + str(outside).lstrip("/")
    listed = _refusal(comfy_server, f"Load Gaussian Scene.scene_file={climbing}")
    assert listed == existing.replace(f"'path': {str(outside)!r}", f"'scene_file': {climbing!r}")


@pytest.mark.parametrize("override, node, expected, kind", [
    ("Finetune Gaussians.iterations=-1", FINETUNE, "iterations", "value_smaller_than_min"),  # ComfyUI's, once
    ("Save Gaussian Scene.filename_prefix=artnvg/" + "s" * 225, "7", "is 235 bytes long; it may have at most 226",
     "custom_validation_failed"),
    # NaN passes ComfyUI's comparisons: the pack's check, on a node feeding one output (9) of five
    ("Render Camera Path.scale=NaN", "8", "Render Camera Path: input 'scale': expected a finite number, got nan",
     "custom_validation_failed"),
    ('Render Camera Path.num_frames="0"', "8", "num_frames", "value_smaller_than_min"),  # text ComfyUI makes an INT
    # a view given twice, which render --views refuses: the pack's check of the text, before the cameras are known
    ("Render Views.views=1,1", "4", "Render Views: input 'views': view 1 is given twice in '1,1'; give each view once",
     "custom_validation_failed"),
    # past the 24 cameras Load Cameras' file holds: refused before the scene loads (it was as Render Views ran)
    ("Render Views.views=0,30", "4", "Render Views: input 'views': view index 30 is out of range for 24 cameras "
     "(0..23)", "custom_validation_failed"),
    # a key view twice: a zero-length segment of the path (loop returns to the first), as evaluate --views refuses
    ("Render Camera Path.key_views=0,1,1", "8", "Render Camera Path: input 'key_views': view 1 is given twice in "
     "'0,1,1'; give each view once", "custom_validation_failed"),
    # ComfyUI makes an INT's 2.5 a silent 2 (int()); the pack refuses it, as it does one through a link
    ("Render Camera Path.num_frames=2.5", "8", "Render Camera Path: input 'num_frames': expected a whole number, got "
     "2.5", "custom_validation_failed"),
])
def test_a_value_our_nodes_refuse_refuses_the_whole_prompt_before_any_work(comfy_server, override, node, expected,
                                                                            kind):
    errors = _refused_before_any_work(comfy_server, _workflow(comfy_server, override))
    assert expected in json.dumps(errors[node]) and [e["type"] for e in errors[node]["errors"]] == [kind], errors
    assert set(errors) <= {node, "7", "9"}  # the outputs it feeds, reported; no other output ran either


def test_a_key_view_past_the_cameras_is_refused_before_anything_runs_where_path_interpolate_reads_it(comfy_server):
    """Render Camera Path's key views were checked against Load Cameras' 24 cameras only as it ran, after the scene had
    loaded and the finetune had run; mode orbit reads none, so never refuses them (tests/test_nodes_prompt_checks)."""
    errors = _refused_before_any_work(comfy_server, _workflow(comfy_server, "Render Camera Path.path=interpolate",
                                                              "Render Camera Path.key_views=0,30"))
    (error,) = errors["8"]["errors"]
    assert error["type"] == "custom_validation_failed" and error["details"].endswith(
        "Render Camera Path: input 'key_views': path interpolate: view index 30 is out of range for 24 cameras (0..23)")
    assert set(errors) <= {"8", "9"}  # the output it feeds; no other output ran either


def _refused_before_any_work(server, workflow: dict) -> dict:
    """The node errors ComfyUI refuses ``workflow`` with, whole (HTTP 400, not 200 with node errors), having written
    nothing."""
    before = sorted(server.output_dir.rglob("*"))
    request = urllib.request.Request(server.url + "/prompt", headers={"Content-Type": "application/json"},
                                     data=json.dumps({"prompt": workflow}).encode())
    with pytest.raises(urllib.error.HTTPError) as rejected:
        urllib.request.urlopen(request, timeout=60)
    assert rejected.value.code == 400
    assert sorted(server.output_dir.rglob("*")) == before
    return json.loads(rejected.value.read())["node_errors"]


@pytest.mark.parametrize("override, expected", [
    ("Cameras Around Scene.elevations=10, 95", "input 'elevations': 95 degrees is not an elevation in (-90, 90)"),
    ("Cameras Around Scene.up=sideways", "input 'up': expected 'auto', one of +x, -x, +y, -y, +z, -z or 3 comma-"
     "separated numbers such as 0, -1, 0, got 'sideways'"),
])
def test_cameras_around_scene_refuses_bad_text_before_anything_runs(comfy_server, override, expected):
    """The text was read only as the node ran, and its error named orbit_cameras, not the node's input."""
    workflow = queue.load_api_workflow(CAMERA_FREE_API)
    for assignment in (f"Load Gaussian Scene.scene_file={comfy_server.test_folder}/scene.ply",
                       f"Style image.image={comfy_server.test_folder}/style.jpg", override):
        queue.apply_override(workflow, assignment)
    errors = _refused_before_any_work(comfy_server, workflow)
    cameras = queue.find_node(workflow, "Cameras Around Scene")
    (error,) = errors[cameras]["errors"]
    assert error["type"] == "custom_validation_failed" and f"Cameras Around Scene: {expected}" in error["details"]


def test_select_gaussians_in_mask_mode_without_a_mask_is_refused_before_anything_runs(comfy_server):
    """It was refused only as it ran, after the scene had loaded; ComfyUI leaves an unconnected optional input out of
    the prompt, so the pack's check of the prompt sees it missing."""
    workflow = queue.load_api_workflow(REGION_API)
    for assignment in (f"Load Gaussian Scene.scene_file={comfy_server.test_folder}/scene.ply",
                       f"Load Cameras.camera_source={comfy_server.test_folder}/transforms.json",
                       f"Style image.image={comfy_server.test_folder}/style.jpg", "Select Gaussians: the bear.mode=mask"):
        queue.apply_override(workflow, assignment)
    errors = _refused_before_any_work(comfy_server, workflow)
    (error,) = errors[queue.find_node(workflow, "Select Gaussians: the bear")]["errors"]
    assert error["type"] == "custom_validation_failed" and error["details"].endswith(
        "Select Gaussians: input 'cameras': mode mask needs cameras and mask connected")


def test_save_gaussian_scenes_message_is_labelled_with_the_input_it_names(comfy_server):
    """ComfyUI labels a node's VALIDATE_INPUTS message "NAME - ..." with each input that function takes (the input the
    editor outlines): Save Gaussian Scene's name filename_prefix, as its messages do; they read "node_id - ..."."""
    errors = _refused_before_any_work(comfy_server, _workflow(comfy_server, "Save Gaussian Scene.filename_prefix=../x"))
    (error,) = errors["7"]["errors"]
    assert error["extra_info"]["input_name"] == "filename_prefix", error
    assert error["details"].startswith("filename_prefix - Save Gaussian Scene: input 'filename_prefix': '../x' must "
                                       "name a file inside the output folder"), error


@pytest.mark.parametrize("input_name, value", [
    ("path", "{folder}/missing_scene.ply"),
    ("scene_file", "{folder}/missing.ply"),
])
def test_missing_scene_file_fails_validation_naming_the_file(comfy_server, input_name, value):
    shown = value.format(folder=comfy_server.test_folder)
    with pytest.raises(queue.RejectedError) as rejected:
        queue.queue_prompt(comfy_server.url, _workflow(comfy_server, f"Load Gaussian Scene.{input_name}={shown}"))
    (error,) = rejected.value.details["node_errors"]["1"]["errors"]  # once, not once per input
    assert f"input '{input_name}': scene file not found" in error["details"] and shown in error["details"], error
    assert "Put it into ComfyUI's input folder" in error["details"]


def _csgo_file_refusal(server, name: str) -> str:
    """The details of the one error ComfyUI refuses Load CSGO with, given file ``name``, feeding Preview Any."""
    prompt = {"1": {"class_type": "ArtNVGLoadCSGO", "inputs": {"csgo_name": name}},
              "2": {"class_type": "PreviewAny", "inputs": {"source": ["1", 0]}}}
    (error,) = _refused_before_any_work(server, prompt)["1"]["errors"]
    assert error["type"] == "custom_validation_failed" and error["extra_info"]["input_name"] == "csgo_name", error
    return error["details"]


def test_a_missing_model_file_is_refused_naming_it_the_folder_looked_in_and_where_to_get_it(comfy_server):
    """Load CSGO's file, missing from the start or deleted after the server listed it: ComfyUI's own answer was
    "Value not in list: csgo_name: 'csgo_4_32.bin' not in []", naming neither the folder nor where to get the
    file. The pack's message, once, labelled with the input (the editor outlines it)."""
    folder = comfy_server.input_dir.parent / "models" / "csgo"  # the folder the pack registers
    listed = f"artnvg_test_{uuid.uuid4().hex[:8]}.bin"
    for name, deleted in (("csgo_4_32.bin", False), (listed, True)):
        if deleted:
            (folder / name).write_bytes(b"")
            try:
                assert name in json.dumps(_get(comfy_server, "/object_info/ArtNVGLoadCSGO"))
            finally:
                (folder / name).unlink()
        details = _csgo_file_refusal(comfy_server, name)
        assert details.startswith(f"csgo_name - Load CSGO: input 'csgo_name': '{name}' is not in the 'csgo' model "
                                  f"folder (looked in {folder}; found "), details
        where = "from https://huggingface.co/InstantX/CSGO/blob/main/csgo_4_32.bin"
        assert (f"{where}: `hf download InstantX/CSGO csgo_4_32.bin --local-dir {folder}` saves it as {folder / name}"
                if name == "csgo_4_32.bin" else  # another name: the command saves the source's, to be renamed
                f"{where} (`hf download InstantX/CSGO csgo_4_32.bin`) and save it as {folder / name}") in details, details


def _full_workflow_refusal(server, present: list[str], edit=lambda workflow: None) -> tuple[dict, dict]:
    """(the shipped full workflow on the test inputs, changed by ``edit``; the node errors ComfyUI refuses it with as
    a whole, having run nothing) while the model files ``present`` (paths under ComfyUI's models/) are there."""
    models = server.input_dir.parent / "models"
    workflow = queue.load_api_workflow(FULL_API)
    for assignment in (f"Load Gaussian Scene.scene_file={server.test_folder}/scene.ply",
                       f"Load Cameras.camera_source={server.test_folder}/transforms.json",
                       f"Style image.image={server.test_folder}/style.jpg"):
        queue.apply_override(workflow, assignment)
    edit(workflow)
    for path in present:
        (models / path).write_bytes(b"")
    try:
        return workflow, _refused_before_any_work(server, workflow)
    finally:
        for path in present:
            (models / path).unlink()


CONTROLNET, CLIP_VISION = ("controlnet/TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors",
                           "clip_vision/CLIP-ViT-bigG-14-laion2B-39B-b160k.safetensors")


def test_a_missing_sdxl_checkpoint_is_named_by_the_nodes_it_feeds_with_its_folder_and_source(comfy_server):
    """The shipped full workflow posted over HTTP, its three other model files there and its SDXL checkpoint not:
    ComfyUI's "Value not in list: ckpt_name: 'sd_xl_base_1.0.safetensors' not in [...]" on Load Checkpoint was all
    the answer said. Apply CSGO and Sample Group, which Load Checkpoint feeds (their model, their vae), now fail
    too, each once, naming the loader, the file, the folder ComfyUI looked in and where to get the file."""
    models = comfy_server.input_dir.parent / "models"
    workflow, errors = _full_workflow_refusal(comfy_server, [CONTROLNET, CLIP_VISION, "csgo/csgo_4_32.bin"])
    checkpoint = queue.find_node(workflow, "Load Checkpoint")
    assert [e["type"] for e in errors[checkpoint]["errors"]] == ["value_not_in_list"]  # ComfyUI's own, as it was
    folder = models / "checkpoints"
    loader = (f"Load Checkpoint (node #{checkpoint}, CheckpointLoaderSimple): input 'ckpt_name': "
              f"'sd_xl_base_1.0.safetensors' is not in the 'checkpoints' model folder (looked in {folder}")
    # ... then in the other folders ComfyUI searches (0.3.64: output/checkpoints)
    source = ("; found nothing). Get the SDXL 1.0 base checkpoint from "
              "https://huggingface.co/stabilityai/stable-diffusion-xl-base-1.0: `hf download "
              f"stabilityai/stable-diffusion-xl-base-1.0 sd_xl_base_1.0.safetensors --local-dir {folder}` saves it as "
              f"{folder / 'sd_xl_base_1.0.safetensors'}")
    for title, input_name in (("Apply CSGO", "model"), ("Sample Group", "vae")):
        (error,) = errors[queue.find_node(workflow, title)]["errors"]
        assert error["type"] == "custom_validation_failed", error
        assert error["details"].startswith(f"node_id - {title}: input '{input_name}' comes from {loader}"), error
        assert error["details"].endswith(source) and "\n" not in error["details"], error
    assert set(errors) == {checkpoint, *(queue.find_node(workflow, title) for title in ("Apply CSGO", "Sample Group"))}


def test_each_loader_the_pack_follows_lists_the_folder_it_is_told_under_the_input_it_is_told(comfy_server):
    """STOCK_LOADERS against ComfyUI's own classes: a file put into each entry's folder is among the choices of the
    loader's input of that name (GET /object_info: the class, the input and the folder are ComfyUI's)."""
    from nodes.model_files import STOCK_LOADERS

    models = comfy_server.input_dir.parent / "models"
    for kind, model_files in STOCK_LOADERS.items():
        for model_file in model_files:
            suffix = ".yaml" if model_file.folder == "configs" else ".safetensors"
            path = models / model_file.folder / f"artnvg_test_{uuid.uuid4().hex[:8]}{suffix}"
            path.parent.mkdir(exist_ok=True)
            path.write_bytes(b"")
            try:
                required = _get(comfy_server, f"/object_info/{kind}")[kind]["input"]["required"]
            finally:
                path.unlink()
            assert path.name in required[model_file.name][0], (kind, model_file)


def test_missing_files_of_comfyuis_other_loaders_are_named_by_the_nodes_they_feed(comfy_server):
    """The full workflow with Apply CSGO's MODEL from Load Diffusion Model through LoraLoaderModelOnly, its
    CONTROL_NET from Load ControlNet Model (diff) on the same UNet, and Sample Group's VAE from Load VAE's
    'pixel_space' (no file: ComfyUI accepts it). The UNet and the LoRA missing, ComfyUI said "Value not in list" on
    each loader and ran the content renders; now the prompt is refused whole, and Apply CSGO names both files."""
    def other_loaders(workflow):
        apply_csgo, sample_group = (queue.find_node(workflow, title) for title in ("Apply CSGO", "Sample Group"))
        workflow.update({
            "101": {"class_type": "UNETLoader", "inputs": {"unet_name": "sdxl_unet.safetensors",
                                                           "weight_dtype": "default"}},
            "102": {"class_type": "LoraLoaderModelOnly", "inputs": {"lora_name": "ink.safetensors",
                                                                    "strength_model": 1.0, "model": ["101", 0]}},
            "103": {"class_type": "DiffControlNetLoader", "inputs": {"control_net_name": Path(CONTROLNET).name,
                                                                     "model": ["101", 0]}},
            "104": {"class_type": "VAELoader", "inputs": {"vae_name": "pixel_space"}}})
        workflow[apply_csgo]["inputs"].update(model=["102", 0], control_net=["103", 0])
        workflow[sample_group]["inputs"]["vae"] = ["104", 0]

    checkpoint = "checkpoints/sd_xl_base_1.0.safetensors"  # still the prompts' CLIP
    workflow, errors = _full_workflow_refusal(comfy_server, [CONTROLNET, CLIP_VISION, "csgo/csgo_4_32.bin", checkpoint],
                                              other_loaders)
    apply_csgo = queue.find_node(workflow, "Apply CSGO")
    assert set(errors) == {"101", "102", apply_csgo}, errors
    for loader in ("101", "102"):
        assert [e["type"] for e in errors[loader]["errors"]] == ["value_not_in_list"], errors  # ComfyUI's own
    (error,) = errors[apply_csgo]["errors"]
    lora, unet = error["details"].split("\n")
    models = comfy_server.input_dir.parent / "models"
    assert lora.startswith("node_id - Apply CSGO: input 'model' comes from LoraLoaderModelOnly (node #102, "
                           "LoraLoaderModelOnly): input 'lora_name': 'ink.safetensors' is not in the 'loras' model "
                           f"folder (looked in {models / 'loras'}"), lora
    assert lora.endswith("(`hf download nerijs/pixel-art-xl pixel-art-xl.safetensors`)"), lora
    assert unet.startswith("Apply CSGO: inputs 'model', 'control_net' come from UNETLoader (node #101, UNETLoader): "
                           "input 'unet_name': 'sdxl_unet.safetensors' is not in the 'diffusion_models' model folder "
                           f"(looked in {models / 'unet'}, {models / 'diffusion_models'}"), unet
    assert unet.endswith(f"as {models / 'unet' / 'sdxl_unet.safetensors'}, e.g. the SDXL 1.0 base's UNet (diffusers "
                         "layout, fp16) from https://huggingface.co/stabilityai/stable-diffusion-xl-base-1.0/blob/main/"
                         "unet/diffusion_pytorch_model.fp16.safetensors (`hf download stabilityai/stable-diffusion-xl-"
                         "base-1.0 unet/diffusion_pytorch_model.fp16.safetensors`)"), unet


def test_unreadable_scene_file_fails_execution_naming_the_input_and_file(comfy_server):
    broken = comfy_server.input_dir / comfy_server.test_folder / "broken.ply"
    broken.write_text("this is not a PLY file\n")
    entry, _ = _run(comfy_server, _workflow(
        comfy_server, f"Load Gaussian Scene.scene_file={comfy_server.test_folder}/broken.ply"))
    summary = queue.run_summary(entry)
    assert summary["status"] == "error"
    assert "Load Gaussian Scene: input 'scene_file'" in summary["error"] and str(broken) in summary["error"]


def test_a_folder_as_the_scene_file_fails_validation_naming_it_as_a_folder(comfy_server):
    with pytest.raises(queue.RejectedError) as rejected:
        queue.queue_prompt(comfy_server.url, _workflow(comfy_server, f"Load Gaussian Scene.path={comfy_server.test_folder}"))
    (error,) = rejected.value.details["node_errors"]["1"]["errors"]
    folder = comfy_server.input_dir / comfy_server.test_folder
    assert (f"input 'path': {folder}: scene file is a folder, not a regular file; expected .ply (INRIA 3DGS or "
            "compressed PLY)") in error["details"], error


def test_a_style_image_the_command_line_refuses_is_refused_before_or_as_finetune_gaussians_starts(comfy_server):
    """Straight from Load Image: the prompt is refused before anything runs; through another node (its size
    known only as the graph runs): Finetune Gaussians stops at its start. Without either check the run succeeded."""
    from PIL import Image

    Image.new("RGB", (20000, 2), (200, 30, 30)).save(comfy_server.input_dir / comfy_server.test_folder / "line.png")
    workflow = _workflow(comfy_server, f"Style image.image={comfy_server.test_folder}/line.png")
    rule = "image size: 20000x2 pixels; a style image may be at most 32 times as long as it is wide"
    with pytest.raises(queue.RejectedError) as rejected:
        queue.queue_prompt(comfy_server.url, workflow)
    (error,) = rejected.value.details["node_errors"][FINETUNE]["errors"]
    assert f"Finetune Gaussians: input 'style_image': {rule}" in error["details"], error
    workflow["99"] = {"class_type": "ImageInvert", "inputs": {"image": workflow[FINETUNE]["inputs"]["style_image"]}}
    workflow[FINETUNE]["inputs"]["style_image"] = ["99", 0]
    summary = queue.run_summary(_run(comfy_server, workflow)[0])
    assert summary["status"] == "error" and f"Finetune Gaussians: input 'style_image': {rule}" in summary["error"]
