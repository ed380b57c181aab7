"""JSON objects with every key in sight: ``json.loads`` keeps only the last value of a key given twice in one
object (``{"iters": 5, "iters": 50}`` reads as ``{"iters": 50}``) and says nothing; :class:`JsonObject` tells."""

from __future__ import annotations


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
