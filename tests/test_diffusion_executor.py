"""GroupExecutor: two CPU Ray workers reproduce stylize_groups bit for bit, also when one is killed mid-group.

The workers import this module (by the name pytest gave it; Ray passes sys.path on) to find the
loader, so it stays a module-level function.
"""

import dataclasses
import functools
import itertools
import os
import signal
import tempfile
import time
from pathlib import Path

import pytest
import torch

from artnvg_core.cluster import Workers
from artnvg_core.diffusion.conditioning import prepare_conditioning
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


def load_tiny_models(kill_flag: str, device: torch.device):
    """Tiny CSGO models (the same weights in every process). The first UNet call in any worker after
    the file ``kill_flag`` appears removes it and kills that worker's process: a crash mid-group."""
    with tempfile.TemporaryDirectory() as folder:
        models = tiny_models(Path(folder))

    def crash_if_flagged(module, inputs):
        try:
            os.remove(kill_flag)
        except FileNotFoundError:
            return
        os.kill(os.getpid(), signal.SIGKILL)

    models.base.unet.register_forward_pre_hook(crash_if_flagged)
    return models


def _images(count: int, seed: int) -> torch.Tensor:
    return torch.rand(count, 64, 64, 3, generator=torch.Generator().manual_seed(seed))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(models, images, conditioning, one-device output, kill flag path)."""
    flag = str(tmp_path_factory.mktemp("executor") / "kill")
    models = load_tiny_models(flag, torch.device("cpu"))
    style = _images(1, seed=9)
    conditioning = prepare_conditioning(models, style, "a painting", None)
    images = _images(GROUPS.num_views, seed=0)
    output = stylize_groups(models, images, GROUPS, conditioning, SETTINGS, seed=SEED)
    return style, images, conditioning, output, flag


@pytest.fixture(scope="module")
def executor(ray_local, reference):
    from artnvg_core.diffusion.executor import GroupExecutor

    with GroupExecutor(functools.partial(load_tiny_models, reference[4]), Workers("cpu", 2)) as executor:
        yield executor


def _run(executor, reference, **options):
    _, images, conditioning, _, _ = reference
    return executor.stylize_groups(images, GROUPS, conditioning, SETTINGS, seed=SEED, **options)


def test_models_that_cannot_load_raise_the_workers_error(ray_local, tmp_path):
    """Its one worker fits beside the module's executor of two (the session's Ray has three CPU slots)."""
    from artnvg_core.diffusion.executor import GroupExecutor
    from artnvg_core.diffusion.model_files import ModelFiles
    from artnvg_core.diffusion.loader import DiffusionModelsUnavailable, load_models_for

    missing = ModelFiles(sdxl=tmp_path / "no-sdxl", controlnet=tmp_path, image_encoder=tmp_path, csgo=tmp_path)
    with GroupExecutor(functools.partial(load_models_for, missing, False), Workers("cpu", 1)) as executor:
        with pytest.raises(DiffusionModelsUnavailable, match="diffusion models could not be loaded: .*no-sdxl"):
            executor.describe()


def test_two_workers_match_one_device_bit_for_bit_with_progress(executor, reference):
    calls = []
    out = _run(executor, reference, progress=lambda step, total, info: calls.append((step, total, info)))
    assert torch.equal(out, reference[3])
    total = len(GROUPS) * SETTINGS.steps
    steps = [c[0] for c in calls]
    assert steps == sorted(set(steps)) and steps[-1] == total and {c[1] for c in calls} == {total}
    assert {c[2]["group"] for c in calls} <= {0, 1, 2} and all(c[2]["groups"] == 3 for c in calls)
    assert len({c[2]["device"] for c in calls}) == 2 and all(c[2]["device"].startswith("cpu on ") for c in calls)


def test_workers_hold_their_next_group_sample_one_at_a_time_and_record_when(executor, reference):
    """Four groups on two workers: each gets its second group while it samples its first."""
    style, images, conditioning, _, flag = reference
    pairs = ViewGroups([ViewGroup((0, 1)), ViewGroup((2, 3)), ViewGroup((4, 5)), ViewGroup((6,), context=(0,))], 7)
    models = load_tiny_models(flag, torch.device("cpu"))
    expected = stylize_groups(models, images, pairs, conditioning, SETTINGS, seed=SEED)
    begin = time.time()
    assert torch.equal(executor.stylize_groups(images, pairs, conditioning, SETTINGS, seed=SEED), expected)
    end = time.time()
    stats = executor.stats()
    tasks = [task for worker in stats for task in worker["tasks"] if task[1] >= begin]
    assert sorted(group for group, _, _ in tasks) == [0, 1, 2, 3]  # each group once, on some worker
    assert all(begin <= start <= stop <= end for _, start, stop in tasks)
    for worker in stats:
        assert worker["busy_s"] == pytest.approx(sum(stop - start for _, start, stop in worker["tasks"]))
        assert worker["peak_gib"] is None and worker["worker"].startswith("cpu on ")
        # a worker holds its next group while it samples one, but samples one at a time
        spans = sorted((start, stop) for _, start, stop in worker["tasks"])
        assert all(stop <= next_start for (_, stop), (next_start, _) in zip(spans, spans[1:]))


def test_conditioning_from_a_worker_equals_the_local_one(executor, reference):
    def tensors(value):
        if isinstance(value, torch.Tensor):
            return [value]
        return [t for field in dataclasses.fields(value) for t in tensors(getattr(value, field.name))]

    theirs = tensors(executor.conditioning(reference[0], "a painting", None))
    mine = tensors(reference[2])
    assert len(theirs) == len(mine) >= 5 and all(torch.equal(a, b) for a, b in zip(theirs, mine))


def _wait_until_every_worker_answers(executor, timeout: float = 120.0) -> None:
    """Ray restarts a killed worker in the background: the module's other tests (in any order) need it back."""
    from ray.exceptions import ActorUnavailableError

    deadline = time.monotonic() + timeout
    while True:
        try:
            executor.describe()
            return
        except ActorUnavailableError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def test_worker_killed_mid_group_is_replaced_and_the_result_unchanged(executor, reference):
    Path(reference[4]).touch()
    try:
        out = _run(executor, reference, group_indices=[2, 0, 1])
    finally:
        _wait_until_every_worker_answers(executor)
    assert not Path(reference[4]).exists()  # a worker did die
    assert torch.equal(out, reference[3])


def test_one_group_or_none(executor, reference):
    _, images, _, output, _ = reference
    out = _run(executor, reference, group_indices=[1])
    owned = list(GROUPS[1].views)
    others = [v for v in range(GROUPS.num_views) if v not in owned]
    assert torch.equal(out[owned], output[owned]) and torch.equal(out[others], images[others])
    assert torch.equal(_run(executor, reference, group_indices=[]), images)


def test_stop_request_cancels_the_workers(executor, reference):
    polls = itertools.count()
    begin = time.perf_counter()
    with pytest.raises(Cancelled):
        _run(executor, reference, should_stop=lambda: next(polls) == 1)
    assert time.perf_counter() - begin < 5
    owned = list(GROUPS[0].views)  # the workers go on working
    assert torch.equal(_run(executor, reference, group_indices=[0])[owned], reference[3][owned])


@pytest.mark.parametrize("chosen", [[0, 3], [1, 1]])
def test_bad_group_indices_raise(executor, reference, chosen):
    with pytest.raises(ValueError, match="group_indices must be distinct indices below 3"):
        _run(executor, reference, group_indices=chosen)
