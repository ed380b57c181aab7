"""LoRAs fused into SDXL at load time: parsing FILE[:STRENGTH], checking the file, and the weights' change
compared with the delta computed here from the file (float64), in kohya's and diffusers' key layouts."""

from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from artnvg_core.diffusion.lora import LoRA, LoRAError, check_lora, parse_lora
from artnvg_core.diffusion.models import load_sdxl
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import diffusers_pipeline, kohya_lora_deltas, kohya_lora_state, tiny_base, tiny_scheduler


@pytest.fixture(scope="module")
def sdxl(tmp_path_factory):
    """(a tiny SDXL diffusers folder, the SDXLBase it was written from, a kohya LoRA file for it, its state)."""
    pytest.importorskip("peft")  # the optional [lora] extra
    root = tmp_path_factory.mktemp("lora")
    base = tiny_base()
    diffusers_pipeline(base, tiny_scheduler()).save_pretrained(root / "sdxl")
    state = kohya_lora_state(base, rank=2, alpha=1.0)
    save_file(state, str(root / "kohya.safetensors"))
    return root / "sdxl", base, root / "kohya.safetensors", state


def _weights(path: Path, loras=()) -> dict[str, torch.Tensor]:
    base = load_sdxl(path, dtype=torch.float32, loras=tuple(loras))
    return {f"{part}.{key}": value.double() for part in ("unet", "text_encoder", "text_encoder_2")
            for key, value in getattr(base, part).state_dict().items()}


def _assert_changed_by(after: dict, before: dict, deltas: dict) -> None:
    assert after.keys() == before.keys()
    for key in before:
        expected = before[key] + deltas.get(key, 0.0)
        torch.testing.assert_close(after[key], expected, rtol=0, atol=1e-5, msg=key)


@pytest.mark.parametrize(("text", "path", "strength"), [
    ("a.safetensors", "a.safetensors", 1.0), ("dir/a.safetensors:0.5", "dir/a.safetensors", 0.5),
    ("a.safetensors:-1", "a.safetensors", -1.0), ("C:\\loras\\a.safetensors", "C:\\loras\\a.safetensors", 1.0),
    ("a.safetensors:0", "a.safetensors", 0.0)])
def test_parse_lora_splits_file_and_strength(text, path, strength):
    assert parse_lora(text) == LoRA(Path(path), strength)


@pytest.mark.parametrize(("text", "message"), [
    ("a.safetensors:strong", "--lora 'a.safetensors:strong': strength 'strong' is not a number"),
    ("a.safetensors:nan", "--lora 'a.safetensors:nan': strength must be a finite number"),
    ("a.safetensors:inf", "--lora 'a.safetensors:inf': strength must be a finite number")])
def test_a_bad_strength_is_refused_naming_it(text, message):
    with pytest.raises(LoRAError, match=message):
        parse_lora(text)
    with pytest.raises(ValueError, match="strength must be a finite number"):
        LoRA(Path("a.safetensors"), float("nan"))


def test_without_peft_a_lora_is_refused_naming_the_package_to_install(tmp_path, monkeypatch):
    import importlib.util

    lora = tmp_path / "style.safetensors"
    save_file({"lora_unet_x.lora_down.weight": torch.zeros(2, 4)}, str(lora))
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: None if name == "peft" else find_spec(name, *args))
    with pytest.raises(LoRAError, match=f"LoRA '{lora}': LoRAs are applied through the peft package, which is not "
                                        r'installed: pip install "peft>=0\.21" in the Python that runs ArtNVG'):
        check_lora(LoRA(lora))


def test_a_file_that_is_not_a_lora_is_refused_naming_it(tmp_path, sdxl):
    folder, _, _, _ = sdxl
    not_lora = tmp_path / "unet.safetensors"
    save_file({"conv_in.weight": torch.zeros(2, 2)}, str(not_lora))
    (tmp_path / "broken.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json")
    (tmp_path / "lora.bin").write_bytes(b"")
    cases = [(tmp_path / "missing.safetensors", "no such file"), (tmp_path / "lora.bin", "expected a .safetensors"),
             (tmp_path, "a folder, not a file"),  # was "no such file"
             (tmp_path / "broken.safetensors", "not a readable .safetensors"),
             (not_lora, r"not a LoRA \(tensors without 'lora' in their names, e.g. \['conv_in.weight'\]")]
    for path, message in cases:
        with pytest.raises(LoRAError, match=f"LoRA '{path}': {message}"):
            check_lora(LoRA(path))
    # a LoRA for another model: names of no SDXL model, of no layer, or of a layer of another shape
    stranger = tmp_path / "stranger.safetensors"
    save_file({"lora_transformer_x.lora_down.weight": torch.zeros(2, 4),
               "lora_transformer_x.lora_up.weight": torch.zeros(4, 2)}, str(stranger))
    misfit = tmp_path / "misfit.safetensors"
    save_file({"lora_unet_input_blocks_4_1_transformer_blocks_0_attn1_to_q.lora_down.weight": torch.zeros(2, 5),
               "lora_unet_input_blocks_4_1_transformer_blocks_0_attn1_to_q.lora_up.weight": torch.zeros(5, 2)},
              str(misfit))
    nowhere = tmp_path / "nowhere.safetensors"
    save_file({"lora_unet_nowhere.lora_down.weight": torch.zeros(2, 4),
               "lora_unet_nowhere.lora_up.weight": torch.zeros(4, 2)}, str(nowhere))
    for path, message in [(stranger, "matches no layer of SDXL"), (misfit, "cannot be applied to SDXL"),
                          (nowhere, r"cannot be applied to SDXL \(Target modules \{'nowhere'\} not found")]:
        with pytest.raises(LoRAError, match=f"LoRA '{path}': {message}"):
            load_sdxl(folder, dtype=torch.float32, loras=(LoRA(path),))


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_a_lora_holding_non_finite_values_is_refused_naming_the_tensor(tmp_path, value):
    """Found probing LoRA files: a NaN or an infinity in a LoRA was fused into the weights silently (every image
    of the run would have come out NaN)."""
    pytest.importorskip("peft")
    path = tmp_path / "nan.safetensors"
    up = torch.zeros(4, 2)
    up[1, 1] = value
    save_file({"lora_unet_x.lora_down.weight": torch.zeros(2, 4), "lora_unet_x.lora_up.weight": up,
               "lora_unet_x.alpha": torch.tensor(2.0)}, str(path))
    with pytest.raises(LoRAError, match=f"LoRA '{path}': tensor 'lora_unet_x.lora_up.weight' holds NaN or infinite"):
        check_lora(LoRA(path))


def test_a_kohya_lora_adds_strength_times_its_delta_and_loras_stack(tmp_path, sdxl):
    folder, base, kohya, state = sdxl
    deltas = kohya_lora_deltas(base, state)
    assert any(k.startswith("unet.") for k in deltas) and any(k.startswith("text_encoder_2.") for k in deltas)
    before = _weights(folder)
    _assert_changed_by(_weights(folder, [LoRA(kohya, 0.0)]), before, {})
    _assert_changed_by(_weights(folder, [LoRA(kohya, 0.7)]), before, {k: 0.7 * d for k, d in deltas.items()})

    # a second LoRA of another rank and alpha, on the same layers: the changes add up
    other = kohya_lora_state(base, rank=3, alpha=6.0, seed=11)
    save_file(other, str(tmp_path / "other.safetensors"))
    other_deltas = kohya_lora_deltas(base, other)
    both = {k: 0.5 * deltas[k] - 0.25 * other_deltas[k] for k in deltas}
    _assert_changed_by(_weights(folder, [LoRA(kohya, 0.5), LoRA(tmp_path / "other.safetensors", -0.25)]), before,
                       both)


def test_a_lora_in_diffusers_layout_changes_the_unet_alike(tmp_path, sdxl, caplog):
    """diffusers' own layout (``unet.<module>.lora_A/lora_B``, scale 1): the same delta as kohya's file
    whose alpha equals its rank; diffusers' notices that it leaves the text encoders alone are dropped."""
    folder, base, _, _ = sdxl
    state = kohya_lora_state(base, rank=2, alpha=2.0, seed=12)
    deltas = {k: d for k, d in kohya_lora_deltas(base, state).items() if k.startswith("unet.")}
    generator = torch.Generator().manual_seed(13)
    peft_state = {}
    for key in deltas:
        module = key.removesuffix(".weight")
        out_features, in_features = deltas[key].shape
        down, up = torch.randn(2, in_features, generator=generator), torch.randn(out_features, 2, generator=generator)
        peft_state[f"{module}.lora_A.weight"], peft_state[f"{module}.lora_B.weight"] = down, up
        deltas[key] = up.double() @ down.double()
    save_file(peft_state, str(tmp_path / "diffusers.safetensors"))
    before = _weights(folder)
    with caplog.at_level("INFO"):
        after = _weights(folder, [LoRA(tmp_path / "diffusers.safetensors", 2.0)])
    _assert_changed_by(after, before, {k: 2.0 * d for k, d in deltas.items()})
    assert not [r for r in caplog.records if "LoRA" in r.getMessage()]
