"""ComfyUI reads the pack's registry metadata (pyproject.toml's [project] and [tool.comfy]) with its own
parser, ``comfy_config``, whose types the Comfy Registry's command line (comfy-cli) keeps in step with,
and finds there what pyproject.toml says. Runs when ARTNVG_COMFYUI_ROOT is set (see conftest.py)."""

import json
import subprocess
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

REPO = Path(__file__).resolve().parents[2]
READ = """
import json, sys
from comfy_config import config_parser
config = config_parser.extract_node_configuration(sys.argv[1])
print(json.dumps({"project": config.project.model_dump(), "comfy": config.tool_comfy.model_dump()}))
"""


def test_comfyuis_parser_reads_the_registry_metadata_as_written(comfy_checkout):
    checkout, python = comfy_checkout
    run = subprocess.run([python, "-c", READ, str(REPO)], cwd=checkout, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    read = json.loads(run.stdout.splitlines()[-1])
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    project, comfy = pyproject["project"], pyproject["tool"]["comfy"]
    assert (read["project"]["name"], read["project"]["version"]) == (project["name"], project["version"])
    assert read["project"]["license"]["text"] == project["license"]
    assert read["project"]["urls"]["repository"] == project["urls"]["Repository"]
    assert read["project"]["supported_os"] == [c.removeprefix("Operating System :: ") for c in project["classifiers"]]
    assert read["project"]["supported_accelerators"] == []
    assert read["project"]["supported_comfyui_version"] == comfy["requires-comfyui"]
    assert (read["comfy"]["publisher_id"], read["comfy"]["display_name"]) == (comfy["PublisherId"], comfy["DisplayName"])
