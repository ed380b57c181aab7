"""The loaders' file checks, run on the whole prompt before ComfyUI validates it: a graph whose files
are missing runs not at all, and each loader's message comes once.

ComfyUI validates each output node on its own and runs every output that passes, so a loader with a
missing file used to stop only the outputs downstream of it while the rest ran and reported success.
And it repeats a ``VALIDATE_INPUTS`` message once per input that function declares.

So the pack registers :func:`check_prompt` as an on-prompt handler. For each node of the prompt whose
class has ``check_values(**inputs) -> str | None`` (every node of the pack: its values of their declared
types, within their declared ranges and choices, read as ComfyUI will pass them: ``"nan"`` and
``{"__value__": NaN}`` are a FLOAT NaN), ``check_links(linked input names, **inputs) -> str | None`` (every node of
the pack: the optional inputs a value needs connected), ``check_views(camera count of a CAMERAS input, **inputs)``
(every node of the pack: view indices past the last camera, where a node such as Load Cameras gives the count before
the graph runs: ``camera_count``) or ``check_files(**inputs) -> str | None`` (the loaders, given
the values as ComfyUI passes them), it runs those checks on the node's values, and ``check_images`` on the
size of each image a stock Load Image feeds it (every node of the pack: a style image's shape); a message
is kept under (prompt id, node id). When any node fails, the prompt's execution targets become the outputs
that depend on a failing node, so validation fails as a whole: ComfyUI refuses the prompt (HTTP 400) and
the editor outlines the nodes and lists their messages; nothing runs. (Without this, a Finetune Gaussians
with iterations -1 failed validation while every output not fed by it ran.) A problem ComfyUI reports
itself (a value out of its range or choices, or one it cannot convert) is not kept: its message would
come twice.
Every node of the pack answers ComfyUI's validation with the kept message (``ArtNVGNode.VALIDATE_INPUTS``,
:func:`check_result`), through one input alone (the hidden input :data:`CHECK_INPUT`, or a model loader's
file input), so ComfyUI shows the message once and still checks every other input's range and choices. The
loaders' file lists (input files, and model files: Load CSGO's) are declared as ``("COMBO", {"options": ...})``,
which ComfyUI does not compare with the value itself: the check's message says more (the folders looked in,
where the file belongs, where to get it).
Without the handler (a prompt validated some other way) the loaders raise the same message when they run.

ComfyUI's own model loaders (:data:`~.model_files.STOCK_LOADERS`) list their folder's files, and ComfyUI's own
check names a file that is not there ("Value not in list"), neither where it looked nor where to get it; the
handler counts such a node as failing too, so that a graph missing a model file runs not at all either, and
gives each node of the pack that such a loader feeds (straight, or through the links of other such loaders: a LoRA
loader's, a diff ControlNet loader's) one message naming its input, the loader, the file, the folders looked in and
where to get it (:func:`_missing_models`). A name the loader lists that is no file (Load VAE's 'pixel_space') is not
missing: ComfyUI accepts it.
"""

from __future__ import annotations

import functools
import uuid
from collections import OrderedDict
from collections.abc import Mapping

from artnvg_core.images import image_size

from .comfy_bridge import comfy_module, load_image_path
from .input_files import outside_folders
from .model_files import STOCK_LOADERS

CHECK_INPUT = "node_id"  # every node's hidden input (ComfyUI's UNIQUE_ID), which its VALIDATE_INPUTS takes
REFUSED = (TypeError, ValueError, OverflowError)  # what comfyui_value raises for a value ComfyUI refuses itself
_KEPT_PROMPTS = 32
_results: OrderedDict[str, dict[str, str]] = OrderedDict()  # prompt id -> node id -> message


def comfyui_value(kind, value):
    """``value`` as ComfyUI 0.3.64's validation passes it to an input of type ``kind``: a ``{"__value__": v}``
    unwrapped, then made an int, float, str or bool for INT, FLOAT, STRING, BOOLEAN (so ``"nan"`` is a FLOAT NaN,
    ``"-1"`` the INT -1). Raises one of :data:`REFUSED` where ComfyUI refuses the value itself."""
    if isinstance(value, dict) and "__value__" in value:
        value = value["__value__"]
    convert = {"INT": int, "FLOAT": float, "STRING": str, "BOOLEAN": bool}.get(kind) if isinstance(kind, str) else None
    return value if convert is None else convert(value)


def _inputs(node) -> dict:
    """A prompt node's inputs (input name -> value or ``[node id, slot]`` link); {} for a malformed node, which
    ComfyUI refuses itself."""
    inputs = node.get("inputs") if isinstance(node, dict) else None
    return inputs if isinstance(inputs, dict) else {}


def _links(node) -> dict[str, str]:
    """Input name -> the node id it is linked to, of a prompt node."""
    return {name: str(value[0]) for name, value in _inputs(node).items() if isinstance(value, list) and len(value) == 2}


def _upstream(prompt: dict, node_id: str) -> set[str]:
    """``node_id`` and every node it reads from, directly or not (links are ``[node id, slot]`` inputs)."""
    seen, stack = set(), [node_id]
    while stack:
        current = stack.pop()
        if current in seen or current not in prompt:
            continue
        seen.add(current)
        stack.extend(_links(prompt[current]).values())
    return seen


def _loaded_image_size(prompt: dict, node: dict, input_name: str) -> tuple[int, int] | None:
    """(width, height) of the image a stock Load Image feeds input ``input_name`` of ``node`` (its IMAGE, output
    0), from its file's header: the size it will pass (or, for a photo that EXIF rotates, that size turned).
    None for another source, or for a file outside ComfyUI's folders or that does not read (Load Image answers
    for those)."""
    link = _inputs(node).get(input_name)
    source = prompt.get(str(link[0])) if isinstance(link, list) and len(link) == 2 and link[1] == 0 else None
    if not isinstance(source, dict) or source.get("class_type") != "LoadImage":
        return None
    name = _inputs(source).get("image")
    file = load_image_path(name) if isinstance(name, str) else None
    if file is None or outside_folders(file):
        return None
    try:
        return image_size(file)
    except ValueError:
        return None


def _camera_count(prompt: dict, node: dict, classes: Mapping[str, type], input_name: str) -> int | None:
    """How many cameras input ``input_name`` of ``node`` will get, where the node feeding it (its output 0) says so
    before the graph runs (its class's ``camera_count(**inputs)``, given its values as ComfyUI passes them and its
    links as ``[node id, slot]``: Load Cameras reads its file); None for another source."""
    link = _inputs(node).get(input_name)
    source = prompt.get(str(link[0])) if isinstance(link, list) and len(link) == 2 and link[1] == 0 else None
    cls = classes.get(source.get("class_type")) if isinstance(source, dict) else None
    if not hasattr(cls, "camera_count"):
        return None
    values = {name: value for name, value in _inputs(source).items() if not isinstance(value, list)}
    return cls.camera_count(**{**_inputs(source), **cls.passed_values(values)})


def _listed(loader: type | None, input_name: str) -> list:
    """The choices ComfyUI's loader class ``loader`` lists now for its input ``input_name``, to which ComfyUI's own
    validation holds the value: its folder's files, and names that are no file (Load VAE's 'pixel_space'); [] without
    the class."""
    declared = loader.INPUT_TYPES().get("required", {}).get(input_name) if loader is not None else None
    return declared[0] if declared and isinstance(declared[0], list) else []


def _missing_model_files(prompt: dict, loader_id: str, classes: Mapping[str, type]) -> list[str]:
    """A message per file input of ComfyUI's model loader ``loader_id`` (:data:`~.model_files.STOCK_LOADERS`) whose
    value is neither among the choices the loader lists nor a file in its folder, naming the loader by its title,
    type and id."""
    loader = prompt[loader_id]
    kind = loader["class_type"]
    title = (loader.get("_meta") or {}).get("title") or kind
    messages = []
    for model_file in STOCK_LOADERS[kind]:
        file = comfyui_value(None, _inputs(loader).get(model_file.name, ""))  # {"__value__": name} unwrapped
        if isinstance(file, list) or file in _listed(classes.get(kind), model_file.name):  # a link: known as it runs
            continue
        message = model_file.check(f"{title} (node #{loader_id}, {kind})", str(file))
        if message:
            messages.append(message)
    return messages


def _missing_models(prompt: dict, node: dict, node_name: str, classes: Mapping[str, type]) -> str | None:
    """The message of pack node ``node`` (called ``node_name``) fed by ComfyUI's model loaders whose file is missing,
    straight or through the loaders' own links (a LoRA loader's MODEL and CLIP, a diff ControlNet loader's MODEL): a
    line per missing file, naming the node's inputs its loader feeds; None when each file is there."""
    fed: dict[str, list[str]] = {}  # loader id -> the node's inputs it feeds
    for input_name, source in _links(node).items():
        seen, stack = set(), [source]
        while stack:
            current = stack.pop()
            loader = prompt.get(current)
            if current in seen or not isinstance(loader, dict) or loader.get("class_type") not in STOCK_LOADERS:
                continue
            seen.add(current)
            fed.setdefault(current, []).append(input_name)
            stack.extend(_links(prompt[current]).values())
    lines = []
    for loader_id, input_names in fed.items():
        names = ", ".join(f"'{name}'" for name in input_names)
        inputs = f"input {names} comes" if len(input_names) == 1 else f"inputs {names} come"
        lines += [f"{node_name}: {inputs} from {message}" for message in _missing_model_files(prompt, loader_id, classes)]
    return "\n".join(lines) or None


def _checked(prompt: dict, classes: Mapping[str, type]) -> dict[str, tuple[str, str | None]]:
    """Node id -> (its problem, as :func:`failed_checks` names it; what its ``VALIDATE_INPUTS`` answers with:
    None where ComfyUI's own validation reports that problem itself: a value out of range or choices, or one it
    cannot convert)."""
    checked = {}
    for node_id, node in prompt.items():
        if not isinstance(node, dict):
            continue
        values = {name: value for name, value in _inputs(node).items() if not isinstance(value, list)}
        if node.get("class_type") in STOCK_LOADERS:
            messages = _missing_model_files(prompt, node_id, classes)
            if messages:
                checked[str(node_id)] = ("\n".join(messages), None)
            continue
        cls = classes.get(node.get("class_type"))
        message = cls.check_values(**values) if hasattr(cls, "check_values") else None
        if message:
            checked[str(node_id)] = (message, cls.unreported_value(**values))
            continue
        passed = cls.passed_values(values) if hasattr(cls, "passed_values") else values  # as ComfyUI passes them
        message = cls.check_files(**passed) if hasattr(cls, "check_files") else None
        if not message and hasattr(cls, "check_links"):  # an unconnected optional input is not in the prompt
            message = cls.check_links(_links(node).keys(), **passed)
        if not message and hasattr(cls, "check_views"):
            message = cls.check_views(functools.partial(_camera_count, prompt, node, classes), **passed)
        if not message and hasattr(cls, "check_images"):
            message = cls.check_images(functools.partial(_loaded_image_size, prompt, node))
        if not message and hasattr(cls, "check_images"):  # a node of the pack
            message = _missing_models(prompt, node, cls.DISPLAY_NAME, classes)
        if message:
            checked[str(node_id)] = (message, message)
    return checked


def failed_checks(prompt: dict, classes: Mapping[str, type]) -> dict[str, str]:
    """Node id -> message of every node whose class's ``check_values``, ``check_files`` or ``check_images``
    finds a problem with its values or the images Load Image nodes feed it, and of every model loader whose
    file is not in its folder."""
    return {node_id: message for node_id, (message, _) in _checked(prompt, classes).items()}


def check_prompt(request: dict, classes: Mapping[str, type]) -> dict:
    """The on-prompt handler (module docstring): ``request`` is the body POSTed to /prompt, ``classes``
    ComfyUI's node classes by type name. Returns ``request``, given a prompt id, its targets narrowed
    when a loader fails."""
    prompt = request.get("prompt")
    if not isinstance(prompt, dict):
        return request
    checked = _checked(prompt, classes)
    if not checked:
        _results.pop(str(request.get("prompt_id")), None)  # a prompt id given again: nothing of its last post
        return request
    prompt_id = request.setdefault("prompt_id", str(uuid.uuid4()))
    _results[str(prompt_id)] = {node_id: shown for node_id, (_, shown) in checked.items() if shown}
    while len(_results) > _KEPT_PROMPTS:
        _results.popitem(last=False)
    outputs = [node_id for node_id, node in prompt.items() if isinstance(node, dict)
               and getattr(classes.get(node.get("class_type")), "OUTPUT_NODE", False) is True]
    targets = request.get("partial_execution_targets")
    chosen = outputs if targets is None else [node_id for node_id in outputs if node_id in targets]
    blocked = [node_id for node_id in chosen if _upstream(prompt, node_id) & set(checked)]
    if blocked:
        request["partial_execution_targets"] = blocked
    return request


def check_result() -> bool | str:
    """A node's ``VALIDATE_INPUTS`` answer: the message :func:`check_prompt` kept for the node of the prompt that
    ComfyUI is validating (its executing context), else True."""
    execution = comfy_module("comfy_execution.utils")
    context = execution.get_executing_context() if hasattr(execution, "get_executing_context") else None
    if context is None:
        return True
    return _results.get(str(context.prompt_id), {}).get(str(context.node_id), True)


def register_prompt_check() -> None:
    """Install :func:`check_prompt` into the running ComfyUI server; nothing without one."""
    server, nodes = comfy_module("server"), comfy_module("nodes")
    instance = getattr(getattr(server, "PromptServer", None), "instance", None)
    if instance is None or not hasattr(nodes, "NODE_CLASS_MAPPINGS"):
        return
    instance.add_on_prompt_handler(lambda request: check_prompt(request, nodes.NODE_CLASS_MAPPINGS))
