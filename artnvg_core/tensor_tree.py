"""One map over the tensors a value holds: the scenes, camera sets and conditionings that cross a
device, a process or ComfyUI's inference mode."""

from __future__ import annotations

import dataclasses
from typing import Callable, TypeVar

import torch

T = TypeVar("T")


def map_tensors(fn: Callable[[torch.Tensor], torch.Tensor], value: T) -> T:
    """``value`` with ``fn`` applied to every tensor in it: a tensor, or a dataclass whose fields hold tensors,
    such dataclasses (followed) and other values (kept, by reference). Dataclasses are rebuilt with
    :func:`dataclasses.replace`, so their checks run again; ``value`` itself is not changed."""
    if isinstance(value, torch.Tensor):
        return fn(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(value, **{field.name: map_tensors(fn, getattr(value, field.name))
                                             for field in dataclasses.fields(value)})
    return value
