"""Strict state dicts: weights given to a model built without random ones, every key checked."""

import threading

import pytest
import torch

from artnvg_core.statedict import UNINITIALISED, assign_strict, parameters_on_meta
from diffusion_tiny import tiny_image_encoder


def test_assigned_weights_take_the_computed_buffers_to_their_device():
    """A model built with its parameters on the meta device and given weights on another device (the GPU
    when a stylize run loads) has every tensor there: the computed buffers (CLIP's position ids) too, which
    the file does not hold (the image encoder failed on CUDA with its position ids left on the CPU)."""
    encoder = tiny_image_encoder()
    with parameters_on_meta():
        built = type(encoder)(encoder.config)
    assign_strict(built, {k: v.to("meta") for k, v in encoder.state_dict().items()}, "weights")
    assert {t.device.type for t in (*built.parameters(), *built.buffers())} == {"meta"}


def test_a_state_that_does_not_fit_is_refused_naming_it_and_its_keys():
    model = torch.nn.Linear(3, 2)
    state = {"weight": torch.zeros(2, 4), "extra": torch.zeros(1)}
    with pytest.raises(ValueError, match=r"^weights 'w\.pt' do not fit Linear: 1 missing key \[bias\], 1 unexpected "
                       r"key \[extra\], 1 wrong shape \['weight \[2, 4\] != \[2, 3\]'\]$"):
        assign_strict(model, state, "weights 'w.pt'")
    fitting = {"weight": torch.ones(2, 3), "bias": torch.ones(2)}
    assign_strict(model, fitting, "weights")
    assert model.weight.data_ptr() == fitting["weight"].data_ptr()  # the state's own storage, not a copy


def test_transformers_initialisation_leaves_the_meta_parameters_alone(monkeypatch):
    """transformers initialises a model's weights after building it: on meta parameters that ran PyTorch's meta
    kernels in Python (0.23 s of the interpreter lock for SDXL's text encoders and the image encoder). Built
    within parameters_on_meta its parameters are marked initialised and none is initialised; the computed
    buffers keep their values."""
    from transformers import initialization

    encoder = tiny_image_encoder()
    initialised = []
    for name, init in initialization.TORCH_INIT_FUNCTIONS.items():
        def spy(tensor, *args, init=init, **kwargs):
            initialised.append(tensor.shape)
            return init(tensor, *args, **kwargs)

        monkeypatch.setitem(initialization.TORCH_INIT_FUNCTIONS, name, spy)
    with parameters_on_meta():
        built = type(encoder)(encoder.config)
    assert initialised == [] and all(p.is_meta for p in built.parameters())
    expected = dict(encoder.named_buffers())
    assert dict(built.named_buffers()).keys() == expected.keys()
    assert all(torch.equal(buffer, expected[name]) for name, buffer in built.named_buffers())
    type(encoder)(encoder.config)
    assert initialised  # the spies see an initialisation outside the block


class _Scaled(torch.nn.Module):
    """A layer with a persistent buffer, a frozen parameter and a non-persistent buffer, under a container."""

    def __init__(self) -> None:
        super().__init__()
        self.inner = torch.nn.Sequential(torch.nn.Linear(3, 2))
        self.scale = torch.nn.Parameter(torch.ones(2), requires_grad=False)
        self.register_buffer("offset", torch.zeros(2))
        self.register_buffer("steps", torch.arange(4), persistent=False)


def _fitting_state() -> dict[str, torch.Tensor]:
    return {"inner.0.weight": torch.full((2, 3), 2.0), "inner.0.bias": torch.full((2,), 3.0),
            "scale": torch.full((2,), 4.0), "offset": torch.full((2,), 5.0)}


def test_a_state_is_assigned_without_load_state_dict_s_work_per_module(monkeypatch):
    """Each tensor becomes its module's parameter (requires_grad kept) or buffer as load_state_dict(assign=True)
    makes it, directly (load_state_dict's checks, hooks and no_grad block per module and tensor were a tenth of
    the lock a load held); the computed buffer stays the model's."""
    def refused(*args, **kwargs):
        raise AssertionError("load_state_dict called")

    expected, model = _Scaled(), _Scaled()
    expected.load_state_dict(_fitting_state(), assign=True)
    state = _fitting_state()
    monkeypatch.setattr(torch.nn.Module, "load_state_dict", refused)
    assign_strict(model, state, "weights")
    ours = dict((*model.named_parameters(), *model.named_buffers()))
    for name, tensor in (*expected.named_parameters(), *expected.named_buffers()):
        assert (type(ours[name]), ours[name].requires_grad) == (type(tensor), tensor.requires_grad), name
        assert torch.equal(ours[name], tensor), name
    assert model.offset is state["offset"] and model.inner[0].weight.data_ptr() == state["inner.0.weight"].data_ptr()


def test_a_model_with_a_module_that_loads_its_own_way_goes_through_load_state_dict():
    """A load hook (or a class's own _load_from_state_dict) is honoured: such a model is given to load_state_dict."""
    model, seen = _Scaled(), []
    model.inner[0]._register_load_state_dict_pre_hook(lambda state, prefix, *args: seen.append(prefix))
    assign_strict(model, _fitting_state(), "weights")
    assert seen == ["inner.0."] and torch.equal(model.offset, torch.full((2,), 5.0))


def _pytorch_functions() -> dict:
    """The functions parameters_on_meta patches, by class and name."""
    return {(owner, name): owner.__dict__[name] for owner, name in
            ((torch.nn.Module, "register_parameter"), *((layer, "reset_parameters") for layer in UNINITIALISED))}


def _in_a_thread(entered: threading.Event, leave: threading.Event, built: list) -> threading.Thread:
    """A started thread that enters parameters_on_meta, builds a Linear into ``built``, sets ``entered``, and
    leaves the block once ``leave`` is set."""
    def inside() -> None:
        with parameters_on_meta():
            built.append(torch.nn.Linear(3, 2))
            entered.set()
            assert leave.wait(10)

    thread = threading.Thread(target=inside)
    thread.start()
    assert entered.wait(10)
    return thread


def test_two_threads_leaving_in_the_order_they_entered_leave_pytorch_unpatched():
    """A enters, B enters, A leaves, B leaves: PyTorch's functions are the originals again (B had saved A's patch
    and put it back for good), and each thread built its Linear on meta."""
    originals, built = _pytorch_functions(), []
    a_in, b_in, a_out, b_out = (threading.Event() for _ in range(4))
    a = _in_a_thread(a_in, a_out, built)
    b = _in_a_thread(b_in, b_out, built)
    a_out.set()
    a.join(10)
    b_out.set()
    b.join(10)
    assert _pytorch_functions() == originals  # == on functions: identity
    assert [linear.weight.is_meta for linear in built] == [True, True]
    assert not torch.nn.Linear(3, 2).weight.is_meta


def test_a_module_another_thread_builds_during_a_block_has_real_initialised_parameters():
    """While a load runs parameters_on_meta in its thread, the caller's thread (ComfyUI's server) builds modules
    as ever: parameters real and initialised by reset_parameters (the same values for the same seed)."""
    torch.manual_seed(0)
    expected = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Conv2d(2, 4, 3), torch.nn.LayerNorm(4))
    entered, leave, built = threading.Event(), threading.Event(), []
    thread = _in_a_thread(entered, leave, built)
    try:
        torch.manual_seed(0)
        beside = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Conv2d(2, 4, 3), torch.nn.LayerNorm(4))
        assert built[0].weight.is_meta  # the block is still open
    finally:
        leave.set()
        thread.join(10)
    assert not any(parameter.is_meta for parameter in beside.parameters())
    for name, parameter in expected.named_parameters():
        assert torch.equal(beside.get_parameter(name), parameter), name


def test_blocks_nest_in_one_thread():
    """Leaving an inner block leaves the outer one building on meta; leaving the outer one restores PyTorch."""
    originals = _pytorch_functions()
    with parameters_on_meta():
        with parameters_on_meta():
            assert torch.nn.Linear(3, 2).weight.is_meta
        assert torch.nn.Linear(3, 2).weight.is_meta
    assert _pytorch_functions() == originals and not torch.nn.Linear(3, 2).weight.is_meta


def test_an_exception_inside_the_block_restores_pytorch():
    originals = _pytorch_functions()
    with pytest.raises(RuntimeError, match="failed load"), parameters_on_meta():
        raise RuntimeError("failed load")
    assert _pytorch_functions() == originals and not torch.nn.Linear(3, 2).weight.is_meta
