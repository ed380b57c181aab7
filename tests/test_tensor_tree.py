"""map_tensors: every tensor of a value, nested dataclasses followed, the rest kept, the input unchanged."""

from dataclasses import dataclass, field

import pytest
import torch

from artnvg_core.tensor_tree import map_tensors


@dataclass(frozen=True)
class Inner:
    weights: torch.Tensor
    name: str


@dataclass(frozen=True)
class Outer:
    inner: Inner
    bias: torch.Tensor
    missing: torch.Tensor | None = None
    tags: list = field(default_factory=list)

    def __post_init__(self):
        if self.bias.ndim != 1:
            raise ValueError("bias must be 1-D")


def test_every_tensor_nested_or_not_is_mapped_and_the_rest_kept():
    tags = ["a"]
    value = Outer(Inner(torch.arange(3.0), "w"), torch.tensor([1.0, -2.0]), tags=tags)
    mapped = map_tensors(lambda t: t * 10, value)
    assert torch.equal(mapped.inner.weights, torch.tensor([0.0, 10.0, 20.0]))
    assert torch.equal(mapped.bias, torch.tensor([10.0, -20.0]))
    assert mapped.inner.name == "w" and mapped.missing is None and mapped.tags is tags
    assert torch.equal(value.inner.weights, torch.arange(3.0)) and torch.equal(value.bias, torch.tensor([1.0, -2.0]))


def test_a_bare_tensor_and_other_values():
    assert torch.equal(map_tensors(torch.neg, torch.ones(2)), -torch.ones(2))
    assert map_tensors(torch.neg, None) is None
    assert map_tensors(torch.neg, Inner) is Inner  # a dataclass type is no value to map


def test_the_dataclass_checks_run_on_the_result():
    with pytest.raises(ValueError, match="bias must be 1-D"):
        map_tensors(lambda t: t[None], Outer(Inner(torch.zeros(1), "w"), torch.zeros(2)))
