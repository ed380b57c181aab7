"""How every node of the pack declares itself and its inputs: one base class, inputs as data.

A node subclasses :class:`ArtNVGNode` and sets ``DISPLAY_NAME``, ``FUNCTION``, ``RETURN_TYPES`` and
``RETURN_NAMES`` as ComfyUI reads them, and its inputs as ``REQUIRED`` and ``OPTIONAL``: dicts of
input name -> ``(type,)`` or ``(type, options)``, in the order saved workflows store them. An entry
may be a function returning the declaration instead, for choices read when ComfyUI asks (files in
a folder). The class docstring is the node's ``DESCRIPTION`` unless the class sets one; either is
shown as plain text (:func:`plain_text`), as the editor shows it.

Checks: a node's work runs inside :func:`~.node_errors.node_input`, which names the node and the
input in the error; a loader's file input is declared, found and checked by an
:class:`~.input_files.InputFile`; :meth:`ArtNVGNode.check_values` holds a prompt's values to the
declared ranges and choices before anything runs (``prompt_checks``), and
:meth:`ArtNVGNode.check_images` a style image's size where a Load Image feeds it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

from artnvg_core.style_image import check_style_size

from .node_types import CATEGORY, IMAGE

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


class ArtNVGNode:
    """Base of the pack's nodes (module docstring): the menu category, the description, the inputs."""

    CATEGORY = CATEGORY
    REQUIRED: dict = {}
    OPTIONAL: dict = {}
    HIDDEN: dict = {}  # ComfyUI's hidden inputs: name -> "UNIQUE_ID", "PROMPT"...

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        cls.DESCRIPTION = plain_text(vars(cls).get("DESCRIPTION") or cls.__doc__ or "")

    @classmethod
    def _value_problems(cls, values: dict) -> Iterator[tuple[str, bool]]:
        """(message, whether ComfyUI's own validation reports it too) for each of ``values`` (input name -> a
        prompt's value; links left out) outside its declared range (INT or FLOAT ``min``/``max``, FLOAT finite)
        or choices."""
        declared = {**cls.REQUIRED, **cls.OPTIONAL}
        for name, value in values.items():
            entry = declared.get(name)
            if entry is None or callable(entry):  # hidden inputs; file lists, which the loaders check
                continue
            kind, options = (*entry, {})[:2]
            if isinstance(kind, (list, tuple)) and value not in kind:  # choices, as a list or a tuple
                yield f"{cls.DISPLAY_NAME}: input '{name}': expected one of {list(kind)}, got {value!r}", True
                continue
            if kind not in ("INT", "FLOAT") or isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            outside = value < options.get("min", -math.inf) or value > options.get("max", math.inf)
            if not math.isfinite(value):  # ComfyUI cannot make an INT of one; a FLOAT NaN passes its comparisons
                yield f"{cls.DISPLAY_NAME}: input '{name}': expected a finite number, got {value}", kind == "INT" or outside
            elif outside:
                yield (f"{cls.DISPLAY_NAME}: input '{name}': {value} is outside {options.get('min', '-inf')} to "
                       f"{options.get('max', 'inf')}", True)

    @classmethod
    def check_values(cls, **values) -> str | None:
        """The message naming the first of ``values`` (input name -> a prompt's value; links left out) outside
        its declared range (INT or FLOAT ``min``/``max``, FLOAT finite) or choices, else None."""
        return next((message for message, _ in cls._value_problems(values)), None)

    @classmethod
    def unreported_value(cls, **values) -> str | None:
        """As :meth:`check_values`, for the values ComfyUI's own validation lets through (NaN; it reports the
        others itself, so a message of ours would repeat its own)."""
        return next((message for message, reported in cls._value_problems(values) if not reported), None)

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
