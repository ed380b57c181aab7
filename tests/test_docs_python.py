"""docs/command_line.md's "From Python" example runs as printed, on a small scene written under its file names
(and nothing else: its last line once read a scene.spz that only the test had written)."""

import json
import re
from pathlib import Path

import torch

from artnvg_core.formats import load_scene, write_ply
from artnvg_core.stylize import DemoInputs

DOC = Path(__file__).resolve().parents[1] / "docs" / "command_line.md"


def test_the_from_python_example_runs_as_printed(tmp_path, monkeypatch):
    section = DOC.read_text().split("\n## From Python\n", 1)[1].split("\n## ", 1)[0]
    (example,) = re.findall(r"^```python\n(.*?)^```", section, flags=re.S | re.M)
    assert "iterations=300" in example
    demo = DemoInputs()
    scene = load_scene(demo.scene).select(slice(0, None, 40))  # 1,000 Gaussians
    write_ply(scene, tmp_path / "scene.ply")
    capture = json.loads(demo.cameras.read_text())
    (tmp_path / "transforms.json").write_text(json.dumps({**capture, "frames": capture["frames"][:3]}))
    (tmp_path / "style.jpg").write_bytes(demo.style.read_bytes())
    monkeypatch.chdir(tmp_path)
    names = {}
    exec(compile(example.replace("iterations=300", "iterations=2"), str(DOC), "exec"), names)  # noqa: S102
    cameras = names["cameras"]
    assert names["images"].shape == (3, cameras.height, cameras.width, 3)
    assert names["images"].dtype == torch.float32 and len(names["stylized"]) == len(names["scene"]) == 1000
    assert load_scene(tmp_path / "stylized.spz").sh.shape == names["stylized"].sh.shape == (1000, 4, 3)
