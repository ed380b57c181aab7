"""Each UI workflow loads in ComfyUI's graph editor (headless Chromium) with every node known and every link whole.

Runs only when ARTNVG_COMFYUI_ROOT is set (see conftest.py) and a ``chromium`` binary is on
PATH (Debian: ``apt-get install chromium``). Drives the page over the DevTools protocol,
loads each workflow with the editor's own ``app.loadGraphData``, checks node types, links
and widget values, checks that the editor's own API export equals the shipped API file,
and keeps a screenshot per workflow in ROOT/artnvg_screenshots/.
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest
from ws_client import WebSocket

REPO = Path(__file__).resolve().parents[2]
UI_WORKFLOWS = sorted(p for p in (REPO / "workflows").glob("*.json") if not p.stem.endswith("_api"))
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

INSPECT = """
(async () => {
  const workflow = %s;
  await app.loadGraphData(workflow, true, true, "artnvg-test");
  await new Promise((done) => setTimeout(done, 1000));
  const graph = app.graph;
  const missing = workflow.nodes.map((n) => n.type).filter((t) => !LiteGraph.registered_node_types[t]);
  const problems = [];
  const links = graph.links instanceof Map ? [...graph.links.values()] : Object.values(graph.links || {});
  for (const link of links) {
    const origin = graph.getNodeById(link.origin_id), target = graph.getNodeById(link.target_id);
    if (!origin || !target) { problems.push(`link ${link.id}: missing end`); continue; }
    const output = origin.outputs[link.origin_slot], input = target.inputs[link.target_slot];
    if (!output || !input || input.link !== link.id || output.type !== input.type || input.type !== link.type)
      problems.push(`link ${link.id}: ${origin.type}.${output && output.name} -> ${target.type}.${input && input.name}`);
  }
  const widgets = {};
  for (const node of graph.serialize().nodes) widgets[node.id] = node.widgets_values || [];
  const dialogs = [...document.querySelectorAll(".p-dialog")].map((d) => d.innerText);
  const prompt = await app.graphToPrompt();
  return {missing, problems, links: links.length, widgets, dialogs, output: prompt.output};
})()
"""


class DevTools:
    """Calls over one page's DevTools websocket; events are kept in ``events``."""

    def __init__(self, url: str):
        self.socket = WebSocket(url, timeout=120)
        self.next_id = 0
        self.events = []

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.socket.send_json({"id": self.next_id, "method": method, "params": params})
        while True:
            message = self.socket.receive_json()
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]
            self.events.append(message)

    def evaluate(self, expression: str):
        result = self.call("Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")


def _json(url: str):
    with urllib.request.urlopen(url, timeout=10) as response:
        return json.loads(response.read())


@pytest.fixture(scope="module")
def editor(comfy_server, tmp_path_factory):
    if CHROMIUM is None:
        pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")
    port = 9300 + int(time.time()) % 500
    browser = subprocess.Popen(
        [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
         f"--remote-debugging-port={port}", f"--user-data-dir={tmp_path_factory.mktemp('chromium')}",
         "--window-size=1800,1000", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        for _ in range(300):
            try:
                pages = [t for t in _json(f"http://127.0.0.1:{port}/json/list") if t["type"] == "page"]
                if pages:
                    break
            except OSError:
                pass
            time.sleep(0.2)
        else:
            pytest.fail("chromium did not open its DevTools port")
        tools = DevTools(pages[0]["webSocketDebuggerUrl"])
        tools.call("Runtime.enable")
        tools.call("Page.enable")
        tools.call("Page.navigate", url=comfy_server.url)
        ready = "Boolean(window.app && app.graph && LiteGraph.registered_node_types['ArtNVGLoadGaussianScene'])"
        for _ in range(240):
            if tools.evaluate(ready):
                break
            time.sleep(0.5)
        else:
            pytest.fail("the graph editor did not finish loading with the ArtNVG nodes")
        yield tools
        tools.socket.close()
    finally:
        browser.terminate()
        browser.wait(timeout=30)


@pytest.mark.parametrize("path", UI_WORKFLOWS, ids=lambda p: p.stem)
def test_ui_workflow_loads_in_the_graph_editor(editor, comfy_server, path):
    workflow = json.loads(path.read_text())
    first_event = len(editor.events)
    report = editor.evaluate(INSPECT % json.dumps(workflow))
    exceptions = [e for e in editor.events[first_event:] if e.get("method") == "Runtime.exceptionThrown"]

    screenshots = comfy_server.root / "artnvg_screenshots"
    screenshots.mkdir(exist_ok=True)
    image = base64.b64decode(editor.call("Page.captureScreenshot", format="png")["data"])
    (screenshots / f"{path.stem}.png").write_bytes(image)

    assert report["missing"] == [], report["missing"]
    assert report["problems"] == [] and report["links"] == len(workflow["links"]), report["problems"]
    assert not any("missing" in text.lower() for text in report["dialogs"]), report["dialogs"]
    assert exceptions == [], exceptions
    for node in workflow["nodes"]:
        assert report["widgets"][str(node["id"])] == node.get("widgets_values", []), node["type"]
    api = json.loads(path.with_name(f"{path.stem}_api.json").read_text())
    assert report["output"] == api  # the editor's own API export is the shipped API file
    assert image[:8] == b"\x89PNG\r\n\x1a\n" and len(image) > 20_000
