"""Stylizing a scene's groups on several devices at once: Ray actors, one per device, each holding the models once.

Groups are independent (each has its own seed and its own neighbouring-view attention), so a
:class:`GroupExecutor` hands them to its workers as tasks, largest first, each task carrying only its
group's views, and each worker gets its next group while it samples one (its inputs arrive meanwhile).
Group ``g`` is sampled with seed ``seed + g`` whichever worker runs it, and the views
come back into view order, so the result equals a one-device run of the same groups on the same kind
of device (bit for bit where the kernels are deterministic; on the CPU, with one thread as every CPU
worker has). The groups do not depend on the number of workers: with ``G`` groups on ``W`` workers the
last round leaves ``W - G mod W`` of them idle unless G is a multiple of W, which
:func:`~artnvg_core.grouping.group_views`'s ``multiple`` gives when asked (``stylize --group-multiple``).
A group whose worker dies (a killed process, a lost machine) is handed to another worker, with the
same seed: the result is unchanged. Needs Ray (``pip install "ray>=2.30"``; :mod:`artnvg_core.cluster`).
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np
import torch

from ..cluster import WorkerPool, Workers, dispatch, from_wire, import_ray, ray_session, to_wire
from ..grouping import ViewGroups
from ..progress import ProgressFn, StopFn
from ..tensor_tree import map_tensors
from .conditioning import StyleConditioning, prepare_conditioning
from .images import check_images
from .models import DiffusionModels
from .sampler import SamplerSettings, stylize_group
from .stylize import group_members


class GroupWorker:
    """Ray actor holding the models of ``load_models(device)`` on its device; three threads: two take
    groups in turn (one samples while the next one's inputs arrive), one answers progress and stop
    requests. A failed load is raised by every later call."""

    def __init__(self, load_models: Callable[[torch.device], DiffusionModels], workers: Workers):
        self.device = workers.device()
        if self.device.type == "cuda":
            torch.cuda.set_device(self.device)
        else:
            torch.set_num_threads(1)
        self.steps: tuple[str, int, int] | None = None  # (run, group, steps done) of the group being sampled
        self.stopped: set[str] = set()
        self.sampling = threading.Lock()  # one group at a time on the device
        self.tasks: list[tuple[int, float, float]] = []  # (group, start, end) of each group stylized, Unix time
        try:
            self.models, self.error = load_models(self.device), None
        except Exception as error:  # raised to the caller by describe(), conditioning() and stylize()
            self.models, self.error = None, error

    def _check(self) -> None:
        if self.error is not None:
            raise self.error

    def describe(self) -> str:
        """Where this worker runs, e.g. ``cuda (GPU 3) on 10.0.0.2, pid 4242``."""
        import ray

        self._check()
        gpus = ray.get_gpu_ids()
        where = f"{self.device.type}" + (f" (GPU {','.join(map(str, gpus))})" if gpus else "")
        return f"{where} on {ray.util.get_node_ip_address()}, pid {os.getpid()}"

    def ping(self) -> bool:
        return True

    def conditioning(self, style_image: torch.Tensor | None, prompt: str, negative_prompt: str | None) -> StyleConditioning:
        """:func:`prepare_conditioning` with this worker's models, returned on the CPU."""
        self._check()
        return map_tensors(torch.Tensor.cpu, prepare_conditioning(self.models, style_image, prompt, negative_prompt))

    def stylize(self, run: str, index: int, members: np.ndarray, centers: np.ndarray | None, owned: int,
                conditioning: StyleConditioning, settings: SamplerSettings, seed: int) -> np.ndarray:
        """Group ``index`` sampled with ``seed`` from its ``members`` [M, H, W, 3] (owned views first; camera
        ``centers`` [M, 3] or None, :func:`~artnvg_core.diffusion.stylize.group_members`; both as
        :func:`~artnvg_core.cluster.to_wire` sends them): its ``owned`` stylized views, the same way.
        Stops when ``run`` is stopped."""
        self._check()

        def report(step: int, total: int, info: dict) -> None:
            self.steps = (run, index, step)

        with self.sampling:
            start = time.time()
            try:
                views = stylize_group(self.models, from_wire(members),
                                      map_tensors(lambda t: t.to(self.device), conditioning), settings, seed=seed,
                                      view_centers=from_wire(centers), progress=report,
                                      should_stop=lambda: run in self.stopped)
                return to_wire(views[:owned])
            finally:
                self.tasks.append((index, start, time.time()))

    def stats(self) -> dict:
        """"worker" (:meth:`describe`), "tasks" (``(group, start, end)`` of every group stylized so far, Unix
        time in seconds), "busy_s" (their total seconds) and "peak_gib" (the most GPU memory allocated so
        far, GiB; None on the CPU)."""
        peak = torch.cuda.max_memory_allocated(self.device) / 2**30 if self.device.type == "cuda" else None
        busy = sum(end - start for _, start, end in self.tasks)
        return {"worker": self.describe(), "tasks": list(self.tasks), "busy_s": busy, "peak_gib": peak}

    def progress(self) -> tuple[str, int, int] | None:
        return self.steps

    def stop(self, run: str) -> None:
        self.stopped.add(run)


class GroupExecutor(WorkerPool):
    """``workers.count`` :class:`GroupWorker` actors (a :class:`~artnvg_core.cluster.WorkerPool`).

    ``load_models(device)`` runs once in each worker, so it must be picklable (a module-level function
    or a ``functools.partial`` of one); every device needs the memory of a one-device run. The workers
    load at once, in parallel; the first call that needs them waits.
    """

    def __init__(self, load_models: Callable[[torch.device], DiffusionModels], workers: Workers):
        super().__init__(GroupWorker, workers, load_models, workers, threads=3)

    def describe(self) -> list[str]:
        """Where each worker runs (waits until they are loaded; raises a worker's load error)."""
        ray = import_ray("GroupExecutor")
        return ray.get([actor.describe.remote() for actor in self.actors])

    def stats(self) -> list[dict]:
        """Per worker: where it runs, the groups it stylized and when, the seconds that took and its peak GPU
        memory (:meth:`GroupWorker.stats`)."""
        ray = import_ray("GroupExecutor")
        return ray.get([actor.stats.remote() for actor in self.actors])

    def conditioning(self, style_image: torch.Tensor | None, prompt: str, negative_prompt: str | None) -> StyleConditioning:
        """:func:`prepare_conditioning` on the first worker (on the CPU)."""
        ray = import_ray("GroupExecutor")
        style_image = map_tensors(torch.Tensor.cpu, style_image)  # or None
        return ray.get(self.actors[0].conditioning.remote(style_image, prompt, negative_prompt))

    def stylize_groups(
        self,
        images: torch.Tensor,
        groups: ViewGroups,
        conditioning: StyleConditioning,
        settings: SamplerSettings = SamplerSettings(),
        *,
        seed: int = 0,
        group_indices: Sequence[int] | None = None,
        progress: ProgressFn | None = None,
        should_stop: StopFn | None = None,
    ) -> torch.Tensor:
        """:func:`~artnvg_core.diffusion.stylize.stylize_groups` with the chosen groups (default: all) spread
        over the workers: a copy of ``images`` [V, H, W, 3] (CPU) with every view owned by a chosen
        group replaced, equal to the one-device result.

        progress(step, total, info) counts denoising steps over the chosen groups, sampled every
        :data:`~artnvg_core.cluster.POLL_SECONDS` (not every step); info holds "group" (the latest),
        "groups" and "device" (where it ran). should_stop is checked as often: the workers stop at their
        next step and :class:`~artnvg_core.progress.Cancelled` is raised. A group's own error is
        raised as it was raised in the worker, after the other workers were told to stop.
        """
        ray = import_ray("GroupExecutor")
        images = check_images(images, "GroupExecutor.stylize_groups: images")
        chosen = list(range(len(groups))) if group_indices is None else [int(g) for g in group_indices]
        if any(not 0 <= g < len(groups) for g in chosen) or len(set(chosen)) != len(chosen):
            raise ValueError(f"GroupExecutor.stylize_groups: group_indices must be distinct indices below "
                             f"{len(groups)}, got {chosen}")
        output = images.clone()
        if not chosen:
            return output
        run = uuid.uuid4().hex
        shared = ray.put(map_tensors(torch.Tensor.cpu, conditioning))
        largest_first = sorted(chosen, key=lambda g: -len(groups[g].all_views))
        meter = _StepMeter(self.actors, run, chosen, settings.steps, len(groups), progress)

        def submit(actor, index: int):
            members, centers = group_members(images, groups, index)
            return actor.stylize.remote(run, index, to_wire(members), to_wire(centers), len(groups[index].views),
                                        shared, settings, seed + index)

        try:
            for index, actor, views, error in dispatch(self.actors, largest_first, submit, on_start=meter.started,
                                                       on_tick=meter.poll, should_stop=should_stop, per_actor=2):
                if error is not None:
                    raise error
                output[list(groups[index].views)] = from_wire(views)
                meter.finished(index, actor)
        finally:
            for actor in self.actors:
                actor.stop.remote(run)  # no-op for a finished run; stops the others at their next step
        return output


class _StepMeter:
    """Progress of one run over the workers: polls each busy worker's step count (one request in flight each)."""

    def __init__(self, actors, run: str, chosen: list[int], steps: int, groups: int, progress: ProgressFn | None):
        self.actors, self.run, self.steps, self.groups, self.progress = actors, run, steps, groups, progress
        self.done = dict.fromkeys(chosen, 0)
        self.busy: Counter[int] = Counter()  # actor -> groups it holds
        self.polls: dict[int, object] = {}  # actor -> progress reference
        self.where: dict[int, str] = {}
        self.reported = 0

    def started(self, index: int, actor: int) -> None:
        self.busy[actor] += 1

    def finished(self, index: int, actor: int) -> None:
        self.busy[actor] -= 1
        if self.busy[actor] <= 0:
            del self.busy[actor]
        self.done[index] = self.steps
        self._report(index, actor)

    def poll(self) -> None:
        if self.progress is None:
            return
        ray = import_ray("GroupExecutor")
        for actor, reference in list(self.polls.items()):
            ready, _ = ray.wait([reference], timeout=0)
            if ready:
                del self.polls[actor]
                try:
                    state = ray.get(reference)
                except Exception:  # a dead worker: its group is handed out again
                    continue
                if state is not None and state[0] == self.run and self.done[state[1]] < state[2]:
                    self.done[state[1]] = state[2]
                    self._report(state[1], actor)
        for actor in self.busy:
            if actor not in self.polls:
                self.polls[actor] = self.actors[actor].progress.remote()

    def _report(self, index: int, actor: int) -> None:
        total = sum(self.done.values())
        if self.progress is not None and total != self.reported:
            self.reported = total
            if actor not in self.where:
                ray = import_ray("GroupExecutor")
                self.where[actor] = ray.get(self.actors[actor].describe.remote())
            self.progress(total, len(self.done) * self.steps,
                          {"group": index, "groups": self.groups, "device": self.where[actor]})


def stylize_on_workers(
    load_models: Callable[[torch.device], DiffusionModels],
    images: torch.Tensor,
    groups: ViewGroups,
    style_image: torch.Tensor | None,
    prompt: str,
    negative_prompt: str | None,
    settings: SamplerSettings = SamplerSettings(),
    *,
    devices: Sequence[str | torch.device] | None = None,
    address: str | None = None,
    seed: int = 0,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Every group of ``images`` [V, H, W, 3] stylized by a :class:`GroupExecutor` in a
    :func:`~artnvg_core.cluster.ray_session` of ``devices`` / ``address``; the conditioning is prepared
    on the first worker. Returns the stylized views (CPU) in view order."""
    needed_by = "--ray-address" if address else "--devices"
    with ray_session(devices, address, needed_by=needed_by) as workers, GroupExecutor(load_models, workers) as executor:
        conditioning = executor.conditioning(style_image, prompt, negative_prompt)
        return executor.stylize_groups(images, groups, conditioning, settings, seed=seed, progress=progress,
                                       should_stop=should_stop)
