"""The command line's own output: progress while loading and rendering (evaluate: tests/test_metrics_report.py)."""

import re

from artnvg_core.__main__ import main
from artnvg_core.formats import load_scene, write_ply
from artnvg_core.stylize import DemoInputs


def test_render_reports_loading_and_each_view(tmp_path, capsys):
    demo = DemoInputs()
    scene = tmp_path / "scene.ply"
    write_ply(load_scene(demo.scene).select(slice(0, None, 40)), scene)  # 1,000 Gaussians: quick renders
    assert main(["render", str(scene), "--cameras", str(demo.cameras), "--out", str(tmp_path),
                 "--views", "0,5,9", "--scale", "0.1", "--device", "cpu"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert re.fullmatch(rf"loading {re.escape(str(scene))} \(0\.1 MiB\)", lines[0])
    assert lines[1].startswith("loaded 1,000 Gaussians (SH degree 1) in ")
    assert lines[2].startswith("rendering 3 views at ")
    views = [line for line in lines if line.startswith("[")]
    assert [line.split("]")[0] + "]" for line in views] == ["[1/3]", "[2/3]", "[3/3]"]
    assert len(list(tmp_path.glob("*.png"))) == 3
