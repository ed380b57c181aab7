"""Cancellation helpers: a stop asked when a backward pass reaches a tensor ends that backward pass."""

import pytest
import torch

from artnvg_core.progress import Cancelled, check_stop, stop_in_backward


def test_check_stop_raises_only_when_asked():
    check_stop(None)
    check_stop(lambda: False)
    with pytest.raises(Cancelled):
        check_stop(lambda: True)


def test_a_stop_asked_when_the_backward_pass_reaches_the_tensor_ends_it_before_the_leaves():
    leaf, stop = torch.ones(3, requires_grad=True), []
    loss = (stop_in_backward(leaf * 2, lambda: bool(stop)) * 3).sum()
    stop.append(True)  # asked after the forward pass: the backward pass is the one stopped
    with pytest.raises(Cancelled):
        loss.backward()
    assert leaf.grad is None


def test_without_a_stop_the_gradient_is_unchanged_and_tensors_without_one_are_left_alone():
    leaf, asked = torch.ones(3, requires_grad=True), []
    (stop_in_backward(leaf * 2, lambda: asked.append(1) or False) * 3).sum().backward()
    assert torch.equal(leaf.grad, torch.full((3,), 6.0)) and asked == [1]
    plain = torch.ones(2)
    assert stop_in_backward(plain, lambda: True) is plain  # no gradient: nothing to ask, no error
    (stop_in_backward(leaf * 2, None)).sum().backward()


def test_stages_fill_one_bar_each_its_share_by_weight():
    from artnvg_core.progress import Stages

    calls = []
    stages = Stages(lambda *call: calls.append(call), 1000, {"read": 1, "decode": 2, "check": 1})
    for step in range(3):
        stages["read"](step, 2, {})
    stages["check"](1, 4, {"note": 1.0})  # a stage that does not report its start
    stages["check"](4, 4, {})
    assert calls == [(0, 1000, {}), (0, 1000, {}), (125, 1000, {}), (250, 1000, {}), (812, 1000, {"note": 1.0}),
                     (1000, 1000, {})]
    assert Stages(None, 1000, {"read": 1})["read"] is None
