"""The examples of docs/comfyui.md's HTTP API section run as printed against a real ComfyUI server.

Each ```bash block of that section runs with bash in the repository's root, the example server's
address (http://127.0.0.1:8188) replaced by the test server's; each must exit 0 and its prompt must
succeed. Runs only when ARTNVG_COMFYUI_ROOT is set (see conftest.py).
"""

from __future__ import annotations

import json
import re
import subprocess
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_SERVER = "http://127.0.0.1:8188"


def http_api_examples() -> list[str]:
    text = (REPO / "docs" / "comfyui.md").read_text()
    section = text.split("\n## HTTP API\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^```bash\n(.*?)^```", section, flags=re.S | re.M)


def _history(server) -> dict:
    with urllib.request.urlopen(f"{server.url}/history", timeout=30) as response:
        return json.loads(response.read())


def _queue_empty(server) -> bool:
    with urllib.request.urlopen(f"{server.url}/queue", timeout=30) as response:
        queue = json.loads(response.read())
    return not queue["queue_running"] and not queue["queue_pending"]


def test_the_http_api_examples_run_as_printed(comfy_server):
    examples = http_api_examples()
    assert len(examples) == 2 and all(EXAMPLE_SERVER in example for example in examples)
    before = set(_history(comfy_server))
    for example in examples:
        done = subprocess.run(["bash", "-c", example.replace(EXAMPLE_SERVER, comfy_server.url)], cwd=REPO,
                              capture_output=True, text=True, timeout=1800)
        assert done.returncode == 0, done.stderr
        assert done.stdout.startswith(("queued ", "success")), done.stdout
    deadline = time.monotonic() + 1800
    while not _queue_empty(comfy_server):
        assert time.monotonic() < deadline, "the examples' prompts did not finish"
        time.sleep(1)
    runs = [entry for prompt_id, entry in _history(comfy_server).items() if prompt_id not in before]
    assert len(runs) == 2 and all(entry["status"]["status_str"] == "success" for entry in runs)
    saved = sorted(item["subfolder"] + "/" + item["filename"].rsplit("_", 1)[0]
                   for entry in runs for item in entry["outputs"]["7"]["scenes"])
    assert saved == ["artnvg/from_python", "artnvg/my_first"]
