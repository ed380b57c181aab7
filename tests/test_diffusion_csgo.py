"""CSGO: released key layouts, loading strict where the released loader keeps random weights, token routing
and scale-0 identity on tiny SDXL models."""

import logging
import pickle
from fractions import Fraction

import pytest
import torch
from diffusers import ControlNetModel, UNet2DConditionModel
from diffusers.models.attention_processor import AttnProcessor2_0

from artnvg_core.diffusion.architectures import SDXL_UNET_CONFIG, controlnet_config_from_unet
from artnvg_core.diffusion.attention import AttentionControl, attention_kwargs
from artnvg_core.diffusion.csgo import (
    CONTROLNET_ROUTES,
    UNET_ROUTES,
    install_processors,
    processor_key_layout,
    routed_keys,
)
from artnvg_core.diffusion.csgo_weights import CSGOWeightsError, load_csgo
from artnvg_core.tensor_files import load_failure
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import CROSS_DIM, RESAMPLER_HEAD_WIDTH, csgo_state, tiny_controlnet, tiny_unet, write_csgo_file


def test_sdxl_processor_indices():
    """SDXL: UNet keys at odd i in 1..47 (down, content) and 49..119 (up, style), none for mid 120..139;
    ControlNet keys at odd i in 1..47 (down, style), none for mid 48..67."""
    with torch.device("meta"):
        unet = UNet2DConditionModel(**SDXL_UNET_CONFIG)
        controlnet = ControlNetModel(**controlnet_config_from_unet(unet.config))
        install_processors(unet, UNET_ROUTES)
        install_processors(controlnet, CONTROLNET_ROUTES)
    assert len(unet.attn_processors) == 140 and len(controlnet.attn_processors) == 68
    unet_indices = {int(key.split(".")[0]) for key in processor_key_layout(unet)}
    assert unet_indices == set(range(1, 120, 2))
    assert len(processor_key_layout(unet)) == 120
    names = list(unet.attn_processors)
    assert all(names[i].startswith("down_blocks") for i in range(1, 48, 2))
    assert all(names[i].startswith("up_blocks") for i in range(49, 120, 2))
    assert all(names[i].startswith("mid_block") for i in range(120, 140))
    assert {int(key.split(".")[0]) for key in processor_key_layout(controlnet)} == set(range(1, 48, 2))
    width = {int(k.split(".")[0]): p.shape for k, p in processor_key_layout(unet).items()}
    assert width[1] == (640, 2048) and width[9] == (1280, 2048) and width[119] == (640, 2048)


@pytest.fixture
def models():
    unet = tiny_unet()
    return unet, tiny_controlnet(unet)


def test_loading_initialises_no_weight_the_file_replaces(tmp_path, models, monkeypatch):
    """The resamplers and the image-branch projections are built without random initialisation (for
    the full-size models seconds of CPU time, all of it overwritten by the file)."""
    unet, controlnet = models
    path = write_csgo_file(tmp_path / "csgo.bin", csgo_state(unet, controlnet))
    initialised = []
    for layer in (torch.nn.Linear, torch.nn.LayerNorm):
        reset = layer.reset_parameters

        def spy(self, reset=reset):
            initialised.append(type(self).__name__ if self.weight is not None and not self.weight.is_meta else None)
            reset(self)

        monkeypatch.setattr(layer, "reset_parameters", spy)
    projections = load_csgo(path, unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    assert initialised and not any(initialised), initialised
    assert all(p.device.type == "cpu" for p in projections.parameters())


@pytest.mark.parametrize("num_style, by_index", [(8, True), (16, False)])
def test_released_layout_loads_every_key(tmp_path, models, num_style, by_index):
    unet, controlnet = models
    state = csgo_state(unet, controlnet, num_style_tokens=num_style, controlnet_by_index=by_index)
    path = write_csgo_file(tmp_path / "csgo.bin", state)
    projections = load_csgo(path, unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    assert (projections.num_content_tokens, projections.num_style_tokens) == (4, num_style)
    for group, module in (("content_image_proj", projections.content), ("style_image_proj", projections.style)):
        loaded = module.state_dict()
        assert set(loaded) == set(state[group])
        assert all(torch.equal(loaded[k], state[group][k]) for k in loaded)
    processors = list(unet.attn_processors.items())
    for key, tensor in state["ip_adapter"].items():
        index, proj, _ = key.split(".")
        name, processor = processors[int(index)]
        assert name.endswith("attn2.processor") and processor.image_tokens == UNET_ROUTES[name.split(".")[0]]
        assert torch.equal(getattr(processor, proj).weight, tensor)
    controlnet_processors = controlnet.attn_processors
    for key, tensor in state["controlnet_adapter_modules"].items():
        head, proj = key.rsplit(".", 2)[:2]
        processor = list(controlnet_processors.values())[int(head)] if by_index else controlnet_processors[head]
        assert processor.image_tokens == "style"
        assert torch.equal(getattr(processor, proj).weight, tensor)
    tokens = projections.tokens("style", torch.randn(2, 257, 16))
    assert tokens.cond.shape == tokens.uncond.shape == (2, num_style, CROSS_DIM)
    torch.testing.assert_close(tokens.uncond, projections.style(torch.zeros(2, 257, 16)))


def _edit(state, group, old, new=None):
    state[group] = dict(state[group])
    tensor = state[group].pop(old)
    if new is not None:
        state[group][new] = tensor
    return state


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda s: _edit(s, "ip_adapter", "13.to_k_ip.weight", "13.to_k_ip_renamed.weight"),
            r"group 'ip_adapter': 1 missing key \[13.to_k_ip.weight\]",
        ),
        (
            lambda s: _edit(s, "style_image_proj", "layers.1.0.to_kv.weight"),
            r"group 'style_image_proj': 1 missing key \[layers.1.0.to_kv.weight\], 0 unexpected",
        ),
        (
            lambda s: {**s, "content_image_proj": {**s["content_image_proj"], "extra": torch.zeros(1)}},
            r"group 'content_image_proj': 0 missing keys \[\], 1 unexpected key \[extra\]",  # strict as released
        ),
        (
            lambda s: _edit(s, "controlnet_adapter_modules", "3.to_v_ip.weight", "2.to_v_ip.weight"),
            r"group 'controlnet_adapter_modules': 1 missing key \[3.to_v_ip.weight\]",
        ),
        (lambda s: {k: v for k, v in s.items() if k != "ip_adapter"}, r"key groups missing \['ip_adapter'\]"),
    ],
)
def test_mismatched_files_fail_with_listed_keys(tmp_path, models, edit, message):
    unet, controlnet = models
    path = write_csgo_file(tmp_path / "bad.bin", edit(csgo_state(unet, controlnet)))
    with pytest.raises(CSGOWeightsError, match=message) as error:
        load_csgo(path, unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    assert str(path) in str(error.value)


def test_wrong_shapes_and_unreadable_files_fail(tmp_path, models):
    unet, controlnet = models
    state = csgo_state(unet, controlnet)
    state["ip_adapter"]["1.to_k_ip.weight"] = torch.zeros(3, 3)
    with pytest.raises(CSGOWeightsError, match=r"wrong shape \['1.to_k_ip.weight \[3, 3\] != \[16, 16\]'\]"):
        load_csgo(write_csgo_file(tmp_path / "shape.bin", state), unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    (tmp_path / "junk.bin").write_bytes(b"not a torch file")
    with pytest.raises(CSGOWeightsError, match="junk.bin': not a readable torch file"):
        load_csgo(tmp_path / "junk.bin", unet, controlnet)
    torch.save({"ip_adapter": Fraction(1, 3)}, tmp_path / "objects.bin")  # refused by weights_only, in our words
    with pytest.raises(CSGOWeightsError) as refused:
        load_csgo(tmp_path / "objects.bin", unet, controlnet)
    said = load_failure(pickle.UnpicklingError())
    assert str(refused.value).endswith(f"objects.bin': not a readable torch file ({said})")
    with pytest.raises(CSGOWeightsError, match="does not exist"):
        load_csgo(tmp_path / "absent.bin", unet, controlnet)


def _save_safetensors(state: dict, path):
    from safetensors.torch import save_file

    save_file({f"{group}.{key}": t.contiguous() for group, keys in state.items() for key, t in keys.items()}, path)
    return path


@pytest.mark.parametrize("suffix", [".bin", ".safetensors"])
def test_file_saved_by_the_released_class_loads_without_unet_content(tmp_path, models, caplog, suffix):
    """The released class's down blocks are text-only: its files hold only the up blocks' ip_adapter entries."""
    unet, controlnet = models
    state = csgo_state(unet, controlnet, unet_content=False)
    assert set(state["ip_adapter"]) == set(routed_keys(unet, UNET_ROUTES, "style"))
    path = tmp_path / f"released{suffix}"
    _save_safetensors(state, path) if suffix == ".safetensors" else write_csgo_file(path, state)
    with caplog.at_level(logging.INFO, logger="artnvg_core.diffusion.csgo_weights"):
        projections = load_csgo(path, unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    assert not projections.unet_content
    for name, processor in unet.attn_processors.items():
        if name.endswith("attn2.processor"):
            assert processor.image_tokens == {"down_blocks": None, "up_blocks": "style", "mid_block": None}[
                name.split(".")[0]]
    assert processor_key_layout(unet).keys() == state["ip_adapter"].keys()
    assert all(torch.equal(p, state["ip_adapter"][k]) for k, p in processor_key_layout(unet).items())
    controlnet_state = state["controlnet_adapter_modules"]
    assert all(torch.equal(p, controlnet_state[k]) for k, p in processor_key_layout(controlnet).items())
    [record] = caplog.records
    assert record.levelno == logging.INFO and "UNet content entries absent" in record.getMessage()
    assert "keyed by processor index" in record.getMessage() and str(path) in record.getMessage()


def test_ignores_what_the_released_loader_ignores_with_a_warning(tmp_path, models, caplog):
    """Other top-level groups, keys no layer reads and an incomplete set of content entries are dropped, named."""
    unet, controlnet = models
    state = csgo_state(unet, controlnet)
    state["image_proj"] = {"proj.weight": torch.zeros(2, 2)}
    state["ip_adapter"]["200.to_k_ip.weight"] = torch.zeros(2, 2)
    del state["ip_adapter"]["1.to_k_ip.weight"]
    path = write_csgo_file(tmp_path / "extra.bin", state)
    with caplog.at_level(logging.WARNING, logger="artnvg_core.diffusion.csgo_weights"):
        projections = load_csgo(path, unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    assert not projections.unet_content
    messages = "\n".join(r.getMessage() for r in caplog.records)
    assert "ignored key groups ['image_proj']" in messages
    assert "only 11 of the 12 UNet content entries; all ignored (missing [1.to_k_ip.weight])" in messages
    assert "group 'ip_adapter': ignored 12 keys" in messages and "200.to_k_ip.weight" in messages


def test_module_path_controlnet_group_also_loads_controlnet_weights(tmp_path, models, caplog):
    """Keyed by module path, the group goes through controlnet.load_state_dict in the released loader:
    any ControlNet weight it holds is loaded too (with its shape checked)."""
    unet, controlnet = models
    state = csgo_state(unet, controlnet, controlnet_by_index=False)
    weight = torch.randn(controlnet.conv_in.weight.shape)
    state["controlnet_adapter_modules"]["conv_in.weight"] = weight
    with caplog.at_level(logging.INFO, logger="artnvg_core.diffusion.csgo_weights"):
        load_csgo(write_csgo_file(tmp_path / "cn.bin", state), unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)
    assert torch.equal(controlnet.conv_in.weight, weight)
    assert "1 other ControlNet weight replaced" in caplog.records[-1].getMessage()
    state["controlnet_adapter_modules"]["conv_in.weight"] = torch.zeros(1)
    with pytest.raises(CSGOWeightsError, match=r"'controlnet_adapter_modules': .*wrong shape \['conv_in.weight \[1\]"):
        load_csgo(write_csgo_file(tmp_path / "cn.bin", state), unet, controlnet, dim_head=RESAMPLER_HEAD_WIDTH)


def _text_image_context(batch: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(batch, 77 + 4 + 8, CROSS_DIM, generator=generator)


def _record_attn2_inputs(model, run) -> dict[str, torch.Tensor]:
    inputs = {}
    hooks = [
        module.register_forward_hook(lambda m, args, out, name=name: inputs.setdefault(name, args[0].detach()))
        for name, module in model.named_modules()
        if name.endswith("attn2")
    ]
    run()
    for hook in hooks:
        hook.remove()
    return inputs


def test_tokens_reach_only_their_blocks(tmp_path, models):
    """Each attn2 layer, fed its recorded input, changes with content tokens only in UNet down blocks
    and with style tokens only in UNet up blocks and ControlNet down blocks."""
    unet, controlnet = models
    load_csgo(
        write_csgo_file(tmp_path / "c.bin", csgo_state(unet, controlnet)),
        unet,
        controlnet,
        dim_head=RESAMPLER_HEAD_WIDTH,
    )
    control = attention_kwargs(
        AttentionControl(num_content_tokens=4, num_style_tokens=8, content_scale=1.0, style_scale=1.0)
    )
    context = _text_image_context(2)
    latents, hint = torch.randn(2, 4, 8, 8), torch.rand(2, 3, 64, 64)
    added = {"text_embeds": torch.randn(2, 8), "time_ids": torch.tensor([[64.0, 64, 0, 0, 64, 64]] * 2)}
    runs = {
        "unet": (unet, lambda: unet(latents, 10, context, added_cond_kwargs=added, cross_attention_kwargs=control)),
        "controlnet": (
            controlnet,
            lambda: controlnet(latents, 10, context, hint, added_cond_kwargs=added, cross_attention_kwargs=control),
        ),
    }
    reach = {("unet", "content"): "down_blocks", ("unet", "style"): "up_blocks", ("controlnet", "style"): "down_blocks"}
    for model_name, (model, run) in runs.items():
        with torch.no_grad():
            inputs = _record_attn2_inputs(model, run)
            assert len(inputs) == len([n for n in model.attn_processors if "attn2" in n])
            for kind, tokens in (("content", slice(77, 81)), ("style", slice(81, 89))):
                perturbed = context.clone()
                perturbed[:, tokens] += 1.0
                for name, hidden in inputs.items():
                    layer = model.get_submodule(name)
                    changed = not torch.equal(layer(hidden, context, **control), layer(hidden, perturbed, **control))
                    assert changed == (reach.get((model_name, kind)) == name.split(".")[0]), (model_name, kind, name)


def test_zero_scales_and_single_views_equal_the_base_model(models):
    unet, _ = models
    latents = torch.randn(3, 4, 8, 8)
    added = {"text_embeds": torch.randn(3, 8), "time_ids": torch.tensor([[64.0, 64, 0, 0, 64, 64]] * 3)}
    context = _text_image_context(3)
    with torch.no_grad():
        unet.set_attn_processor(AttnProcessor2_0())
        base = unet(latents, 500, context[:, :77], added_cond_kwargs=added).sample
        install_processors(unet, UNET_ROUTES)
        control = AttentionControl(
            views_per_group=1, num_content_tokens=4, num_style_tokens=8, content_scale=0.0, style_scale=0.0
        )
        ours = unet(
            latents, 500, context, added_cond_kwargs=added, cross_attention_kwargs=attention_kwargs(control)
        ).sample
    torch.testing.assert_close(ours, base, rtol=0, atol=1e-6)


def test_groups_in_one_batch_stay_independent(models):
    """UNet with NV attention over a batch of 2 groups x 3 views: perturbing group 2 leaves group 1 unchanged."""
    unet, _ = models
    install_processors(unet, UNET_ROUTES, image_branches=False)
    latents = torch.randn(6, 4, 8, 8)
    added = {"text_embeds": torch.randn(6, 8), "time_ids": torch.tensor([[64.0, 64, 0, 0, 64, 64]] * 6)}
    context = _text_image_context(6)[:, :77]
    control = attention_kwargs(AttentionControl(views_per_group=3))
    with torch.no_grad():
        before = unet(latents, 500, context, added_cond_kwargs=added, cross_attention_kwargs=control).sample
        latents[4] += 1.0
        after = unet(latents, 500, context, added_cond_kwargs=added, cross_attention_kwargs=control).sample
    torch.testing.assert_close(after[:3], before[:3], rtol=0, atol=1e-6)
    assert all((after[b] - before[b]).abs().max() > 1e-4 for b in (3, 5))
