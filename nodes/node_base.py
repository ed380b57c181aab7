"""How every node of the pack declares itself and its inputs: one base class, inputs as data.

A node subclasses :class:`ArtNVGNode` and sets ``DISPLAY_NAME``, ``FUNCTION``, ``RETURN_TYPES`` and
``RETURN_NAMES`` as ComfyUI reads them, and its inputs as ``REQUIRED`` and ``OPTIONAL``: dicts of
input name -> ``(type,)`` or ``(type, options)``, in the order saved workflows store them. An entry
may be a function returning the declaration instead, for choices read when ComfyUI asks (files in
a folder). The class docstring is the node's ``DESCRIPTION`` unless the class sets one; either is
shown as plain text (:func:`plain_text`), as the editor shows it.

Checks: a node's work runs inside :func:`~.node_errors.node_input`, which names the node and the
input in the error; a loader's file input is declared, found and checked by an
:class:`~.input_files.InputFile`; :meth:`ArtNVGNode.check_values` holds a prompt's values, as ComfyUI
will pass them (:func:`comfyui_value`), to the declared types, ranges and choices before anything runs
(``prompt_checks``; an input also to what the node's ``VALUE_CHECKS`` read from it), :meth:`ArtNVGNode.check_links`
the prompt's links to the optional inputs a value needs connected (``NEEDS_LINKS``: Select Gaussians' mode mask its
cameras and mask), :meth:`ArtNVGNode.check_views` a view index against the count of the cameras it indexes where
that is known, in the modes that read it (``VIEW_INPUTS``: a Load Cameras' file read), and
:meth:`ArtNVGNode.check_images` a style image's size where a Load Image feeds it. Every node answers
ComfyUI's validation with what those checks kept for it (``VALIDATE_INPUTS``), which ComfyUI labels with the one
input that function takes, ``REPORTED_INPUT``: the hidden input :data:`~.prompt_checks.CHECK_INPUT` (the node id,
which each node's function takes last, unused: "node_id - ..."), or, where every message the node shows names one
input, that input ("csgo_name - ...", "filename_prefix - ..."). ComfyUI reads that function's inputs from the class,
before it knows the node or the message, and labels the message with each of them: one fixed label per class. When a node runs, its
function first holds what it is given to the same checks and to the Python type its declared type stands
for, a number made its declared type's (:meth:`ArtNVGNode.run_inputs`): a value through a link meets no prompt
check.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import math
import numbers
from collections.abc import Callable, Collection, Iterator
from typing import NamedTuple

import torch

from artnvg_core.cameras.selection import check_view_index, listed_views
from artnvg_core.style_image import check_style_size

from .node_errors import NodeInputError
from .node_types import CATEGORY, IMAGE, RUN_TYPES
from .prompt_checks import CHECK_INPUT, REFUSED, check_result, comfyui_value

STYLE_IMAGE_INPUT = (IMAGE, {"tooltip": "The style reference (first image of the batch)."})


def plain_text(doc: str) -> str:
    """``doc`` (a docstring) as the editor's plain text: paragraphs (split at blank lines) each on one
    line, without the reStructuredText literal marks ``.. ``."""
    paragraphs = (" ".join(line.strip() for line in block.splitlines()) for block in doc.strip().split("\n\n"))
    return "\n\n".join(paragraph.replace("``", "") for paragraph in paragraphs if paragraph)


def _declared(inputs: dict) -> dict:
    """``inputs`` as ComfyUI reads them: every entry that is a function replaced by what it returns now, and
    choices declared as a tuple given as a list (ComfyUI holds a value to its choices only when they are one)."""
    declared = {}
    for name, entry in inputs.items():
        entry = entry() if callable(entry) else entry
        declared[name] = (list(entry[0]), *entry[1:]) if isinstance(entry[0], tuple) else entry
    return declared


def _type_name(cls: type) -> str:
    """``cls`` as a message names it: its module and name (builtins without the module)."""
    return cls.__qualname__ if cls.__module__ == "builtins" else f"{cls.__module__}.{cls.__qualname__}"


def _number_problem(kind: str, value) -> str | None:
    """What is wrong with the number ``value`` (a :class:`numbers.Real`: Python's, numpy's) for an input of type
    ``kind`` (INT or FLOAT) that converting it as ComfyUI does (``int()``, ``float()``) would hide: a bool (``True``
    is 1), or for an INT a fraction (``int(2.5)`` is 2); else None."""
    if isinstance(value, bool):
        return f"expected a number, got {value}"
    if kind == "INT" and not isinstance(value, numbers.Integral) and not float(value).is_integer():
        return f"expected a whole number, got {value}"
    return None


def _run_type_problem(kind, value) -> str | None:
    """What is wrong with ``value`` given to an input of type ``kind`` when the node runs: not an instance of the
    Python type :data:`~.node_types.RUN_TYPES` names for ``kind`` (for INT and FLOAT, either number that
    :func:`_number_problem` keeps), or a tensor of another rank; None when right, or when ``kind`` has no entry
    there (ComfyUI's MODEL, VAE...)."""
    expected = RUN_TYPES.get(kind) if isinstance(kind, str) else None
    if kind in ("INT", "FLOAT") and isinstance(value, numbers.Real):  # numpy's numbers too
        return _number_problem(kind, value)
    if expected is None or isinstance(value, expected.cls) and (not expected.ranks or value.ndim in expected.ranks):
        return None
    ranks = f" of {' or '.join(map(str, expected.ranks))} dimensions {expected.layout}" if expected.ranks else ""
    got = f"a tensor of shape {list(value.shape)}" if isinstance(value, torch.Tensor) else _type_name(type(value))
    return f"expected {kind}, {_type_name(expected.cls)}{ranks}; got {got}"


def _validate_inputs(input_name: str) -> classmethod:
    """A node's ``VALIDATE_INPUTS``: what the pack's checks of the whole prompt kept for the node ComfyUI is validating
    (:func:`~.prompt_checks.check_result`), else True. ComfyUI reads the inputs it takes from its signature, made here
    to name ``input_name`` alone: ComfyUI passes that input, labels a failure with its name (the details' "NAME - ",
    ``extra_info.input_name``: the input the editor outlines), once, and skips its own range and choice checks of it."""

    def validate(cls, **_input):
        return check_result()

    parameter = inspect.Parameter.POSITIONAL_OR_KEYWORD
    validate.__signature__ = inspect.Signature([inspect.Parameter("cls", parameter),
                                                inspect.Parameter(input_name, parameter, default=None)])
    return classmethod(validate)


def _checking_inputs(function: Callable) -> Callable:
    """A node's ``FUNCTION`` that first takes its inputs through :meth:`ArtNVGNode.run_inputs` (which refuses them
    with a :class:`~.node_errors.NodeInputError`), then does its work."""
    signature = inspect.signature(function)

    @functools.wraps(function)
    def run(self, *args, **kwargs):
        inputs = signature.bind(self, *args, **kwargs)
        inputs.arguments.update(type(self).run_inputs(inputs.arguments))
        return function(*inputs.args, **inputs.kwargs)

    return run


class ViewInput(NamedTuple):
    """An input of view indices (a view list's text, or an INT view) in a node's ``VIEW_INPUTS``: the CAMERAS input
    whose views it indexes and, for an input that one mode alone reads, that mode as (input name, value): Render
    Camera Path's key_views ("path", "interpolate"); None where every mode reads it."""

    cameras: str = "cameras"
    mode: tuple[str, str] | None = None


class ArtNVGNode:
    """Base of the pack's nodes (module docstring): the menu category, the description, the inputs."""

    CATEGORY = CATEGORY
    REQUIRED: dict = {}
    OPTIONAL: dict = {}
    HIDDEN = {CHECK_INPUT: "UNIQUE_ID"}  # ComfyUI's hidden inputs: name -> "UNIQUE_ID", "PROMPT"...
    REPORTED_INPUT = CHECK_INPUT  # the input ComfyUI labels the node's validation message with (_validate_inputs):
    # the hidden node id, or the input each message of the node names: a required COMBO or STRING, whose value
    # ComfyUI holds to no range or choices (naming an input in VALIDATE_INPUTS skips those checks of it)
    VALIDATE_INPUTS = _validate_inputs(CHECK_INPUT)
    VALUE_CHECKS: dict = {}  # input name -> the function (value, once of its declared type and range) -> anything
    # the node reads it with when it runs, raising ValueError for a value it refuses (text it cannot read, a number
    # the declared range lets through): checked with the prompt's values, before the graph runs
    VIEW_INPUTS: dict[str, ViewInput] = {}  # input name -> the cameras whose views it indexes (and the mode that
    # reads it): checked against their count where it is known before the graph runs (a Load Cameras' file)
    NEEDS_LINKS: dict = {}  # input name -> {a value of it -> the optional inputs the node then needs connected}:
    # checked with the prompt's links, before the graph runs (an unconnected optional input is not in the prompt)

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        cls.DESCRIPTION = plain_text(vars(cls).get("DESCRIPTION") or cls.__doc__ or "")
        if "REPORTED_INPUT" in vars(cls):
            cls.VALIDATE_INPUTS = _validate_inputs(cls.REPORTED_INPUT)
        function = vars(cls).get(getattr(cls, "FUNCTION", None))
        if function is not None:
            setattr(cls, cls.FUNCTION, _checking_inputs(function))

    @classmethod
    def _value_problems(cls, values: dict) -> Iterator[tuple[str, bool]]:
        """(message, whether ComfyUI's own validation reports it too) for each of ``values`` (input name -> a
        prompt's value; links left out) that ComfyUI cannot convert to its declared type, or that lies, once
        converted (:func:`comfyui_value`), outside its declared range (INT or FLOAT ``min``/``max``, FLOAT finite)
        or choices, or is not text where a COMBO (a loader's file list, which the loader checks) takes it, or is
        text where a BOOLEAN takes true or false, or that the node's ``VALUE_CHECKS`` refuse. ComfyUI checks
        the range and choices of every declared input (:meth:`VALIDATE_INPUTS` names none of them), but not a
        FLOAT's NaN, a COMBO's value, a BOOLEAN's nor what a value means to the node."""
        inputs = {**cls.REQUIRED, **cls.OPTIONAL}
        declared = _declared({name: entry for name, entry in inputs.items() if name in values})
        for name, given in values.items():
            if name not in declared:  # hidden inputs, and undeclared ones (ComfyUI drops those)
                continue
            kind, options = (*declared[name], {})[:2]
            where = f"{cls.DISPLAY_NAME}: input '{name}'"
            try:
                value = comfyui_value(kind, given)
            except REFUSED:
                yield f"{where}: expected a value of type {kind}, got {given!r}", True
                continue
            found = []  # (message, reported by ComfyUI too): at most one
            if isinstance(kind, list):
                if value not in kind:
                    found.append((f"{where}: expected one of {kind}, got {value!r}", True))
            elif kind == "COMBO":
                if not isinstance(value, str):
                    found.append((f"{where}: expected a file name, got {value!r}", False))
            elif kind == "BOOLEAN":
                if isinstance(comfyui_value(None, given), str):  # bool("false") is True
                    found.append((f"{where}: expected true or false, got {given!r}", False))
            elif kind in ("INT", "FLOAT"):
                outside = value < options.get("min", -math.inf) or value > options.get("max", math.inf)
                raw = comfyui_value(None, given)  # a number, or text ComfyUI converted
                number = _number_problem(kind, raw) if isinstance(raw, numbers.Real) else None
                if number:  # ComfyUI converts it: int(2.5) is 2
                    found.append((f"{where}: {number}", False))
                elif not math.isfinite(value):  # a FLOAT: NaN passes ComfyUI's comparisons
                    found.append((f"{where}: expected a finite number, got {value}", outside))
                elif outside:
                    low, high = options.get("min", "-inf"), options.get("max", "inf")
                    found.append((f"{where}: {value} is outside {low} to {high}", True))
            if not found and name in cls.VALUE_CHECKS:
                try:
                    cls.VALUE_CHECKS[name](value)
                except ValueError as error:
                    found.append((f"{where}: {error}", False))
            yield from found

    @classmethod
    def passed_values(cls, values: dict) -> dict:
        """``values`` (input name -> a prompt's value; links left out) as ComfyUI passes them to the node
        (:func:`comfyui_value`); those it cannot convert, and hidden inputs, as given."""
        declared = _declared({**cls.REQUIRED, **cls.OPTIONAL})
        passed = dict(values)
        for name in values.keys() & declared.keys():
            with contextlib.suppress(*REFUSED):
                passed[name] = comfyui_value(declared[name][0], values[name])
        return passed

    @classmethod
    def check_values(cls, **values) -> str | None:
        """The message naming the first of ``values`` (input name -> a prompt's value; links left out) not of
        its declared type, outside its declared range (INT or FLOAT ``min``/``max``, FLOAT finite) or choices, not
        text where a COMBO takes it or text where a BOOLEAN does (:meth:`_value_problems`), else None."""
        return next((message for message, _ in cls._value_problems(values)), None)

    @classmethod
    def check_links(cls, linked: Collection[str], **values) -> str | None:
        """The message naming the first optional input that a value of ``values`` (input name -> a prompt's value)
        needs connected (:attr:`NEEDS_LINKS`) and that is not among ``linked`` (the inputs a link feeds), else None."""
        passed = cls.passed_values(values)
        for name, needs in cls.NEEDS_LINKS.items():
            value = passed.get(name)
            needed = needs.get(value, ()) if isinstance(value, str) else ()
            missing = [input_name for input_name in needed if input_name not in linked]
            if missing:
                return (f"{cls.DISPLAY_NAME}: input '{missing[0]}': {name} {value} needs {' and '.join(needed)} "
                        "connected")
        return None

    @classmethod
    def check_views(cls, camera_count: Callable[[str], int | None], **values) -> str | None:
        """The message naming the first input of :attr:`VIEW_INPUTS` among ``values`` (input name -> a prompt's value)
        that indexes a view past the last of its cameras, whose count ``camera_count(cameras input)`` gives where
        known (else None), else None; an input that one mode alone reads only in that mode (its message names it), not
        when the mode is another or unknown (through a link). Run after :meth:`check_values`, which refuses text that
        is no view list. The count is asked for only where an index is above 0 (a camera set is never empty)."""
        passed = cls.passed_values(values)
        for name, (cameras, mode) in cls.VIEW_INPUTS.items():
            if mode is not None and passed.get(mode[0]) != mode[1]:
                continue
            value = passed.get(name)
            indices = listed_views(value) if isinstance(value, str) else [value] if type(value) is int else []
            count = camera_count(cameras) if any(indices) else None  # a Load Cameras reads its file for it
            for index in indices if count is not None else ():
                try:
                    check_view_index(index, count, " ".join(mode) if mode else None)
                except ValueError as error:
                    return f"{cls.DISPLAY_NAME}: input '{name}': {error}"
        return None

    @classmethod
    def unreported_value(cls, **values) -> str | None:
        """As :meth:`check_values`, for the values ComfyUI's own validation lets through (a FLOAT NaN, a COMBO's
        value that is not text, a BOOLEAN's that is; it reports the others itself, so a message of ours would
        repeat its own)."""
        return next((message for message, reported in cls._value_problems(values) if not reported), None)

    @classmethod
    def run_inputs(cls, inputs: dict) -> dict:
        """When the node runs, before any work: ``inputs`` (input name -> the value given; an optional input given
        None counts as unconnected) as the node takes them, numbers as their declared type's (an INT's 3.0 as 3, a
        FLOAT's 1 as 1.0, as ComfyUI converts a prompt's). Raises :class:`~.node_errors.NodeInputError` naming the
        first input that is not what its declared type holds (:data:`~.node_types.RUN_TYPES`: another pack's output
        of type ``*`` passes ComfyUI's link check, and ComfyUI passes it as it is: 2.5 to an INT), or that
        :meth:`check_values` refuses (a value through a link meets no prompt check), or an optional input left
        unconnected that :meth:`check_links` needs (an input given counts as linked), or a view index past the
        cameras given (:meth:`check_views`). Inputs declared by a function
        (a loader's file list, ComfyUI's samplers) are left to the node, whose message says more."""
        declared = _declared({name: entry for name, entry in {**cls.REQUIRED, **cls.OPTIONAL}.items()
                              if name in inputs and not callable(entry)})
        given = {name: value for name, value in inputs.items()
                 if name in declared and not (value is None and name in cls.OPTIONAL)}
        for name, value in given.items():
            problem = _run_type_problem(declared[name][0], value)
            if problem:
                raise NodeInputError(f"{cls.DISPLAY_NAME}: input '{name}': {problem}")
        problem = (cls.check_values(**given) or cls.check_links(given.keys(), **given)
                   or cls.check_views(lambda cameras: len(given[cameras]) if cameras in given else None, **given))
        if problem:
            raise NodeInputError(problem)
        return {name: RUN_TYPES[declared[name][0]].cls(value) for name, value in given.items()
                if declared[name][0] in ("INT", "FLOAT")}

    @classmethod
    def check_images(cls, image_size: Callable[[str], tuple[int, int] | None]) -> str | None:
        """The message naming the first style image input (declared as :data:`STYLE_IMAGE_INPUT`) whose size
        ``image_size(input name)`` ((width, height), known before the graph runs where a Load Image feeds the
        input, else None) breaks :func:`artnvg_core.style_image.check_style_size`, else None. A node with such an
        input checks it again when it runs (an IMAGE's size is known then)."""
        for name, entry in {**cls.REQUIRED, **cls.OPTIONAL}.items():
            size = image_size(name) if entry is STYLE_IMAGE_INPUT else None
            if size is None:
                continue
            try:
                check_style_size(*size)
            except ValueError as error:
                return f"{cls.DISPLAY_NAME}: input '{name}': {error}"
        return None

    @classmethod
    def INPUT_TYPES(cls) -> dict:
        """ComfyUI's input declaration: ``{"required": REQUIRED, "optional": OPTIONAL, "hidden": HIDDEN}`` (the last
        two when any)."""
        types = {"required": _declared(cls.REQUIRED)}
        if cls.OPTIONAL:
            types["optional"] = _declared(cls.OPTIONAL)
        if cls.HIDDEN:
            types["hidden"] = dict(cls.HIDDEN)
        return types
