"""Device choice (CLI --device, the nodes' device and fallback), with CUDA and MPS availability faked."""

import pytest
import torch

from artnvg_core.cli.options import parse_device
from artnvg_core.devices import DEVICE_CHOICES, best_device, device_for
from nodes.comfy_bridge import compute_device


@pytest.fixture
def machine(monkeypatch):
    """Set which accelerators this machine seems to have: machine(cuda=..., mps=...)."""

    def fake(*, cuda: bool, mps: bool) -> None:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
        monkeypatch.setattr(torch.backends.mps, "is_available", lambda: mps)

    return fake


@pytest.mark.parametrize("cuda, mps, expected", [
    (True, True, "cuda"), (True, False, "cuda"), (False, True, "mps"), (False, False, "cpu"),
])
def test_auto_prefers_cuda_then_mps_then_cpu(machine, cuda, mps, expected):
    machine(cuda=cuda, mps=mps)
    assert best_device() == device_for("auto") == parse_device("auto") == torch.device(expected)
    assert compute_device() == torch.device(expected)  # the nodes' fallback outside ComfyUI


def test_named_devices_must_be_present(machine):
    machine(cuda=False, mps=True)
    assert device_for("mps") == torch.device("mps") and device_for("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match=r"^--device cuda: no CUDA device is available$"):
        parse_device("cuda")
    machine(cuda=True, mps=False)
    assert device_for("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(ValueError, match=r"^mps: Apple's MPS backend is not available"):
        device_for("mps")
    with pytest.raises(ValueError, match=r"'tpu' is not a device"):
        device_for("tpu")


def test_every_device_input_offers_mps():
    from artnvg_core.cli.main import build_parser

    assert "mps" in DEVICE_CHOICES
    parser = build_parser()
    for command in ("render", "stylize", "evaluate"):
        assert parser.parse_args([command, *COMMAND_ARGS[command], "--device", "mps"]).device == "mps"


COMMAND_ARGS = {
    "render": ["s.ply", "--cameras", "t.json", "--out", "o"],
    "stylize": [],
    "evaluate": ["--original", "a.ply", "--stylized", "b.ply", "--cameras", "t.json", "--style", "s.jpg"],
}
