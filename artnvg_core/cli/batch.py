"""``python -m artnvg_core batch JOBS``: many stylize jobs over the GPUs of one machine or of a Ray cluster.

JOBS is a JSON list of objects, or a CSV file with a header row; each job (object or row) gives
``stylize``'s options by name: ``scene``, ``cameras``, ``style``, ``out`` (required), ``stylizer``,
``preset``, ``iters``, ``seed``, ``color_transfer``, ``lora``, ... (``_`` or ``-`` alike; a flag takes
true/false; a repeatable option such as ``lora`` takes one value or, in JSON, a list; an empty value or
null leaves the option out). Jobs are parsed by ``stylize``'s own parser, so every
stylize option works here and none can drift. Relative paths start at the JOBS file's folder. Where
jobs run is the batch's choice (``--devices``, ``--ray-address``), not a job's.

Each job runs whole on one worker (a Ray actor with one GPU, or one CPU core), which keeps the diffusion
models loaded from one job to the next. Jobs start longest first
(:func:`~artnvg_core.cli.batch_jobs.expected_work`), so that no long
job starts last while the other workers idle; each job's line is printed as it finishes (under it, what its
scene files' read and write did to the scenes: their notes), and the summary lists the failed ones in job
order. The diffusion groups of a job run on that worker's GPU (``stylize
--devices`` spreads one scene's groups over several GPUs instead). A job whose worker dies is run again
on another worker; a job that fails (bad input, missing file) fails alone, as does one that would write
over its own inputs or over another job's output or contact sheet (``a.ply`` and ``a.spz`` share
``a.contact.png``), refused before any work; a job whose output scene loads and whose contact sheet
exists, both its own, is skipped (``--redo`` runs it anyway); outputs are written whole or not at all
(:func:`artnvg_core.fileio.written_together`). Ctrl-C or SIGTERM stops the running jobs at their next
Python step; a job that does not get there within 30 s has its worker killed, which may leave a hidden
temporary (``.NAME.*.partial.*``) behind.

With ``--keep-workers`` (and ``--ray-address``: a local Ray that the command starts ends with it) the
workers stay after the batch, named Ray actors of the cluster, and the next batch with ``--keep-workers``
runs on them warm (their imports done, their models loaded: a worker's first job takes about 15 s more on
an H200), starting only those missing or dead. Kept workers hold their models' memory on each GPU (what the
jobs worked in is freed as their batch ends) until ``batch --release-workers --ray-address ADDR`` or ``ray
stop``; they run the code they started with (release them after updating ArtNVG), and one batch at a time
(a job handed to a worker busy with another batch's job fails, unless that batch's command is gone, killed:
its job is stopped first); a batch without --keep-workers waits for the devices they hold (it says so). A
stop (Ctrl-C, SIGTERM) ends the batch's jobs, not its kept workers (unless one is killed for not stopping
within 30 s; the next batch replaces it).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import functools
import os
import re
import sys
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from ..cluster import (POLL_SECONDS, WorkerPool, Workers, dispatch, import_ray, job_alive, kept_workers, ray_joined,
                       ray_session, release_workers)
from ..counted import counted
from ..progress import Cancelled, StopFn
from .batch_jobs import Job, load_jobs, output_complete, parse_stylize, stylize_options
from .common import close_progress_bars, terminate_as_interrupt
from .options import parse_devices

STATUSES = ("done", "failed", "skipped", "cancelled")
STOP_SECONDS = 30.0  # how long stopped jobs may take to unwind before their workers are killed
REST_SECONDS = 10.0  # how long a batch's end waits for its workers to free their cached memory (BatchWorker.rest)


@dataclass(frozen=True)
class JobResult:
    """What became of a job: ``status`` one of :data:`STATUSES`, ``message`` the error or reason,
    ``seconds`` its run time, ``worker`` where it ran, ``peak_gib`` the most GPU memory it allocated
    (GiB; None on the CPU or when it did not run), ``notes`` what its scene files' read and write did to the
    scenes (``load_scene``'s and ``save_scene``'s notes, each once)."""

    job: Job
    status: str
    message: str = ""
    seconds: float = 0.0
    worker: str = ""
    peak_gib: float | None = None
    notes: tuple[str, ...] = ()


class BatchWorker:
    """Ray actor running whole stylize jobs on its device, one at a time, keeping the diffusion models
    between jobs (:func:`artnvg_core.diffusion.loader.load_models_for` keeps the latest set). Three threads: one
    runs the job, one answers ``ping`` (its process id), ``stop`` and ``rest``, and one lets a job wait for the job
    of a batch whose command is gone. A kept worker (``--keep-workers``) serves one batch after another; a job
    handed to it while it runs another batch's fails at once, unless that batch's command is gone (killed): then
    that job is stopped first (:meth:`_take`)."""

    def __init__(self, workers: Workers):
        self.workers = workers
        if workers.kind == "cuda":
            torch.cuda.set_device(workers.device())
        else:
            torch.set_num_threads(1)
        self.lock = threading.Lock()
        self.running: tuple[str, str, int] | None = None  # the running job's (run, its command's Ray job, thread)
        self.stopped: set[str] = set()

    def ping(self) -> int:
        return os.getpid()

    def run(self, run: str, argv: Sequence[str], folder: str, driver: str = "") -> dict:
        """Run one job (``argv``: stylize's arguments; relative paths from ``folder``) of the batch ``run``,
        which the command of Ray job id ``driver`` runs (:meth:`_take`); returns its "status" (done, failed,
        cancelled), "message", "seconds", "worker", "peak_gib" and "notes" (its scene files' notes for the user).
        What else the job prints (stylize's lines and progress bars) is dropped: the batch prints a line per job,
        and its notes."""
        import ray

        worker = f"{self.workers.kind} on {ray.util.get_node_ip_address()}, pid {os.getpid()}"
        start, cwd = time.perf_counter(), os.getcwd()
        notes: list[str] = []
        refused = self._take(run, driver, worker, notes)
        if refused is not None:
            return dict(status=refused[0], message=refused[1], seconds=0.0, worker=worker, peak_gib=None, notes=notes)
        try:
            args = parse_stylize([*argv, f"--device={self.workers.kind}"], "job")
            args.should_stop, args.notes = (lambda: run in self.stopped), notes.append
            if self.workers.kind == "cuda":
                torch.cuda.reset_peak_memory_stats()
            os.chdir(folder)
            with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
                try:
                    args.run(args)
                finally:  # as the command line's: a stopped or failed job's bars end with it, none left open
                    close_progress_bars()
            status, message = "done", ""
        except (Cancelled, KeyboardInterrupt):
            status, message = "cancelled", "stopped by request"
        except Exception as error:
            if run in self.stopped:  # the stop, wrapped by a loader that reports any error as its own
                status, message = "cancelled", "stopped by request"
            elif isinstance(error, (ValueError, OSError)):
                status, message = "failed", str(error)
            else:  # any other failure of one job is that job's, reported with its type
                status, message = "failed", f"{type(error).__name__}: {error}"
        finally:
            with self.lock:
                self.running = None
            os.chdir(cwd)
        peak = torch.cuda.max_memory_allocated() / 2**30 if self.workers.kind == "cuda" else None
        return dict(status=status, message=message, seconds=time.perf_counter() - start, worker=worker, peak_gib=peak,
                    notes=notes)

    def _take(self, run: str, driver: str, worker: str, notes: list[str]) -> tuple[str, str] | None:
        """Marks this worker running a job of ``run``: None; else the (status, message) of the job, which does
        not run: cancelled once ``run`` is stopped, failed while a job of another batch runs (two jobs would
        share the worker's folder). A job of a batch whose command (Ray job ``driver``) is gone, killed without
        stopping its jobs, is stopped first (a note says so) and waited for, :data:`STOP_SECONDS` at most."""
        stopping, deadline = None, 0.0
        while True:
            with self.lock:
                if run in self.stopped:
                    return "cancelled", "stopped by request"
                if self.running is None:
                    self.running = (run, driver, threading.get_ident())
                    return None
                other, other_driver, _ = self.running
            if other != stopping:
                if job_alive(other_driver):
                    return "failed", (f"its worker ({worker}) runs a job of another batch; run batches on kept "
                                      "workers one after another")
                self.stop(other)
                notes.append("its worker first stopped a job left running by a batch whose command is gone")
                stopping, deadline = other, time.monotonic() + STOP_SECONDS
            elif time.monotonic() > deadline:
                return "failed", (f"its worker ({worker}) runs a job left by a batch whose command is gone, which "
                                  f"did not stop within {STOP_SECONDS:.0f} s; end the worker with --release-workers")
            time.sleep(POLL_SECONDS)

    def rest(self) -> None:
        """A batch ended: PyTorch's cached GPU memory that no tensor holds goes back to the GPU
        (``torch.cuda.empty_cache``; nothing on the CPU or before CUDA starts), so that a kept worker waits
        holding its models, not a job's peak. Not while a job runs (a later batch's), nor between a batch's
        jobs: each would allocate its working memory again."""
        with self.lock:
            if self.running is None:
                torch.cuda.empty_cache()

    def stop(self, run: str) -> None:
        """Stop the job of ``run`` if it is running: its stylize stops at its next stop check, and
        :class:`Cancelled` is raised at its next Python step (steps with no check: loading); the jobs of
        ``run`` that start later return at once, cancelled."""
        with self.lock:
            self.stopped.add(run)
            if self.running is not None and self.running[0] == run:
                ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(self.running[2]), ctypes.py_object(Cancelled))


class BatchPool(WorkerPool):
    """``workers.count`` :class:`BatchWorker` actors (a :class:`~artnvg_core.cluster.WorkerPool`, ``keep``: kept
    for later pools); :meth:`run` them over jobs, as often as needed, each run on the workers as the last left
    them (warm)."""

    def __init__(self, workers: Workers, keep: bool = False):
        super().__init__(BatchWorker, workers, workers, threads=3, keep=keep)

    def run(
        self,
        jobs: Sequence[Job],
        *,
        redo: bool = False,
        on_event: Callable[[str, Job, object], None] | None = None,
        should_stop: StopFn | None = None,
    ) -> list[JobResult]:
        """One :class:`JobResult` per job, in job order.

        Jobs with an error fail at once; jobs whose output is complete are skipped (unless ``redo``);
        the others run on the workers, the most :attr:`Job.work` first (in job order where equal).
        ``on_event("started", job, {"worker": i, "actor": actor})`` when a job is handed out (again, if its
        worker died) and ``on_event("finished", job, result)`` for every job. When ``should_stop`` says
        so, or on KeyboardInterrupt (Ctrl-C), the running jobs are stopped (a worker whose job has not
        stopped within :data:`STOP_SECONDS` is killed), and every job not finished is ``cancelled``. At the
        end the workers free their cached GPU memory (:meth:`BatchWorker.rest`).
        """
        ray = import_ray("batch")
        results: dict[int, JobResult] = {}

        def finish(result: JobResult) -> None:
            results[result.job.number] = result
            if on_event is not None:
                on_event("finished", result.job, result)

        todo = []
        for job in jobs:
            if job.error is not None:
                finish(JobResult(job, "failed", job.error))
            elif not redo and output_complete(job.out):
                finish(JobResult(job, "skipped", "output complete"))
            else:
                todo.append(job)
        todo.sort(key=lambda job: job.work, reverse=True)  # a stable sort: equal work keeps job order
        run, running = uuid.uuid4().hex, {}  # job number -> (job, reference) while it runs
        driver = ray.get_runtime_context().get_job_id()

        def submit(actor, job: Job):
            reference = actor.run.remote(run, job.argv, str(job.folder), driver)
            running[job.number] = job, reference
            return reference

        def started(job: Job, index: int) -> None:
            if on_event is not None:
                on_event("started", job, {"worker": index, "actor": self.actors[index]})

        try:
            for job, _, value, error in dispatch(self.actors, todo, submit, on_start=started, should_stop=should_stop):
                running.pop(job.number, None)
                if error is not None:
                    status = "cancelled" if isinstance(error, Cancelled) else "failed"
                    finish(JobResult(job, status, str(error)))
                else:
                    finish(_result(job, value))
        except (Cancelled, KeyboardInterrupt):
            for job, result in self._stop(ray, run, list(running.values())):
                finish(result)
            for job in todo:
                if job.number not in results:
                    finish(JobResult(job, "cancelled", "batch stopped"))
        if self.actors:  # waited for: a command that ends at once could take the calls with it
            ray.wait([actor.rest.remote() for actor in self.actors], num_returns=len(self.actors), timeout=REST_SECONDS)
        return [results[job.number] for job in jobs]

    def _stop(self, ray, run: str, running: list[tuple[Job, object]]) -> list[tuple[Job, JobResult]]:
        """Stop the jobs of ``run`` and wait for them; the results of those that ended (cancelled, or
        done just before). A worker whose job has not ended within :data:`STOP_SECONDS` is killed."""
        for actor in self.actors:
            actor.stop.remote(run)
        ended = []
        if running:
            references = [reference for _, reference in running]
            ready, late = ray.wait(references, num_returns=len(references), timeout=STOP_SECONDS)
            for job, reference in running:
                if reference in ready:
                    try:
                        value = ray.get(reference)
                    except Exception:  # its worker died meanwhile, or the stop came as it returned
                        continue
                    ended.append((job, _result(job, value)))
            if late:  # a job that did not reach a Python step in time: the workers go, kept or not
                self.kill()
        return ended


def _result(job: Job, value: dict) -> JobResult:
    """The result of ``job`` from what :meth:`BatchWorker.run` returned."""
    return JobResult(job, value["status"], value["message"], value["seconds"], value["worker"], value["peak_gib"],
                     tuple(value["notes"]))


def cmd_batch(args: argparse.Namespace, options: dict[str, argparse.Action]) -> int:
    """The ``batch`` command: 0 when every job is done or skipped, 1 when one failed, 130 when stopped
    (Ctrl-C), 143 when terminated (SIGTERM)."""
    from tqdm import tqdm

    if args.release_workers:
        return cmd_release(args)
    if args.jobs is None:
        raise ValueError("batch: give a JOBS file (or --release-workers)")
    if args.keep_workers and not args.ray_address:
        raise ValueError("--keep-workers needs --ray-address: workers are kept by a running Ray cluster (ray start "
                         "--head), and a local Ray that this command starts ends with it")
    jobs = load_jobs(args.jobs, options)
    devices = parse_devices(args.devices)
    # the terminate handler goes in after Ray's (ray.init sets one that exits mid-call, with a C stack)
    with ray_session(devices, args.ray_address, needed_by="batch") as workers, terminate_as_interrupt() as terminated:
        place = f" of the Ray cluster at {args.ray_address}" if args.ray_address else ""
        kept = " (kept after the batch: --release-workers ends them)" if args.keep_workers else ""
        print(f"batch: {counted(len(jobs), 'job')} on {counted(workers.count, f'{workers.kind} worker')}{place}{kept}",
              flush=True)
        others = kept_workers() if args.ray_address and not args.keep_workers else []
        if others:  # they hold their GPUs: this batch's workers would wait for them without a word
            print(f"note: workers kept by earlier batches hold their devices ({', '.join(others)}); this batch's "
                  "workers wait for free ones. Give --keep-workers to run on them, or end them with --release-workers",
                  flush=True)
        # the bar is closed however the run ends, before main prints an error below it
        with tqdm(total=len(jobs), desc="batch", unit="job", dynamic_ncols=True) as bar, \
                BatchPool(workers, keep=args.keep_workers) as pool:
            def report(kind: str, job: Job, detail) -> None:
                if kind == "finished":
                    bar.update(1)
                    bar.write(_line(detail, len(jobs)), file=sys.stdout)

            results = pool.run(jobs, redo=args.redo, on_event=report)
    counts = {status: sum(r.status == status for r in results) for status in STATUSES}
    print("summary: " + ", ".join(f"{counts[s]} {s}" for s in STATUSES if counts[s] or s == "done"))
    for result in results:
        if result.status == "failed":
            print(f"  failed job {result.job.number}: {result.message}")
    return 143 if terminated else 130 if counts["cancelled"] else 1 if counts["failed"] else 0


def cmd_release(args: argparse.Namespace) -> int:
    """``batch --release-workers``: ends the workers that batches kept on the cluster at ``--ray-address``."""
    if args.jobs is not None or args.devices or args.redo or args.keep_workers:
        raise ValueError("--release-workers takes --ray-address alone (no JOBS, --devices, --redo or --keep-workers)")
    if not args.ray_address:
        raise ValueError("--release-workers needs the --ray-address of the cluster that keeps them")
    with ray_joined(args.ray_address, needed_by="batch"):
        names = release_workers()
    print(f"released {counted(len(names), 'kept worker')}" + "".join(f"\n  {name}" for name in names))
    return 0


def _line(result: JobResult, total: int) -> str:
    job = result.job
    what = str(job.out) if job.out is not None else "(not run)"
    extra = {"done": f"{result.seconds:.0f} s on {result.worker}", "skipped": result.message}.get(
        result.status, result.message)
    return f"{result.status:<9} job {job.number}/{total}  {what}  {extra}" + "".join(
        f"\n  note: {note}" for note in result.notes)


def plain_text(docstring: str) -> str:
    """``docstring`` as ``--help`` prints it: without its cross-references (a space, then ``(:func:`name`)``) and
    its markup."""
    text = re.sub(r"\s\(:\w+:`[^`]+`\)", "", docstring)
    return re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("``", "")


def add_batch_command(commands) -> None:
    """Register ``batch`` with the command line's subparsers; its jobs take stylize's options."""
    options = stylize_options()
    p = commands.add_parser("batch", help="run many stylize jobs (a JSON or CSV list) over GPUs or a Ray cluster",
                            description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("jobs", nargs="?", help="JSON list of jobs or CSV table; each job holds stylize's options by "
                   "name (none with --release-workers)")
    p.add_argument("--devices", help="GPUs of this machine sharing the jobs, e.g. cuda:0,cuda:1 (default: every "
                   "visible GPU, else one CPU worker; cpu,cpu: two CPU workers)")
    p.add_argument("--ray-address", help="join a running Ray cluster (auto, or HOST:PORT) instead: one worker per "
                   "GPU of the cluster")
    p.add_argument("--redo", action="store_true", help="run jobs whose output is already complete, too")
    p.add_argument("--keep-workers", action="store_true", help="keep the workers running after the batch (needs "
                   "--ray-address); a later batch with --keep-workers runs on them warm, their imports done and "
                   "models loaded. They hold their GPU memory until --release-workers or `ray stop` (default: the "
                   "workers end with the batch)")
    p.add_argument("--release-workers", action="store_true", help="end the workers that batches kept on the cluster "
                   "at --ray-address, run no jobs")
    p.set_defaults(run=functools.partial(cmd_batch, options=options))
