"""JSON as the project reads it from files: every key in sight, and every failure a ValueError naming the file.

``json.loads`` keeps only the last value of a key given twice in one object (``{"iters": 5, "iters": 50}``
reads as ``{"iters": 50}``) and says nothing; :class:`JsonObject` tells. :func:`parse_json` is the one reader
of a file's JSON (cameras, model configs, safetensors headers, the batch's jobs)."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable

KINDS = ((dict, "object"), (list, "list"), (str, "string"), (bool, "boolean"), ((int, float), "number"))


class JsonObject(dict):
    """A JSON object as ``json.loads(text, object_pairs_hook=JsonObject)`` reads it: a dict (the last value of
    each key), and ``twice``, the first key given more than once in it (None when none)."""

    def __init__(self, pairs: list[tuple[str, object]]):
        super().__init__(pairs)
        self.twice = _first_repeated([key for key, _ in pairs]) if len(self) < len(pairs) else None


def _first_repeated(keys: list[str]) -> str | None:
    """The first of ``keys`` that equals an earlier one (None when none), in time linear in their number."""
    seen = set()
    for key in keys:
        if key in seen:
            return key
        seen.add(key)
    return None


def parse_json(text: str | bytes, what: str, expected: type | None = dict, *, once: bool = True,
               parse_int: Callable[[str], object] | None = None, hint: str = ""):
    """The JSON value of ``text`` (str, or UTF-8 bytes) read from ``what`` (a file, or a part of one: every
    message starts with it); its objects are :class:`JsonObject`. ValueErrors: text that is not JSON (or not
    UTF-8) and nesting deeper than Python's parser goes (``hint`` ends those messages: an example, say);
    a value that is not an ``expected`` (dict: an object, list: a list; None: any); with ``once``, a key given
    twice in one object. ``parse_int``: as ``json.loads``'s (``float``: a number beyond float range, 10**400,
    becomes infinite and is refused by the field that holds it)."""
    try:
        data = json.loads(text, parse_int=parse_int, object_pairs_hook=functools.partial(_object, what, once))
    except json.JSONDecodeError as error:
        raise ValueError(f"{what}: not valid JSON (line {error.lineno}, column {error.colno}: {error.msg}){hint}") \
            from None
    except UnicodeDecodeError:
        raise ValueError(f"{what}: not valid JSON (not UTF-8 text){hint}") from None
    except RecursionError:
        raise ValueError(f"{what}: not valid JSON (it nests too deeply){hint}") from None
    if expected is not None and not isinstance(data, expected):
        raise ValueError(f"{what}: expected a JSON {dict(KINDS)[expected]}, got {_kind(data)}")
    return data


def _kind(value) -> str:
    """"an object", "a list", ... or "null": what a JSON value is, in words."""
    name = next((name for types, name in KINDS if isinstance(value, types)), "null")
    return name if name == "null" else ("an " if name == "object" else "a ") + name


def _object(what: str, once: bool, pairs: list[tuple[str, object]]) -> JsonObject:
    """json's ``object_pairs_hook``: a :class:`JsonObject`, refused with ``once`` when it gives a key twice."""
    data = JsonObject(pairs)
    if once and data.twice is not None:
        raise ValueError(f"{what}: key '{data.twice}' is given twice in one object; give it once")
    return data
