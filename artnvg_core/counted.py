"""Counts in words, for the lines people read: ``counted(1, "view")`` is "1 view", ``counted(24, "view")``
"24 views", ``counted(100000, "Gaussian")`` "100,000 Gaussians"."""

from __future__ import annotations


def counted(count: int, noun: str, plural: str | None = None) -> str:
    """``count`` (thousands separated by commas) and ``noun``, in the plural (``plural``, else ``noun + "s"``)
    unless ``count`` is 1."""
    return f"{count:,} {noun if count == 1 else plural or noun + 's'}"
