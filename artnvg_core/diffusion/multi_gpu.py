"""Stylizing the groups of a scene on several devices at once: one worker process per device.

Groups are independent (each has its own seed and its own neighbouring-view attention), so
:func:`stylize_groups_on_devices` hands them to worker processes, one per device, started with
``torch.multiprocessing``'s "spawn" context (safe with CUDA). Each worker loads its own full copy
of the models, takes the next group from a shared task queue (largest groups first, so the devices
finish at about the same time) and stylizes it as :func:`stylize_groups` does; the parent assembles
the owned views in view order and aggregates progress.

Tensors travel between processes through shared memory (``/dev/shm`` must hold the content images
and the results in flight; in Docker use ``--shm-size`` or ``--ipc=host``).
"""

from __future__ import annotations

import dataclasses
import queue
import traceback
from collections.abc import Callable, Sequence

import torch
import torch.multiprocessing as mp

from ..grouping import ViewGroups
from ..progress import Cancelled, ProgressFn, StopFn, check_stop
from .conditioning import StyleConditioning
from .images import check_images
from .models import DiffusionModels
from .sampler import SamplerSettings
from .stylize import stylize_groups, stylize_owned_views

_POLL_SECONDS = 0.1  # how often the parent checks should_stop and the workers' liveness
_JOIN_SECONDS = 10.0  # how long a worker may take to exit after a completed run before it is terminated


def stylize_groups_on_devices(
    load_models: Callable[[torch.device], DiffusionModels],
    images: torch.Tensor,
    groups: ViewGroups,
    conditioning: StyleConditioning,
    settings: SamplerSettings = SamplerSettings(),
    *,
    devices: Sequence[str | torch.device],
    seed: int = 0,
    group_indices: Sequence[int] | None = None,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """:func:`stylize_groups` with the chosen groups (default: all) spread over ``devices``.

    * ``load_models(device)`` returns the models on ``device``; it runs once in each worker, so it
      must be picklable (a module-level function or a ``functools.partial`` of one). Every worker
      holds a full copy of the models: each device needs the memory of a one-device run.
    * Same contract as :func:`stylize_groups`: returns a copy of ``images`` [V, H, W, 3] (CPU) with
      every view owned by a chosen group replaced; group ``g`` uses seed ``seed + g`` whichever
      device runs it, so the result equals a one-device run on the same kind of device (bit for
      bit where the kernels are deterministic; on the CPU, with the same thread count).
    * One worker per device, at most one per chosen group; one device runs in this process (no
      worker). Devices may repeat (several workers on one device).
    * progress(step, total, info) counts denoising steps over all chosen groups and devices; info
      holds "group", "groups" and "device". should_stop is checked while waiting: when it returns
      True the workers are terminated and :class:`Cancelled` is raised. A worker's exception is
      raised here as RuntimeError naming its device, with the worker's traceback; the other workers
      are terminated. (If the other workers finish every group before the error arrives, the
      complete result is returned.) After a completed run the workers exit by themselves.
    """
    devices = _check_devices(devices)
    images = check_images(images, "stylize_groups_on_devices: images")
    chosen = list(range(len(groups))) if group_indices is None else [int(g) for g in group_indices]
    if any(not 0 <= g < len(groups) for g in chosen) or len(set(chosen)) != len(chosen):
        raise ValueError(
            f"stylize_groups_on_devices: group_indices must be distinct indices below {len(groups)}, got {chosen}"
        )
    if not chosen:
        return images.clone()
    devices = devices[: len(chosen)]  # no worker without a group
    if len(devices) == 1:
        device = devices[0]

        def report(step: int, total: int, info: dict) -> None:
            if progress is not None:
                progress(step, total, {**info, "device": str(device)})

        return stylize_groups(load_models(device), images, groups, _moved(conditioning, device), settings,
                              seed=seed, group_indices=chosen, progress=report, should_stop=should_stop)

    context = mp.get_context("spawn")
    tasks, results, finished = context.Queue(), context.Queue(), context.Event()
    for index in sorted(chosen, key=lambda g: -len(groups[g].all_views)):
        tasks.put(index)
    for _ in devices:
        tasks.put(None)
    shared = (load_models, images, groups, _moved(conditioning, torch.device("cpu")), settings, seed)
    workers = [
        context.Process(target=_work, args=(device, *shared, tasks, results, finished), name=f"artnvg-stylize-{device}")
        for device in devices
    ]
    completed = False
    try:
        for worker in workers:
            worker.start()
        output = _collect(images, groups, chosen, settings.steps, workers, results, progress, should_stop)
        completed = True
        return output
    finally:
        finished.set()
        for worker in workers:
            if worker.pid is not None:
                worker.join(_JOIN_SECONDS if completed else 0)  # after a failure nothing more is needed
                if worker.is_alive():
                    worker.terminate()
                    worker.join()
        for channel in (tasks, results):
            channel.cancel_join_thread()
            channel.close()


def _check_devices(devices) -> list[torch.device]:
    if isinstance(devices, (str, torch.device)) or not isinstance(devices, Sequence) or not devices:
        raise ValueError(
            f"stylize_groups_on_devices: devices must be a non-empty list of devices such as ['cuda:0', 'cuda:1'], "
            f"got {devices!r}"
        )
    parsed = []
    for device in devices:
        try:
            parsed.append(torch.device(device))
        except (RuntimeError, TypeError) as error:
            raise ValueError(f"stylize_groups_on_devices: devices holds {device!r}, not a device: {error}") from None
        if parsed[-1].type == "cuda" and (parsed[-1].index or 0) >= torch.cuda.device_count():
            raise ValueError(
                f"stylize_groups_on_devices: devices holds {device!r}, but {torch.cuda.device_count()} CUDA devices "
                "are visible"
            )
    return parsed


def _moved(value, device: torch.device):
    """``value`` (a tensor, or a dataclass of tensors, dataclasses and None) on ``device``."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if dataclasses.is_dataclass(value):
        return dataclasses.replace(
            value, **{field.name: _moved(getattr(value, field.name), device) for field in dataclasses.fields(value)}
        )
    return value


def _collect(images, groups, chosen, steps, workers, results, progress, should_stop) -> torch.Tensor:
    """Receive every chosen group's views from the workers and place them into a copy of ``images``."""
    output = images.clone()
    steps_done = dict.fromkeys(chosen, 0)
    remaining = set(chosen)
    while remaining:
        check_stop(should_stop)
        try:
            kind, device, *payload = results.get(timeout=_POLL_SECONDS)
        except queue.Empty:
            for worker in workers:
                if not worker.is_alive():
                    raise RuntimeError(
                        f"stylize_groups_on_devices: the worker {worker.name} exited unexpectedly "
                        f"(exit code {worker.exitcode})"
                    ) from None
            continue
        if kind == "error":
            raise RuntimeError(f"stylize_groups_on_devices: the worker on {device} failed:\n{payload[0]}")
        if kind == "progress":
            step, info = payload
            steps_done[info["group"]] = step
            if progress is not None:
                progress(sum(steps_done.values()), len(chosen) * steps, {**info, "device": device})
        else:  # "group"
            index, views = payload
            output[list(groups[index].views)] = views
            remaining.discard(index)
    return output


def _work(device, load_models, images, groups, conditioning, settings, seed, tasks, results, finished) -> None:
    """Worker process: stylize groups taken from ``tasks`` until the None sentinel, send their owned views.

    It then waits for ``finished`` before exiting: the tensors it sent live in its shared memory until
    the parent has received them. It stops early when the parent process is gone.
    """
    parent = mp.parent_process()

    def stopped() -> bool:
        return finished.is_set() or not parent.is_alive()

    name = str(device)
    try:
        if device.type == "cuda":
            torch.cuda.set_device(device)
        models = load_models(device)
        conditioning = _moved(conditioning, device)
        for index in iter(tasks.get, None):

            def report(step: int, total: int, info: dict, index: int = index) -> None:
                results.put(("progress", name, step, {**info, "group": index, "groups": len(groups)}))

            views = stylize_owned_views(models, images, groups, index, conditioning, settings, seed=seed,
                                        progress=report, should_stop=stopped)
            results.put(("group", name, index, views))
    except Cancelled:
        pass
    except Exception:
        results.put(("error", name, traceback.format_exc()))
    while not finished.wait(_POLL_SECONDS) and parent.is_alive():
        pass
