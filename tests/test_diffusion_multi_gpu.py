"""stylize_groups_on_devices: two CPU worker processes reproduce stylize_groups bit for bit.

Spawned workers import this module (by the name pytest gave it; spawn passes sys.path on) to
find the loaders, so they stay module-level functions.
"""

import itertools
import multiprocessing
import tempfile
import time
from pathlib import Path

import pytest
import torch

from artnvg_core.diffusion.conditioning import prepare_conditioning
from artnvg_core.diffusion.multi_gpu import stylize_groups_on_devices
from artnvg_core.diffusion.sampler import SamplerSettings
from artnvg_core.diffusion.stylize import stylize_groups
from artnvg_core.grouping import ViewGroup, ViewGroups
from artnvg_core.progress import Cancelled
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import tiny_models

SETTINGS = SamplerSettings(steps=2, guidance_scale=5.0, resolution=None)
SEED = 5
# sizes 3, 2 + 1 context view, 2: unequal groups, one borrowing a view it does not own
GROUPS = ViewGroups([ViewGroup((0, 3, 5)), ViewGroup((1, 2), context=(0,)), ViewGroup((4, 6))], num_views=7)


def load_tiny_models(device: torch.device):
    """Tiny CSGO models (same weights in every process), one intra-op thread as in this test process."""
    if device.type != "cpu":
        raise ValueError(f"no tiny models for {device}")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        return tiny_models(Path(folder))


def load_on_cpu_never(device: torch.device):
    """A CPU worker that never finishes loading, so only the other worker's error can arrive."""
    if device.type == "cpu":
        time.sleep(3600)
    return load_tiny_models(device)


def _images(count: int, seed: int) -> torch.Tensor:
    return torch.rand(count, 64, 64, 3, generator=torch.Generator().manual_seed(seed))


@pytest.fixture(scope="module")
def scene():
    """(models, images, conditioning, one-device reference output)."""
    models = load_tiny_models(torch.device("cpu"))
    conditioning = prepare_conditioning(models, _images(1, seed=9), "a painting", None)
    images = _images(GROUPS.num_views, seed=0)
    reference = stylize_groups(models, images, GROUPS, conditioning, SETTINGS, seed=SEED)
    return models, images, conditioning, reference


def _run(scene, devices, loader=load_tiny_models, **options):
    _, images, conditioning, _ = scene
    return stylize_groups_on_devices(loader, images, GROUPS, conditioning, SETTINGS, devices=devices, seed=SEED,
                                     **options)


def test_two_workers_match_one_device_bit_for_bit(scene):
    calls = []
    out = _run(scene, ["cpu", "cpu"], progress=lambda step, total, info: calls.append((step, total, info)))
    assert torch.equal(out, scene[3])
    assert not multiprocessing.active_children()
    total = len(GROUPS) * SETTINGS.steps
    assert len(calls) == total and {c[1] for c in calls} == {total}
    assert [c[0] for c in calls] == list(range(1, total + 1))
    assert {c[2]["group"] for c in calls} == {0, 1, 2}
    assert all(c[2]["groups"] == 3 and c[2]["device"] == "cpu" for c in calls)


@pytest.mark.parametrize("devices, chosen", [([torch.device("cpu")], [2, 0]), (["cpu", "cpu"], [1])])
def test_one_device_or_one_group_runs_in_process(scene, devices, chosen):
    """A lambda loader cannot reach a worker: these calls must not spawn any."""
    models, images, _, reference = scene
    calls = []
    out = _run(scene, devices, lambda device: models, group_indices=chosen, progress=lambda *c: calls.append(c))
    owned = [v for g in chosen for v in GROUPS[g].views]
    others = [v for v in range(GROUPS.num_views) if v not in owned]
    assert torch.equal(out[owned], reference[owned]) and torch.equal(out[others], images[others])
    total = len(chosen) * SETTINGS.steps
    assert [c[:2] for c in calls] == [(step, total) for step in range(1, total + 1)]
    assert all(c[2]["device"] == "cpu" for c in calls)


def test_no_group_needs_no_models(scene):
    assert torch.equal(_run(scene, ["cpu", "meta"], group_indices=[]), scene[1])


def test_worker_error_names_device_and_traceback(scene):
    """The worker on "meta" fails to load; its error surfaces and the (hanging) CPU worker is terminated."""
    with pytest.raises(RuntimeError, match=r"worker on meta failed:\nTraceback") as error:
        _run(scene, ["cpu", "meta"], load_on_cpu_never)
    assert "in load_tiny_models" in str(error.value) and "ValueError: no tiny models for meta" in str(error.value)
    assert not multiprocessing.active_children()


def test_stop_request_while_waiting_cancels(scene):
    polls = itertools.count()
    begin = time.perf_counter()
    with pytest.raises(Cancelled):
        _run(scene, ["cpu", "cpu"], should_stop=lambda: next(polls) == 3)
    assert time.perf_counter() - begin < 5  # workers (still starting) terminated, not awaited
    assert not multiprocessing.active_children()


@pytest.mark.parametrize(
    "devices, options, message",
    [
        ([], {}, "devices must be a non-empty list"),
        ("cpu", {}, "devices must be a non-empty list"),
        (["cpu", "gpu"], {}, "devices holds 'gpu', not a device"),
        ([f"cuda:{torch.cuda.device_count()}"], {}, "CUDA devices are visible"),
        (["cpu"], {"group_indices": [0, 3]}, "group_indices must be distinct indices below 3"),
        (["cpu"], {"group_indices": [1, 1]}, "group_indices must be distinct indices below 3"),
    ],
)
def test_bad_arguments_raise(scene, devices, options, message):
    with pytest.raises(ValueError, match=message):
        _run(scene, devices, **options)
