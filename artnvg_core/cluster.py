"""Ray, the optional engine behind several devices and machines (``pip install "ray>=2.30"``; from a clone,
``pip install -e ".[cluster]"``).

* :func:`ray_session` joins a running cluster (``address``: ``"auto"`` or ``"HOST:PORT"``), uses a Ray
  already initialised in this process, or starts a local Ray instance with exactly the given devices
  (``cuda:0,cuda:1``: no cluster set-up needed); it yields the :class:`Workers` to start.
* :func:`ray_joined` only joins a running cluster (or uses this process's Ray): for what starts no
  workers (:func:`release_workers`).
* :func:`to_wire` and :func:`from_wire`: a tensor as a task's argument or result (a NumPy array, which
  Ray passes through its shared store without pickling) and back.
* :class:`WorkerPool` holds the worker actors, its own or, kept, named ones that outlive it (a later pool
  of a later process reuses those alive, so their imports and loaded models); :func:`kept_workers` names
  the kept ones and :func:`release_workers` ends them. :func:`dispatch` hands tasks to them in the order
  given, one at a time per actor or, with ``per_actor=2``, the next one while it runs one (so that
  the next task's inputs reach it meanwhile; the actor runs them in turn). A task whose actor died (a
  killed process, a lost machine) is handed again to the next idle actor; the dead actor restarts by
  itself (``max_restarts``) and rejoins once it answers.
* :func:`job_alive`: whether a driver (a command using the cluster) still runs.

Ray is imported here, and only when one of these is called: without it installed nothing else changes.
Actors see only the GPU Ray gave them, as ``cuda:0``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

RAY_REQUIREMENT = "ray>=2.30"  # the [cluster] extra's (pyproject.toml), named in the message when Ray is missing

from .counted import counted
from .progress import StopFn, check_stop

RESTARTS = 1  # how often Ray restarts a worker actor whose process died
ATTEMPTS = 3  # how often one task is handed out before it counts as failed
POLL_SECONDS = 0.1  # how often dispatch checks should_stop and calls on_tick
PROBES = 3  # how often a worker that lost its task is asked whether it is back before it is given up
KEPT_NAMESPACE = "artnvg"  # the Ray namespace of kept workers (WorkerPool's keep)


class RayUnavailable(ValueError):
    """Ray is needed but not installed (the message says how to install it)."""


class WorkerLost(RuntimeError):
    """A task's worker died every time it was handed out."""


def import_ray(needed_by: str):
    """The ``ray`` module; :class:`RayUnavailable` naming ``needed_by`` when it is not installed."""
    try:
        import ray
    except ImportError as error:
        raise RayUnavailable(f"{needed_by} needs Ray, which is not installed: pip install \"{RAY_REQUIREMENT}\" in "
                             "the Python that runs ArtNVG (ComfyUI's, for the nodes)") from error
    return ray


@dataclass(frozen=True)
class Workers:
    """``count`` worker actors of ``kind`` ``"cuda"`` (one GPU each) or ``"cpu"`` (one CPU core and one
    thread each: a stand-in for tests and machines without a GPU)."""

    kind: str
    count: int

    def actor_options(self) -> dict:
        """Ray resources and restarts of one worker actor."""
        gpus = 1 if self.kind == "cuda" else 0
        return dict(num_cpus=1, num_gpus=gpus, max_restarts=RESTARTS)

    def device(self) -> torch.device:
        """The device inside a worker actor: its one GPU (Ray shows it as ``cuda:0``) or the CPU."""
        return torch.device("cuda", 0) if self.kind == "cuda" else torch.device("cpu")


def plan_workers(devices: Sequence[str | torch.device] | None, option: str = "--devices") -> Workers | None:
    """The workers for ``devices`` (all CUDA or all CPU; a GPU at most once), None for None.

    ValueError naming ``option`` for a mixture, another kind of device or a repeated GPU."""
    if devices is None:
        return None
    parsed = [torch.device(d) for d in devices]
    kinds = {d.type for d in parsed}
    if not parsed or len(kinds) > 1 or kinds - {"cuda", "cpu"}:
        raise ValueError(f"{option}: expected CUDA devices such as cuda:0,cuda:1 (or cpu,cpu: one CPU worker each), "
                         f"got {','.join(map(str, parsed)) or 'none'}")
    if "cuda" in kinds:
        indices = [d.index or 0 for d in parsed]
        if len(set(indices)) != len(indices):
            raise ValueError(f"{option}: a GPU appears twice in {','.join(map(str, parsed))}; each worker holds one")
    return Workers(kinds.pop(), len(parsed))


@contextlib.contextmanager
def ray_session(devices: Sequence[str | torch.device] | None = None, address: str | None = None,
                *, needed_by: str = "--devices") -> Iterator[Workers]:
    """Ray connected for the block; yields the workers to start.

    * ``address`` given: joins that cluster; the workers are ``devices``' count and kind, else one per
      GPU of the cluster.
    * Ray already initialised in this process: used as it is, workers as with ``address``.
    * Otherwise a new local Ray instance is started with exactly ``devices`` (default: every visible GPU,
      else one CPU worker): for ``cuda:2,cuda:3`` Ray sees those two GPUs only. It is started even where
      a cluster runs that a bare ``ray.init()`` would join (one from ``ray start --head`` on this machine,
      or the ``RAY_ADDRESS`` environment variable's): only ``address`` joins one (``"auto"``: the one
      ``RAY_ADDRESS`` names, else this machine's).

    What the block started it shuts down (disconnects from a cluster); Ray's actors of this process go
    with it, kept workers (:class:`WorkerPool`) of a cluster it joined stay.
    """
    ray = import_ray(needed_by)
    workers = plan_workers(devices)
    if address or ray.is_initialized():
        with ray_joined(address, needed_by=needed_by):
            yield workers or _cluster_gpus(ray, address)
        return
    workers = workers or _local_default()
    _start_local(ray, workers, devices)
    try:
        yield workers
    finally:
        ray.shutdown()


@contextlib.contextmanager
def ray_joined(address: str | None, *, needed_by: str) -> Iterator[Any]:
    """The ``ray`` module connected for the block to the running cluster at ``address`` (``"auto"`` or
    ``"HOST:PORT"``), or as this process already is; disconnects what it connected."""
    ray = import_ray(needed_by)
    joined = not ray.is_initialized()
    if joined:
        _init(ray, address=address)
    try:
        yield ray
    finally:
        if joined:
            ray.shutdown()


_QUIET = dict(include_dashboard=False, logging_level=logging.WARNING, log_to_driver=True)
# Ray's notice, as a local cluster starts (or one found with "auto" is joined), that it turned token authentication
# on: Ray made the token itself (~/.ray/auth_token), nothing for our users to do. Ray 2.5x on logs it as a warning.
TOKEN_NOTICE_LOGGER = "ray._private.authentication.authentication_token_setup"
TOKEN_NOTICE = "Token authentication is enabled for this Ray cluster"


def _init(ray, **options) -> None:
    """``ray.init(**options)`` quietly: no dashboard, Ray's own INFO lines hidden and its token notice
    (:data:`TOKEN_NOTICE`) dropped; its other warnings and errors, and what the workers print, still shown."""
    logger = logging.getLogger(TOKEN_NOTICE_LOGGER)

    def not_the_token_notice(record: logging.LogRecord) -> bool:
        return TOKEN_NOTICE not in record.getMessage()

    logger.addFilter(not_the_token_notice)
    try:
        ray.init(**options, **_QUIET)
    finally:
        logger.removeFilter(not_the_token_notice)


def _local_default() -> Workers:
    count = torch.cuda.device_count()
    return Workers("cuda", count) if count else Workers("cpu", 1)


def _start_local(ray, workers: Workers, devices) -> None:
    """A new local Ray instance with ``workers``' resources (``address="local"``: not a running cluster that
    Ray would otherwise join, which refuses resources); for CUDA devices only the GPUs named are visible
    to it (Ray's GPU list is the CUDA_VISIBLE_DEVICES of the process that starts it)."""
    if workers.kind == "cpu":
        _init(ray, address="local", num_cpus=workers.count, num_gpus=0)
        return
    indices = [torch.device(d).index or 0 for d in devices] if devices else list(range(workers.count))
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    physical = visible.split(",") if visible else [str(i) for i in range(torch.cuda.device_count())]
    if max(indices) >= len(physical):
        raise ValueError(f"--devices: cuda:{max(indices)} asked for, but this process sees "
                         f"{counted(len(physical), 'CUDA device')}")
    try:
        os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(physical[i] for i in indices)
        _init(ray, address="local", num_gpus=len(indices))
    finally:
        if visible is None:
            del os.environ["CUDA_VISIBLE_DEVICES"]
        else:
            os.environ["CUDA_VISIBLE_DEVICES"] = visible


def _cluster_gpus(ray, address: str | None) -> Workers:
    count = int(ray.cluster_resources().get("GPU", 0))
    if not count:
        raise ValueError(f"the Ray cluster {address or '(already connected)'} has no GPU; "
                         "give --devices cpu,cpu,... to run on CPU workers")
    return Workers("cuda", count)


def to_wire(tensor: torch.Tensor | None) -> np.ndarray | torch.Tensor | None:
    """``tensor`` as a Ray task's argument or result: a NumPy array on the CPU, the same bits, which Ray
    copies into its shared store as a raw buffer that the other process reads in place (a tensor it
    pickles, storage and all: 0.15-0.2 s against 0.01-0.03 s for a task's 50 MB of views). bfloat16,
    which NumPy lacks, stays a tensor; None stays None. :func:`from_wire` undoes it."""
    if tensor is None or tensor.dtype == torch.bfloat16:
        return tensor
    return tensor.detach().cpu().numpy()


def from_wire(value: np.ndarray | torch.Tensor | None) -> torch.Tensor | None:
    """The tensor :func:`to_wire` sent: a CPU tensor of its own memory (Ray's arrays are read-only
    views of its store, so an array is copied)."""
    return torch.tensor(value) if isinstance(value, np.ndarray) else value


class WorkerPool:
    """``workers.count`` Ray actors of class ``worker``, each built with ``args`` and given ``threads``
    threads (one per task it holds at once, one more to answer progress and stop requests); leaving the
    ``with`` block, or :meth:`close`, ends them and frees their memory. Ray must be connected
    (:func:`ray_session`).

    ``keep``: the actors are named ``CLASS-KIND-INDEX`` (``BatchWorker-cuda-0``) in the Ray namespace
    :data:`KEPT_NAMESPACE` and detached, so they outlive the pool and its process: a later pool of the
    same class and kind takes those alive, warm (imports done, models loaded), and starts only the missing
    ones (never started, or dead for good). They hold their memory, a GPU's models, until
    :func:`release_workers` or ``ray stop``; they run the code they imported when they started.
    """

    def __init__(self, worker: type, workers: Workers, *args, threads: int = 2, keep: bool = False):
        ray = import_ray(worker.__name__)
        actor, options = ray.remote(worker), dict(workers.actor_options(), max_concurrency=threads)
        if keep:
            options.update(namespace=KEPT_NAMESPACE, lifetime="detached", get_if_exists=True)
        self.keep = keep
        names = [f"{worker.__name__}-{workers.kind}-{index}" if keep else None for index in range(workers.count)]
        self.actors = [actor.options(**options, name=name).remote(*args) for name in names]

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Ends the actors, unless kept; the pool holds none after."""
        if self.keep:
            self.actors = []
        else:
            self.kill()

    def kill(self) -> None:
        """Ends the actors, kept or not (a later pool starts new ones in place of kept ones)."""
        ray = import_ray("WorkerPool")
        for actor in self.actors:
            ray.kill(actor)
        self.actors = []


def kept_workers() -> list[str]:
    """The names of the kept workers (:class:`WorkerPool`'s ``keep``) of the cluster Ray is connected to,
    whichever process started them, sorted."""
    ray = import_ray("kept_workers")
    return sorted(actor["name"] for actor in ray.util.list_named_actors(all_namespaces=True)
                  if actor["namespace"] == KEPT_NAMESPACE)


def release_workers() -> list[str]:
    """Ends every kept worker of the cluster Ray is connected to (:func:`ray_joined`); returns their names."""
    ray = import_ray("release_workers")
    names = kept_workers()
    for name in names:
        ray.kill(ray.get_actor(name, namespace=KEPT_NAMESPACE))
    return names


def job_alive(job_id: str) -> bool:
    """Whether the Ray job ``job_id`` (hex, ``ray.get_runtime_context().get_job_id()``: a driver process, such
    as a command) still runs on the cluster this process is in; True for "" (not known). Read from the GCS
    job table, which marks a driver dead within a second even when it was killed (Ray's public job listing
    needs its dashboard)."""
    if not job_id:
        return True
    import_ray("job_alive")
    from ray._private.state import jobs

    return not any(job["JobID"] == job_id and job["IsDead"] for job in jobs())


def dispatch(
    actors: Sequence[Any],
    tasks: Sequence[Any],
    submit: Callable[[Any, Any], Any],
    *,
    on_start: Callable[[Any, int], None] | None = None,
    on_tick: Callable[[], None] | None = None,
    should_stop: StopFn | None = None,
    per_actor: int = 1,
) -> Iterator[tuple[Any, int, Any, BaseException | None]]:
    """Run ``tasks`` on ``actors``; yields ``(task, actor index, value, error)`` as each task ends.

    * ``submit(actor, task)`` starts a task and returns its Ray object reference; tasks are handed out
      in the order given, each actor holding at most ``per_actor`` at once: to an actor that holds none
      first, and to one that holds some only while at least one task per actor waits (so the last
      round goes to whichever actors free first, and none waits behind another's queued task).
    * ``error`` is the task's own exception (value None) or :class:`WorkerLost` when its actor died
      :data:`ATTEMPTS` times with it. A task whose actor died is handed out again first; the actor is
      asked (its ``ping`` method) whether it is back before it gets more work.
    * ``on_start(task, actor index)`` after each hand-out; ``on_tick()`` every :data:`POLL_SECONDS`.
      ``should_stop`` is checked as often: :class:`~artnvg_core.progress.Cancelled` is raised and
      the tasks still running are left to the caller (stop or kill the actors).
    * RuntimeError when every actor is gone with tasks left.
    """
    ray = import_ray("dispatch")
    from ray.exceptions import ActorDiedError, RayActorError, RayTaskError

    queue = deque(range(len(tasks)))
    handed = [0] * len(tasks)
    idle = deque(list(range(len(actors))) * per_actor)  # an actor's free places
    running: dict[Any, tuple[int, int]] = {}  # reference -> (task, actor)
    probing: dict[Any, tuple[int, int]] = {}  # ping reference -> (actor, probes so far)

    def next_actor() -> int | None:
        holding = Counter(actor for _, actor in running.values())
        for place, actor in enumerate(idle):
            if not holding[actor]:
                del idle[place]
                return actor
        return idle.popleft() if len(queue) >= len(actors) else None

    while queue or running:
        check_stop(should_stop)
        while queue and idle:
            actor = next_actor()
            if actor is None:
                break
            task = queue.popleft()
            handed[task] += 1
            running[submit(actors[actor], tasks[task])] = (task, actor)
            if on_start is not None:
                on_start(tasks[task], actor)
        if not running and not probing:
            raise RuntimeError(f"dispatch: every worker died; {counted(len(queue), 'task')} left")
        ready, _ = ray.wait([*running, *probing], num_returns=1, timeout=POLL_SECONDS)
        for reference in ready:
            if reference in probing:
                actor, probes = probing.pop(reference)
                try:
                    ray.get(reference)
                    idle.append(actor)
                except ActorDiedError:
                    pass  # restarts used up: gone for good
                except RayActorError:
                    if probes < PROBES:
                        probing[actors[actor].ping.remote()] = (actor, probes + 1)
                continue
            task, actor = running.pop(reference)
            try:
                value = ray.get(reference)
            except RayActorError as error:  # the actor's process died (or its machine): hand the task out again
                probing[actors[actor].ping.remote()] = (actor, 1)
                if handed[task] < ATTEMPTS:
                    queue.appendleft(task)
                else:
                    yield tasks[task], actor, None, WorkerLost(
                        f"its worker died each of the {ATTEMPTS} times it was handed out (last: {error})")
                continue
            except RayTaskError as error:
                yield tasks[task], actor, None, error.cause if error.cause is not None else error
                idle.append(actor)
                continue
            yield tasks[task], actor, value, None
            idle.append(actor)
        if on_tick is not None:
            on_tick()
