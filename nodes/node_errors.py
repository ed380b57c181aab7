"""Errors that tell the user which node input was wrong (and, through the core's message, which file)."""

from __future__ import annotations

from contextlib import contextmanager


class NodeInputError(ValueError):
    """Bad value or file for a node's inputs; the message starts with ``<node>: input '<name>':``
    (or ``<node>:`` when the core's message itself names the field)."""


@contextmanager
def node_input(node: str, input_name: str | None = None):
    """Re-raise a ``ValueError`` from the block as :class:`NodeInputError` naming ``node`` and ``input_name``.

    The core's message (which names the file and the field) is kept whole after the prefix.
    Leave ``input_name`` out when the block reads several inputs and its errors name the field.
    """
    try:
        yield
    except NodeInputError:
        raise
    except ValueError as error:
        where = f"{node}: input '{input_name}'" if input_name else node
        raise NodeInputError(f"{where}: {error}") from error
