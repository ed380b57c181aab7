"""Which views of a camera set to use, from text: the one view-list grammar of the command line's
``--views`` and the nodes' view inputs.

Grammar: view indices in file order, separated by commas (or semicolons), e.g. ``0, 5, 9``; each in
``0..count-1``; repeats (unless refused: a view rendered to a file of its own) and any order are kept as
written. Blank text (or None, or separators alone) means every view.
"""

from __future__ import annotations

from ..counted import counted


def listed_views(text: str | None, what: str | None = None, *, distinct: bool = False) -> list[int]:
    """The indices written in ``text`` (the module's grammar), as written; [] when blank. The checks that need
    no camera count, so that a view list can be checked before the cameras are known.

    Raises ValueError naming the offending entry (not an index, or negative), after ``what:`` (an option's
    name) when given; with ``distinct``, also naming a view given twice.
    """
    where = f"{what}: " if what else ""
    indices, seen = [], set()
    for part in (text or "").replace(";", ",").split(","):
        part = part.strip()
        if not part:
            continue
        try:
            index = int(part)
        except ValueError:
            raise ValueError(f"{where}expected comma-separated view indices such as 0,5,9, got {part!r} "
                             f"in {text!r}") from None
        if index < 0:
            raise ValueError(f"{where}view index {index} is out of range: views count from 0")
        if distinct and index in seen:
            raise ValueError(f"{where}view {index} is given twice in {text!r}; give each view once")
        indices.append(index)
        seen.add(index)
    return indices


def check_view_index(index: int, count: int, what: str | None = None) -> None:
    """ValueError naming the view index ``index`` (>= 0), after ``what:`` when given, and the valid range when it lies
    past the last of ``count`` views."""
    if index >= count:
        where = f"{what}: " if what else ""
        raise ValueError(f"{where}view index {index} is out of range for {counted(count, 'camera')} (0..{count - 1})")


def parse_views(text: str | None, count: int, what: str | None = None, *, distinct: bool = False) -> list[int]:
    """Indices from ``text`` (the module's grammar) for a set of ``count`` views: every view when blank.

    Raises ValueError as :func:`listed_views` does, and naming an index past the last view.
    """
    indices = listed_views(text, what, distinct=distinct)
    for index in indices:
        check_view_index(index, count, what)
    return indices or list(range(count))
