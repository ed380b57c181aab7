"""Strict state dicts: weights given to a model built without random ones, every key checked."""

import pytest
import torch

from artnvg_core.statedict import assign_strict, parameters_on_meta
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


def test_transformers_models_are_built_without_their_weight_initialisation(monkeypatch):
    """transformers initialises a model's weights after building it: on meta parameters that ran PyTorch's meta
    kernels in Python (0.5 s of the interpreter lock for SDXL's text encoders and the image encoder). Built
    within parameters_on_meta it is skipped, as transformers' own from_pretrained skips it; the computed
    buffers keep their values."""
    from transformers.models.clip.modeling_clip import CLIPPreTrainedModel

    encoder = tiny_image_encoder()
    initialised = []
    monkeypatch.setattr(CLIPPreTrainedModel, "_init_weights", lambda self, module: initialised.append(module))
    with parameters_on_meta():
        built = type(encoder)(encoder.config)
    assert initialised == [] and all(p.is_meta for p in built.parameters())
    expected = dict(encoder.named_buffers())
    assert dict(built.named_buffers()).keys() == expected.keys()
    assert all(torch.equal(buffer, expected[name]) for name, buffer in built.named_buffers())
    type(encoder)(encoder.config)
    assert initialised  # the spy sees an initialisation outside the block
