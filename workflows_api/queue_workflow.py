#!/usr/bin/env python3
"""Queue an API-format ComfyUI workflow on a running server, wait for it and report its outputs.

Standard library only. Usage::

    python workflows_api/queue_workflow.py workflows_api/ArtNVG_1_quick_start_NNFM_no_model_downloads_api.json \\
        --server http://127.0.0.1:8188 \\
        --set "Finetune Gaussians.iterations=24" \\
        --set "Save Gaussian Scene.filename_prefix=artnvg/my_first"

``--set NODE.INPUT=VALUE`` overrides one input before queueing. NODE is a node id of the
API file or a node's title (``_meta.title``, e.g. ``Finetune Gaussians``); a name that is the
title of several nodes, or the id of one and the title of another, is refused as ambiguous.
INPUT must be one of the node's inputs in the file (an unknown node or input is refused with
the list of valid ones). VALUE is read as JSON when it parses (numbers, true/false, lists) and
as a plain string otherwise. Linked inputs (``["node", slot]``) cannot be overridden.

Exit status: 0 the run succeeded; 1 it failed or was interrupted; 2 the server rejected
the workflow or any of its nodes (validation errors are printed per node and input; a
workflow the server would run only in part is withdrawn from its queue), or the file or an
override is bad; 3 the server could not be reached or the run did not finish within
``--timeout`` seconds: then the prompt is taken off the server, deleted from its queue if it has not
started, else interrupted (only when it is the prompt running), and the message says which.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path


class WorkflowError(ValueError):
    """The workflow file or an override is not usable (exit status 2)."""


class ServerError(RuntimeError):
    """The server could not be reached, or did not finish in time (exit status 3)."""


class RejectedError(RuntimeError):
    """The server refused the workflow; ``details`` is its JSON answer (exit status 2)."""

    def __init__(self, message: str, details: dict):
        super().__init__(message)
        self.details = details


# --------------------------------------------------------------------------- workflow file


def load_api_workflow(path: str | Path) -> dict:
    """The API-format workflow in ``path``: ``{node_id: {"class_type": ..., "inputs": {...}}}``."""
    path = Path(path)
    try:
        workflow = json.loads(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise WorkflowError(f"{path}: cannot read the workflow ({error})") from error
    except json.JSONDecodeError as error:
        raise WorkflowError(f"{path}: not valid JSON ({error})") from error
    if isinstance(workflow, dict) and "nodes" in workflow and "links" in workflow:
        raise WorkflowError(f"{path}: this is a UI-format workflow; queue the API-format file (*_api.json)")
    if not isinstance(workflow, dict) or not all(
        isinstance(node, dict) and "class_type" in node and isinstance(node.get("inputs"), dict)
        for node in workflow.values()
    ):
        raise WorkflowError(f"{path}: expected an API-format workflow {{node_id: {{class_type, inputs}}}}")
    return workflow


def parse_value(text: str):
    """JSON value of ``text`` when it parses, else ``text`` itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _node_name(workflow: dict, node_id: str) -> str:
    node = workflow.get(node_id, {})
    return f"{node_id} ({node.get('_meta', {}).get('title') or node.get('class_type', '?')})"


def find_node(workflow: dict, key: str) -> str:
    """The id of the node called ``key``: a node id or a node title (``_meta.title``), naming one node only."""
    matches = {node_id for node_id, node in workflow.items()
               if node_id == key or node.get("_meta", {}).get("title") == key}
    if len(matches) == 1:
        return matches.pop()
    if matches:
        named = ", ".join(_node_name(workflow, node_id) for node_id in sorted(matches))
        raise WorkflowError(f"--set: node '{key}' is ambiguous: it names {named}; use the node id")
    known = ", ".join(_node_name(workflow, node_id) for node_id in workflow)
    raise WorkflowError(f"--set: node '{key}' matches no node id or title; nodes: {known}")


def apply_override(workflow: dict, assignment: str) -> None:
    """Apply one ``NODE.INPUT=VALUE`` override to ``workflow`` in place."""
    target, sep, value = assignment.partition("=")
    key, dot, input_name = target.rpartition(".")
    if not sep or not dot or not key or not input_name:
        raise WorkflowError(f"--set: expected NODE.INPUT=VALUE, got {assignment!r}")
    node_id = find_node(workflow, key)
    inputs = workflow[node_id]["inputs"]
    if input_name not in inputs:
        values = ", ".join(name for name, current in inputs.items() if not isinstance(current, list)) or "none"
        raise WorkflowError(f"--set: node {_node_name(workflow, node_id)} has no input '{input_name}'; "
                            f"its inputs that take a value: {values}")
    if isinstance(inputs[input_name], list):
        raise WorkflowError(f"--set: input '{input_name}' of node {_node_name(workflow, node_id)} is a link, not a value")
    inputs[input_name] = parse_value(value)


# --------------------------------------------------------------------------- server


def _request(server: str, path: str, payload: dict | None = None, timeout: float = 30) -> dict:
    data = None if payload is None else json.dumps(payload).encode("utf-8")
    request = urllib.request.Request(server.rstrip("/") + path, data=data,
                                     headers={"Content-Type": "application/json"} if data else {})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return json.loads(response.read() or b"{}")
    except urllib.error.HTTPError as error:
        body = error.read()
        try:
            details = json.loads(body)
        except json.JSONDecodeError:
            details = {"error": {"message": body.decode("utf-8", "replace")}}
        raise RejectedError(f"{server}{path}: HTTP {error.code}", details) from error
    except (urllib.error.URLError, OSError) as error:
        raise ServerError(f"{server}{path}: cannot reach the server ({error})") from error


def queue_prompt(server: str, workflow: dict, client_id: str | None = None) -> str:
    """POST the workflow to ``/prompt``; returns its prompt id.

    Raises RejectedError when the server refuses it, and also when it queues it with ``node_errors``
    (ComfyUI then runs only the outputs that validated): such a prompt is first withdrawn from the
    queue, or interrupted if it has started. ``client_id``: the id of a websocket connection
    (``/ws?clientId=...``) that should receive the run's progress messages.
    """
    answer = _request(server, "/prompt", {"prompt": workflow, "client_id": client_id or uuid.uuid4().hex})
    if answer.get("node_errors"):
        withdraw(server, answer["prompt_id"])
        raise RejectedError(f"{server}/prompt: nodes failed validation", answer)
    return answer["prompt_id"]


def interrupt(server: str) -> None:
    """Ask the server to stop the running prompt (``POST /interrupt``)."""
    _request(server, "/interrupt", {})


def _queued_ids(queue: dict, key: str) -> set[str]:
    """The prompt ids of ``queue[key]`` (``/queue``'s ``queue_running`` or ``queue_pending``: lists of
    ``[number, prompt id, prompt, extra data, outputs]``)."""
    return {str(item[1]) for item in queue.get(key) or [] if isinstance(item, list) and len(item) > 1}


def withdraw(server: str, prompt_id: str) -> str | None:
    """Take ``prompt_id`` off the server: delete it from the queue (``POST /queue {"delete": [id]}``, which leaves a
    running prompt alone), then, if it is the prompt running (``GET /queue``), interrupt it (``POST /interrupt``
    naming it: another client's prompt is never stopped). Returns what was done, for a message ("interrupted it",
    "deleted it from the queue before it started"), or None when it was neither queued nor running (it had ended)."""
    pending = prompt_id in _queued_ids(_request(server, "/queue"), "queue_pending")
    _request(server, "/queue", {"delete": [prompt_id]})
    if prompt_id in _queued_ids(_request(server, "/queue"), "queue_running"):  # it may have started meanwhile
        _request(server, "/interrupt", {"prompt_id": prompt_id})
        return "interrupted it"
    return "deleted it from the queue before it started" if pending else None


def _finished(server: str, prompt_id: str) -> dict | None:
    """The history entry of ``prompt_id`` once it has ended, else None."""
    entry = _request(server, f"/history/{prompt_id}").get(prompt_id)
    return entry if entry is not None and (entry.get("status") or {}).get("completed") is not None else None


def wait_for(server: str, prompt_id: str, timeout: float, poll: float = 0.5) -> dict:
    """The history entry of ``prompt_id`` once it has ended (``status``, ``outputs``). When ``timeout`` seconds pass
    first, the prompt is withdrawn (:func:`withdraw`: it would go on running on the server) and ServerError says
    so (unless it ended meanwhile)."""
    deadline = time.monotonic() + timeout
    while True:
        entry = _finished(server, prompt_id)
        if entry is not None:
            return entry
        if time.monotonic() > deadline:
            done = withdraw(server, prompt_id)
            entry = _finished(server, prompt_id) if done is None else None
            if entry is not None:
                return entry
            raise ServerError(f"prompt {prompt_id} did not finish within {timeout:g} s; "
                              f"{done or 'it is no longer on the server'}")
        time.sleep(poll)


# --------------------------------------------------------------------------- report


def _run_nodes(entry: dict) -> dict:
    """The nodes of the prompt a history entry keeps (``entry["prompt"]``: number, id, prompt, ...); {} without."""
    prompt = entry.get("prompt")
    nodes = prompt[2] if isinstance(prompt, list) and len(prompt) > 2 else None
    return nodes if isinstance(nodes, dict) else {}


def run_summary(entry: dict) -> dict:
    """``{"status": "success"|"error"|"interrupted", "error": str|None, "outputs": [...]}`` of a history entry.

    Each output is ``{"node": id, "title": "Save Gaussian Scene", "kind": "images"|"scenes"|..., "file":
    "subfolder/name", "type": "output"}``; nodes are named by their titles in the prompt the entry keeps (else
    their types).
    """
    nodes = _run_nodes(entry)

    def named(node_id, node_type=None) -> str:
        return _node_name({str(node_id): nodes.get(str(node_id)) or {"class_type": node_type}}, str(node_id))

    status = entry.get("status") or {}
    messages = {event: data for event, data in status.get("messages", [])}
    error = None
    state = "success" if status.get("status_str") == "success" else "error"
    if "execution_interrupted" in messages:
        state = "interrupted"
        data = messages["execution_interrupted"]
        error = f"in node {named(data.get('node_id'), data.get('node_type'))}"
    elif "execution_error" in messages:
        data = messages["execution_error"]
        kind = str(data.get("exception_type")).rpartition(".")[2]  # a pack's module path names its folder: left out
        error = f"node {named(data.get('node_id'), data.get('node_type'))}: {kind}: {data.get('exception_message', '').strip()}"
    outputs = []
    for node_id, node_outputs in (entry.get("outputs") or {}).items():
        for kind, items in node_outputs.items():
            for item in items if isinstance(items, list) else []:
                if isinstance(item, dict) and "filename" in item:
                    name = "/".join(part for part in (item.get("subfolder", ""), item["filename"]) if part)
                    outputs.append({"node": node_id, "title": (nodes.get(node_id) or {}).get("_meta", {}).get("title"),
                                    "kind": kind, "file": name, "type": item.get("type", "")})
    return {"status": state, "error": error, "outputs": outputs}


def summary_text(summary: dict) -> str:
    """A few lines for people: the status (and error), then one line per node and kind of output with the
    number of files and the first one (a workflow's previews can hold dozens of frames)."""
    lines = [f"{summary['status']}" + (f": {summary['error']}" if summary["error"] else "")]
    groups: dict[tuple[str, str, str], list[str]] = {}
    for output in summary["outputs"]:
        node = output["node"] + (f" ({output['title']})" if output.get("title") else "")
        groups.setdefault((node, output["kind"], output["type"]), []).append(output["file"])
    for (node, kind, place), files in groups.items():
        more = f" (+{len(files) - 1} more)" if len(files) > 1 else ""
        lines.append(f"  node {node} {kind}: {files[0]}{more} [{place}]")
    return "\n".join(lines)


def rejection_text(details: dict, workflow: dict) -> str:
    """The server's validation errors, one line per node and input: ``node 6 (Finetune Gaussians), input
    'iterations': Value smaller than min: iterations -1 < 1``. A node's own check (``custom_validation_failed``,
    whose details ComfyUI prefixes with the name of its check's argument, ``NAME - ``) is given by its message
    alone, the input named only where it is one of the node's inputs in ``workflow`` (a pack may check through
    a hidden input)."""
    lines = []
    error = details.get("error")
    if isinstance(error, dict):
        lines.append(f"{error.get('message', '')} {error.get('details', '')}".strip())
    for node_id, node in (details.get("node_errors") or {}).items():
        for item in node.get("errors", []):
            input_name = (item.get("extra_info") or {}).get("input_name")
            text = f"{item.get('message')}: {item.get('details')}"
            if item.get("type") == "custom_validation_failed":
                text = str(item.get("details")).removeprefix(f"{input_name} - ")
                if input_name not in workflow.get(node_id, {}).get("inputs", {}):
                    input_name = None
            where = f", input '{input_name}'" if input_name else ""
            lines.append(f"node {_node_name(workflow, node_id)}{where}: {text}")
    return "\n".join(lines) or json.dumps(details)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workflow", help="API-format workflow JSON (File > Export (API) in ComfyUI)")
    parser.add_argument("--server", default="http://127.0.0.1:8188", help="ComfyUI address (default %(default)s)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="NODE.INPUT=VALUE",
                        help="override an input; NODE is an id or a title; repeatable")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds to wait for the run (default %(default)s); "
                        "then the prompt is deleted from the queue, or interrupted if it is running")
    parser.add_argument("--no-wait", action="store_true", help="print the prompt id and return at once")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    args = parser.parse_args(argv)
    try:
        workflow = load_api_workflow(args.workflow)
        for assignment in args.overrides:
            apply_override(workflow, assignment)
        prompt_id = queue_prompt(args.server, workflow)
        if args.no_wait:
            print(prompt_id)
            return 0
        print(f"queued {prompt_id}; waiting...", file=sys.stderr)
        summary = {"prompt_id": prompt_id, **run_summary(wait_for(args.server, prompt_id, args.timeout))}
    except WorkflowError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except RejectedError as error:
        print(f"error: the server rejected the workflow:\n{rejection_text(error.details, workflow)}", file=sys.stderr)
        return 2
    except ServerError as error:
        print(f"error: {error}", file=sys.stderr)
        return 3
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(summary_text(summary))
    return 0 if summary["status"] == "success" else 1


if __name__ == "__main__":
    sys.exit(main())
