"""Models loaded once per process: the same key returns the kept set; another key, an edited file or
forget_models loads afresh and lets the old set go."""

import gc
import os
import weakref

import pytest

from artnvg_core.diffusion.model_cache import file_key, forget_models, load_once
from artnvg_core.diffusion.model_files import ModelFiles
from artnvg_core.progress import Cancelled
from artnvg_core.diffusion.loader import load_models_for
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import write_model_files


class _Models:  # a stand-in that can be weakly referenced
    pass


@pytest.fixture(autouse=True)
def empty_cache():
    forget_models()
    yield
    forget_models()


def test_same_key_loads_once_another_key_drops_the_kept_set():
    loads = []

    def load():
        loads.append(1)
        return _Models()

    first = load_once(("a", 1), load)
    assert load_once(("a", 1), load) is first and len(loads) == 1
    kept = weakref.ref(first)
    del first
    second = load_once(("a", 2), load)
    gc.collect()
    assert len(loads) == 2 and kept() is None  # only one set is kept
    assert load_once(("a", 2), load) is second
    forget_models()
    assert load_once(("a", 2), load) is not second and len(loads) == 3


def test_a_failing_load_keeps_nothing():
    def fail():
        raise OSError("disk")

    load_once("k", _Models)
    with pytest.raises(OSError, match="disk"):
        load_once("other", fail)
    calls = []
    load_once("k", lambda: calls.append(1) or _Models())
    assert calls == [1]


def test_file_key_follows_every_file_of_a_folder(tmp_path):
    folder = tmp_path / "model"
    (folder / "unet").mkdir(parents=True)
    weights = folder / "unet" / "weights.bin"
    weights.write_bytes(b"1234")
    key = file_key(folder)
    assert file_key(folder) == key and file_key(None) is None
    os.utime(weights, ns=(weights.stat().st_atime_ns, weights.stat().st_mtime_ns + 10**9))
    assert file_key(folder) != key
    key = file_key(folder)
    (folder / "config.json").write_text("{}")
    assert file_key(folder) != key
    assert file_key(weights) != file_key(folder) and file_key(tmp_path / "missing") == (str(tmp_path / "missing"), ())


def test_load_models_for_reuses_the_loaded_models_until_a_file_changes(tmp_path):
    paths = ModelFiles(**write_model_files(tmp_path))
    models = load_models_for(paths, False, "cpu")
    assert load_models_for(paths, False, "cpu") is models
    low = load_models_for(paths, True, "cpu")
    assert low is not models and load_models_for(paths, True, "cpu") is low
    csgo = paths.csgo
    os.utime(csgo, ns=(csgo.stat().st_atime_ns, csgo.stat().st_mtime_ns + 10**9))
    assert load_models_for(paths, True, "cpu") is not low


def test_load_models_for_fuses_the_loras_and_keys_them_by_file_and_strength(tmp_path):
    """The LoRAs reach the loaded UNet; another strength loads afresh; a bad LoRA is the user's error (a
    LoRAError), not a missing model the command line would fall back from."""
    import torch
    from safetensors.torch import save_file

    from artnvg_core.diffusion.lora import LoRA, LoRAError
    from artnvg_core.diffusion.loader import DiffusionModelsUnavailable
    from diffusion_tiny import kohya_lora_deltas, kohya_lora_state, tiny_base

    pytest.importorskip("peft")  # the optional [lora] extra
    paths = ModelFiles(**write_model_files(tmp_path))
    state = kohya_lora_state(tiny_base())
    save_file(state, str(tmp_path / "lora.safetensors"))
    key, delta = next((k, d) for k, d in kohya_lora_deltas(tiny_base(), state).items() if k.startswith("unet."))
    weight = lambda models: models.base.unet.state_dict()[key.removeprefix("unet.")].double()  # noqa: E731
    plain = weight(load_models_for(paths, False, "cpu"))
    half = load_models_for(paths, False, "cpu", loras=(LoRA(tmp_path / "lora.safetensors", 0.5),))
    assert load_models_for(paths, False, "cpu", loras=(LoRA(tmp_path / "lora.safetensors", 0.5),)) is half
    torch.testing.assert_close(weight(half), plain + 0.5 * delta, rtol=0, atol=1e-5)
    full = load_models_for(paths, False, "cpu", loras=(LoRA(tmp_path / "lora.safetensors"),))
    torch.testing.assert_close(weight(full), plain + delta, rtol=0, atol=1e-5)
    save_file({"lora_transformer_x.lora_down.weight": torch.zeros(2, 4)}, str(tmp_path / "flux.safetensors"))
    with pytest.raises(LoRAError, match="flux.safetensors") as raised:
        load_models_for(paths, False, "cpu", loras=(LoRA(tmp_path / "flux.safetensors"),))
    assert not isinstance(raised.value, DiffusionModelsUnavailable)


def test_a_stop_while_loading_is_a_cancel_not_a_missing_model(tmp_path):
    """A stop during loading stays :class:`Cancelled` (the command line would otherwise fall back to the
    NNFM stylizer as if a model were missing), and nothing is kept for the next call."""
    paths = ModelFiles(**write_model_files(tmp_path))
    with pytest.raises(Cancelled):
        load_models_for(paths, False, "cpu", should_stop=lambda: True)
    steps = []
    load_models_for(paths, False, "cpu", progress=lambda done, total, info: steps.append(info.get("loading")))
    assert steps == ["SDXL", "ControlNet", "image encoder", "CSGO", None]
