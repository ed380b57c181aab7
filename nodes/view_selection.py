"""Which capture views a node uses: a comma-separated list of view indices, or every stride-th view."""

from __future__ import annotations


def parse_view_list(text: str, count: int) -> list[int]:
    """Indices from text such as ``"0, 5, 9"`` (file order, each in 0..count-1); [] for blank text.

    Raises ValueError naming the offending entry.
    """
    indices = []
    for part in text.replace(";", ",").split(","):
        part = part.strip()
        if not part:
            continue
        try:
            index = int(part)
        except ValueError:
            raise ValueError(f"expected comma-separated view indices such as 0,5,9, got {part!r} in {text!r}") from None
        if not 0 <= index < count:
            raise ValueError(f"view index {index} is out of range for {count} cameras (0..{count - 1})")
        indices.append(index)
    return indices


def select_views(count: int, stride: int, views: str) -> list[int]:
    """The listed ``views`` when not blank, else views 0, stride, 2*stride, ... of ``count``."""
    return parse_view_list(views, count) or list(range(0, count, stride))
