"""What a ComfyUI user waits for: a shipped API workflow queued on a running ComfyUI server, run after run.

    cd bench && python comfyui_wall.py --server http://127.0.0.1:8188 \
        --workflow ../workflows_api/ArtNVG_1_quick_start_NNFM_no_model_downloads_api.json \
        [--runs 2] [--vary "Finetune Gaussians.seed"] [--set NODE.INPUT=VALUE ...] [--json OUT.json]

Start the server first as a user does (``python main.py``, ``--cpu`` without a GPU) with this pack
installed; the first run then meets what a fresh server meets (the pack's imports, model and kernel
loading on first use). Each run queues the workflow over HTTP (``POST /prompt``, as
``workflows_api/queue_workflow.py`` does; ``--set`` overrides inputs the same way) and follows the
server's websocket until the run ends. ComfyUI reuses a node's output while its inputs are
unchanged, so run ``i`` sets the ``--vary`` input to ``i`` (by default the finetune's seed): later runs
execute only the nodes downstream of it, as when a user changes a setting and queues again.

Per run: the wall time from queueing to the end of the run, seen from here; the wait before the
server started it; the seconds of each node that executed (from the websocket's "executing" message
of the node to the next one, timed here as they arrive); the nodes ComfyUI served from its cache.
Prints a table; ``--json`` keeps every run's node times and the server's messages.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shlex
import sys
import time
import uuid
from pathlib import Path

from common import print_table

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "integration"))
from ws_client import WebSocket  # noqa: E402  (a standard-library websocket client)

_spec = importlib.util.spec_from_file_location("queue_workflow", REPO / "workflows_api" / "queue_workflow.py")
queue = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(queue)

ENDS = ("execution_success", "execution_error", "execution_interrupted")


def run_once(server: str, workflow: dict, timeout: float) -> dict:
    """Queue ``workflow`` and follow it to its end: wall and waiting seconds, seconds per executed node
    (in execution order) and when each ran ([start, end] seconds after queueing), the nodes' progress
    messages ([node, value, max, seconds after queueing]), the cached nodes, and how it ended."""
    client_id = uuid.uuid4().hex
    socket = WebSocket(f"{server.replace('http', 'ws', 1)}/ws?clientId={client_id}", timeout=timeout)
    try:
        queued = time.perf_counter()
        prompt_id = queue.queue_prompt(server, workflow, client_id)
        started, current, nodes, spans, progress, cached, end = None, None, {}, {}, [], [], None
        while end is None:
            message = socket.receive_json()
            data, now = message.get("data", {}), time.perf_counter()
            if data.get("prompt_id") != prompt_id:
                continue
            kind = message["type"]
            if kind == "execution_start":
                started = now
            elif kind == "execution_cached":
                cached = list(data.get("nodes", []))
            elif kind == "progress":
                progress.append([data.get("node"), data["value"], data["max"], now - queued])
            if current is not None and (kind == "executing" or kind in ENDS):
                node, since = current
                nodes[node] = nodes.get(node, 0.0) + now - since
                spans[node] = [since - queued, now - queued]
                current = None
            if kind == "executing" and data.get("node") is not None:
                current = (data["node"], now)
            if kind in ENDS:
                end = kind
        wall = time.perf_counter() - queued
    finally:
        socket.close()
    return {"wall": wall, "waiting": (started or queued) - queued, "nodes": nodes, "spans": spans,
            "progress": progress, "cached": cached, "end": end.removeprefix("execution_")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default="http://127.0.0.1:8188")
    parser.add_argument("--workflow", required=True, help="an API-format workflow (workflows_api/)")
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--vary", default="Finetune Gaussians.seed", help="NODE.INPUT set to the run's number")
    parser.add_argument("--set", action="append", default=[], metavar="NODE.INPUT=VALUE")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds a run may take")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    workflow = queue.load_api_workflow(args.workflow)
    for assignment in args.set:
        queue.apply_override(workflow, assignment)
    titles = {node: spec.get("_meta", {}).get("title", spec["class_type"]) for node, spec in workflow.items()}

    runs = []
    for number in range(1, args.runs + 1):
        queue.apply_override(workflow, f"{args.vary}={number}")
        runs.append(run_once(args.server, workflow, args.timeout))
        print(json.dumps({key: value for key, value in runs[-1].items() if key != "progress"}), flush=True)
        if args.json:
            args.json.write_text(json.dumps({"workflow": args.workflow, "runs": runs}, indent=1))
    shown = [node for node in workflow if any(node in run["nodes"] for run in runs)]
    def seconds(value: float | None) -> str:
        return "" if value is None else f"{value:.2f}"

    rows = [[number, run["end"], seconds(run["wall"]), seconds(run["waiting"]),
             *[seconds(run["nodes"].get(node)) for node in shown], len(run["cached"])]
            for number, run in enumerate(runs, 1)]
    print_table(f"{Path(args.workflow).name} on {args.server} (seconds)",
                ["run", "end", "wall", "waiting", *[titles[node] for node in shown], "cached nodes"], rows,
                "python " + shlex.join(sys.argv))


if __name__ == "__main__":
    main()
