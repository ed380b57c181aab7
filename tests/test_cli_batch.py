"""batch: on two CPU Ray workers a batch writes what single stylize runs write, byte for byte, also when a
worker is killed mid-job; bad jobs fail alone; a second run skips complete outputs; a stop (Ctrl-C) cancels
the running jobs without leaving a file. (Its JOBS files: tests/test_cli_batch_jobs.py.)"""

import json
import os
import re
import signal
import threading
import time
from pathlib import Path

import pytest
import torch
from tqdm import tqdm

from artnvg_core.cli import main as cli
from artnvg_core.cli.batch_jobs import Job, load_jobs, output_complete, stylize_options
from artnvg_core.formats import load_scene, save_scene
from artnvg_core.presets import PRESETS
from artnvg_core.stylize import DemoInputs, sheet_path
from child_process import child_env
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import write_model_files
from ray_workers import TINY_FAST
from tests.test_cli_batch_jobs import write_jobs


SIGTERM_DURING_A_BATCH = """
import contextlib, os, signal, sys, time
from artnvg_core.cli import batch, main as cli
from artnvg_core.cluster import Workers

@contextlib.contextmanager
def session(devices, address, needed_by):  # as ray.init does: SIGTERM exits mid-call
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))
    yield Workers("cpu", 1)

class Pool:  # stops as BatchPool does on Ctrl-C: every job cancelled
    def __init__(self, workers, keep): pass
    def __enter__(self): return self
    def __exit__(self, *exc): pass
    def run(self, jobs, redo=False, on_event=None):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(60)
        except KeyboardInterrupt:
            return [batch.JobResult(job, "cancelled", "batch stopped") for job in jobs]

batch.ray_session, batch.BatchPool = session, Pool
sys.exit(cli.main(["batch", sys.argv[1]]))
"""


def test_sigterm_stops_a_batch_as_ctrl_c_does(tmp_path):
    """SIGTERM during the jobs cancels them through the Ctrl-C path and exits 143 with the summary, no
    traceback (Ray's own handler once exited mid-call and printed a C stack)."""
    import subprocess
    import sys

    jobs = write_jobs(tmp_path / "jobs.json", [{"scene": "a.ply", "style": "s.jpg", "out": "out/a.ply"}])
    result = subprocess.run([sys.executable, "-c", SIGTERM_DURING_A_BATCH, str(jobs)], capture_output=True, text=True,
                            timeout=120, env=child_env(), cwd=str(Path(__file__).parents[1]))
    assert result.returncode == 143, (result.returncode, result.stderr[-2000:])
    assert "summary: 0 done, 1 cancelled" in result.stdout and "Traceback" not in result.stderr


def test_a_batch_that_fails_closes_its_bar_before_the_error(tmp_path, monkeypatch, capsys):
    """The error is printed on a line of its own, below the bar's last state; the bar was left open
    (mid-line) when the jobs' run raised."""
    import contextlib

    from artnvg_core.cli import batch
    from artnvg_core.cluster import Workers

    class Pool:  # one job finished, then the run fails
        def __init__(self, workers, keep): pass
        def __enter__(self): return self
        def __exit__(self, *exc): pass
        def run(self, jobs, redo=False, on_event=None):
            on_event("finished", jobs[0], batch.JobResult(jobs[0], "skipped", "complete"))
            raise OSError("the jobs' folder is gone")

    monkeypatch.setattr(batch, "ray_session", lambda *args, **kwargs: contextlib.nullcontext(Workers("cpu", 1)))
    monkeypatch.setattr(batch, "BatchPool", Pool)
    entries = [{"scene": "a.ply", "style": "s.jpg", "out": f"out/{name}.ply"} for name in "ab"]
    assert cli.main(["batch", str(write_jobs(tmp_path / "jobs.json", entries))]) == 2
    err = capsys.readouterr().err
    assert re.search(r"batch: +50%.*\| 1/2 \[[^\]]+\] *\nerror: the jobs' folder is gone\n$", err), err


@pytest.mark.parametrize("where", ["finetune", "loading"])
def test_a_stop_whose_exception_is_lost_or_wrapped_still_cancels_the_job(tmp_path, monkeypatch, where):
    """The worker's stop raises Cancelled in the job's thread; when that exception never arrives (a
    finaliser running just then swallows it, here as the finetune returns) the stylize's own stop checks
    end the job (the contact sheet's renders), and when a loader wraps it in its own error the job is still
    cancelled, not failed. Either way nothing is written."""
    pytest.importorskip("ray")  # the worker names its machine through Ray
    import artnvg_core.stylize as core
    from artnvg_core.cli import stylize as command
    from artnvg_core.cli.batch import BatchWorker
    from artnvg_core.cluster import Workers

    worker = BatchWorker(Workers("cpu", 1))
    if where == "finetune":
        def finetune_as_the_stop_arrives(*args, **kwargs):
            result = real_finetune(*args, **kwargs)
            worker.stopped.add("run")  # the stop, its exception lost
            return result

        real_finetune = core.stylize_nnfm
        monkeypatch.setattr(core, "stylize_nnfm", finetune_as_the_stop_arrives)
    else:
        def load_as_the_stop_arrives(path, *args, **kwargs):
            worker.stopped.add("run")
            raise ValueError(f"{path}: not a readable PLY file (Cancelled: stopped by request)")

        monkeypatch.setattr(command, "load_scene_verbose", load_as_the_stop_arrives)
    demo = DemoInputs()
    argv = [str(demo.scene), f"--cameras={demo.cameras}", f"--style={demo.style}", "--stylizer=nnfm", "--iters=2",
            "--scale=0.0625", "--out=out/a.ply"]
    bars = set(tqdm._instances)
    result = worker.run("run", argv, str(tmp_path))
    assert (result["status"], result["message"]) == ("cancelled", "stopped by request"), result
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    assert set(tqdm._instances) <= bars  # the stopped job's bars closed (one left open shifts every later bar down)


def test_a_jobs_scene_file_notes_come_back_with_it_and_print_under_its_line(tmp_path, capsys, caplog):
    """A bare .spz names no axes and a .splat holds SH degree 0: what the job's load and save told, which the
    worker's silenced output would drop, is in its result, and the batch prints it under the job's line."""
    pytest.importorskip("ray")  # the worker names its machine through Ray
    from artnvg_core.cli.batch import BatchWorker, JobResult, _line
    from artnvg_core.cluster import Workers

    demo = DemoInputs()
    save_scene(load_scene(demo.scene).select(slice(0, None, 40)), tmp_path / "bare.spz")
    argv = ["bare.spz", f"--style={demo.style}", "--stylizer=nnfm", "--iters=1", "--orbit-views=2",
            "--orbit-size=32", "--out=out/a.splat"]
    with caplog.at_level("INFO"):
        result = BatchWorker(Workers("cpu", 1)).run("run", argv, str(tmp_path))
    assert result["status"] == "done", result
    notes = ["the file names no axes: read in the PLY's axes (x right, y down, z forward), as splat-transform, "
             "spz-js and Niantic's ply-to-spz write; if it is upside down, read it with spz axes 'rub' (--spz-axes "
             "rub, the Load Gaussian Scene node's spz_axes)",
             ".splat holds SH up to degree 0; the degree 1 view-dependent terms are dropped"]
    assert result["notes"] == notes
    assert not [r for r in caplog.records if "names no axes" in r.getMessage() or "degree 0" in r.getMessage()]
    job = Job(1, tuple(argv), tmp_path, tmp_path / "out" / "a.splat")
    assert _line(JobResult(job, "done", "", 3.0, "cpu", None, tuple(notes)), 2).splitlines() == [
        f"done      job 1/2  {job.out}  3 s on cpu", *(f"  note: {note}" for note in notes)]


# --- on a local Ray cluster of two CPU workers ---------------------------------------------------


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A JOBS file of three good jobs (nnfm with cameras, diffusion with cameras on tiny models, nnfm
    on a bare .spz given by a relative path) and two bad ones (a missing scene, an unknown preset);
    returns (jobs path, {job number: reference output path}) with the references written by single
    ``stylize`` runs in this process."""
    folder = tmp_path_factory.mktemp("batch")
    demo = DemoInputs()
    transforms = json.loads(demo.cameras.read_text())
    transforms["frames"] = transforms["frames"][:4]
    (folder / "cameras.json").write_text(json.dumps(transforms))
    save_scene(load_scene(demo.scene), folder / "bare.spz")
    models = write_model_files(folder)
    small = {"style": str(demo.style), "iters": 2, "seed": 3}
    with_cameras = {**small, "scene": str(demo.scene), "cameras": str(folder / "cameras.json"), "scale": 0.125}
    entries = [
        {**with_cameras, "stylizer": "nnfm", "out": "out/nnfm.ply"},
        {**with_cameras, "stylizer": "diffusion", "preset": "fast", "out": "out/diffusion.ply",
         **{role: str(path) for role, path in models.items()}},
        {**small, "scene": "bare.spz", "stylizer": "nnfm", "orbit_views": 4, "orbit_size": 48, "out": "out/bare.ply"},
        {**small, "scene": "missing.ply", "stylizer": "nnfm", "out": "out/missing.ply"},
        {**small, "scene": "bare.spz", "preset": "slow", "out": "out/slow.ply"},
    ]
    jobs_path = write_jobs(folder / "jobs.json", entries)
    references = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(PRESETS, "fast", TINY_FAST)  # as in the Ray workers (ray_workers.setup_worker)
        for job in load_jobs(jobs_path, stylize_options())[:3]:
            references[job.number] = folder / "reference" / job.out.name
            argv = [*job.argv, f"--out={references[job.number]}", "--device=cpu"]
            cwd = os.getcwd()
            os.chdir(folder)
            try:
                assert cli.main(["stylize", *argv]) == 0
            finally:
                os.chdir(cwd)
    return jobs_path, references


@pytest.fixture(scope="module")
def pool(ray_local):
    from artnvg_core.cli.batch import BatchPool
    from artnvg_core.cluster import Workers

    with BatchPool(Workers("cpu", 2)) as pool:
        yield pool


def _same_output(out: Path, reference: Path) -> bool:
    return out.read_bytes() == reference.read_bytes() and sheet_path(out).read_bytes() == sheet_path(reference).read_bytes()


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture(scope="module")
def first_batch(inputs, pool, ray_local):
    """The JOBS file's first run on the pool, the worker that takes the first job killed as it begins;
    returns (results, the job numbers in the order they started, {job number: its output equals the
    single run's}, the hidden files left in the output folder), read right after the batch, so that
    each test may run first."""
    jobs_path, references = inputs
    jobs = load_jobs(jobs_path, stylize_options())
    starts = []

    def kill_the_first_worker(kind: str, job: Job, detail) -> None:
        if kind == "started":
            starts.append(job.number)
            if len(starts) == 1:  # the worker that took the first job dies as the job begins
                os.kill(ray_local.get(detail["actor"].ping.remote()), signal.SIGKILL)

    results = pool.run(jobs, on_event=kill_the_first_worker)
    same = {number: _same_output(jobs[number - 1].out, reference) for number, reference in references.items()}
    return results, starts, same, _leftovers(jobs_path.parent / "out")


def test_batch_equals_single_runs_a_killed_worker_retried_bad_jobs_alone(inputs, first_batch):
    jobs_path, _ = inputs
    results, starts, same, leftovers = first_batch
    assert [r.status for r in results] == ["done", "done", "done", "failed", "failed"], results
    # the longest first: the diffusion job, then the NNFM jobs by scene size; job 5 fails before it starts
    assert starts[:2] == [2, 1] and starts.count(2) == 2 and sorted(set(starts)) == [1, 2, 3, 4], starts
    assert same == {1: True, 2: True, 3: True}
    assert "missing.ply" in results[3].message and "argument --preset: invalid choice: 'slow'" in results[4].message
    assert not (jobs_path.parent / "out" / "missing.ply").exists() and not leftovers


def test_second_run_skips_complete_outputs_and_a_stop_cancels_cleanly(inputs, pool, first_batch, capsys, ray_local):
    jobs_path, references = inputs
    jobs = load_jobs(jobs_path, stylize_options())
    assert all(output_complete(jobs[n - 1].out) for n in references)
    modified = {n: jobs[n - 1].out.stat().st_mtime_ns for n in references}
    # the command line, on the three good jobs and the one that cannot be parsed: no job needs a
    # worker (the module's pool holds the session's two CPUs)
    entries = json.loads(jobs_path.read_text())
    again = write_jobs(jobs_path.parent / "again.json", entries[:3] + entries[4:])
    assert cli.main(["batch", str(again), "--devices", "cpu,cpu"]) == 1  # the bad job still fails
    printed = capsys.readouterr().out
    assert printed.count("\nskipped ") == 3 and "summary: 0 done, 1 failed, 3 skipped" in printed
    assert "failed job 4: again.json job 4: argument --preset: invalid choice: 'slow'" in printed
    assert {n: jobs[n - 1].out.stat().st_mtime_ns for n in references} == modified

    for number in (1, 3):
        jobs[number - 1].out.unlink()

    def ctrl_c(kind: str, job: Job, detail) -> None:
        if kind == "started":
            raise KeyboardInterrupt

    processes = ray_local.get([actor.ping.remote() for actor in pool.actors])
    results = pool.run(jobs, on_event=ctrl_c)
    assert [r.status for r in results] == ["cancelled", "skipped", "cancelled", "cancelled", "failed"], results
    assert not jobs[0].out.exists() and not jobs[2].out.exists() and not _leftovers(jobs_path.parent / "out")
    results = pool.run(jobs)  # the workers go on, the same processes (warm): the cancelled jobs run now
    assert [r.status for r in results] == ["done", "skipped", "done", "failed", "failed"], results
    assert ray_local.get([actor.ping.remote() for actor in pool.actors]) == processes
    assert _same_output(jobs[0].out, references[1]) and _same_output(jobs[2].out, references[3])


def test_a_kept_worker_busy_with_another_batchs_job_fails_the_job_at_once(tmp_path, monkeypatch):
    """Two batches on one kept worker would run two jobs in its process at once, in one working folder."""
    pytest.importorskip("ray")  # the worker names its machine through Ray
    from artnvg_core.cli import batch
    from artnvg_core.cluster import Workers

    monkeypatch.setattr(batch, "job_alive", lambda job_id: True)
    worker = batch.BatchWorker(Workers("cpu", 1))
    worker.running = ("another batch", "01000000", 0)
    result = worker.run("run", ["a.ply", "--out=out/a.ply"], str(tmp_path), "02000000")
    assert result["status"] == "failed" and "runs a job of another batch" in result["message"], result
    assert worker.running == ("another batch", "01000000", 0)


def test_a_job_left_running_by_a_killed_batch_command_is_stopped_for_the_next_batchs_job(tmp_path, monkeypatch):
    """A batch command killed (SIGKILL) leaves its job running on its kept worker; the next batch's job there
    stops that job (its command's Ray job is dead), waits for it, runs, and says so in a note."""
    pytest.importorskip("ray")  # the worker names its machine through Ray
    from artnvg_core.cli import batch
    from artnvg_core.cluster import Workers

    monkeypatch.setattr(batch, "job_alive", lambda job_id: job_id != "01000000")
    worker = batch.BatchWorker(Workers("cpu", 1))
    demo = DemoInputs()
    argv = [str(demo.scene), f"--style={demo.style}", "--stylizer=nnfm", "--orbit-views=2", "--orbit-size=32"]
    left = []
    orphan = threading.Thread(target=lambda: left.append(
        worker.run("killed batch", [*argv, "--iters=1000000", "--out=out/left.ply"], str(tmp_path), "01000000")))
    orphan.start()
    try:
        while worker.running is None:
            time.sleep(0.01)
        result = worker.run("next batch", [*argv, "--iters=1", "--out=out/a.ply"], str(tmp_path), "02000000")
    finally:  # not left running when the code is wrong
        worker.stop("killed batch")
        orphan.join(timeout=60)
    assert result["status"] == "done", result
    assert result["notes"][0] == "its worker first stopped a job left running by a batch whose command is gone"
    assert [(r["status"], r["message"]) for r in left] == [("cancelled", "stopped by request")]
    assert (tmp_path / "out" / "a.ply").exists() and not (tmp_path / "out" / "left.ply").exists()


def test_a_worker_frees_its_cached_gpu_memory_when_asked_between_batches_not_in_a_job(tmp_path, monkeypatch):
    """``rest`` (a batch ended) empties PyTorch's CUDA cache, a stand-in here; a job does not, nor does a
    ``rest`` that arrives while a later batch's job runs (it would take that job's working memory away)."""
    pytest.importorskip("ray")  # the worker names its machine through Ray
    from artnvg_core.cli.batch import BatchWorker
    from artnvg_core.cluster import Workers

    emptied = []
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: emptied.append(True))
    worker = BatchWorker(Workers("cpu", 1))
    demo = DemoInputs()
    argv = [str(demo.scene), f"--style={demo.style}", "--stylizer=nnfm", "--iters=1", "--orbit-views=2",
            "--orbit-size=32", "--out=out/a.ply"]
    assert worker.run("run", argv, str(tmp_path))["status"] == "done" and not emptied
    worker.running = ("a later batch", 0)
    worker.rest()
    assert not emptied
    worker.running = None
    worker.rest()
    assert emptied == [True]


def test_a_batch_lets_its_workers_free_their_cached_memory_once_its_last_job_ended(ray_local, monkeypatch):
    """Two batches on one worker: the cache is emptied after each batch's last job, not between jobs."""
    from artnvg_core.cli import batch
    from artnvg_core.cluster import Workers

    class Recorded(batch.BatchWorker):  # its jobs only record themselves, as its torch.cuda.empty_cache does
        def __init__(self, workers):
            super().__init__(workers)
            self.events = []
            torch.cuda.empty_cache = lambda: self.events.append("empty_cache")  # in the actor's process

        def run(self, run, argv, folder, driver):
            self.events.append(argv[0])
            return dict(status="done", message="", seconds=0.0, worker="", peak_gib=None, notes=[])

        def recorded(self) -> list[str]:
            return self.events

    monkeypatch.setattr(batch, "BatchWorker", Recorded)
    jobs = [Job(n, (f"job {n}",), Path("/nonexistent"), Path(f"/nonexistent/{n}.ply")) for n in (1, 2, 3)]
    with batch.BatchPool(Workers("cpu", 1)) as pool:
        assert [r.status for r in pool.run(jobs)] == ["done"] * 3
        assert [r.status for r in pool.run(jobs[:1])] == ["done"]
        assert ray_local.get(pool.actors[0].recorded.remote()) == [
            "job 1", "job 2", "job 3", "empty_cache", "job 1", "empty_cache"]


@pytest.mark.parametrize("arguments, message", [
    (["JOBS", "--keep-workers"], "--keep-workers needs --ray-address: workers are kept by a running Ray cluster"),
    (["--release-workers"], "--release-workers needs the --ray-address of the cluster that keeps them"),
    (["JOBS", "--release-workers", "--ray-address=auto"], "--release-workers takes --ray-address alone"),
    ([], "batch: give a JOBS file (or --release-workers)"),
])
def test_kept_workers_need_a_running_cluster_and_release_runs_no_jobs(tmp_path, monkeypatch, capsys, arguments,
                                                                      message):
    from artnvg_core.cli import batch

    monkeypatch.setattr(batch, "ray_session", None)  # refused before Ray
    monkeypatch.setattr(batch, "ray_joined", None)
    jobs = str(write_jobs(tmp_path / "jobs.json", [{"scene": "a.ply", "style": "s.jpg", "out": "out/a.ply"}]))
    assert cli.main(["batch", *(jobs if a == "JOBS" else a for a in arguments)]) == 2
    assert capsys.readouterr().err.startswith(f"error: {message}")


def test_kept_workers_serve_later_batches_warm_through_a_stop_until_released(tmp_path, ray_local, capsys):
    """Two batch commands (processes of their own) with --keep-workers on one running Ray instance run on
    the same worker process; a batch stopped in between ends its job, not the worker, and the next batch's
    job runs (its own run is not the stopped one); a batch without --keep-workers says that it waits for
    the devices kept workers hold (else it would wait without a word); --release-workers ends them."""
    import subprocess
    import sys

    from artnvg_core.cli.batch import BatchPool
    from artnvg_core.cluster import Workers, release_workers

    demo = DemoInputs()
    jobs_path = write_jobs(tmp_path / "jobs.json", [{
        "scene": str(demo.scene), "style": str(demo.style), "stylizer": "nnfm", "iters": 1, "orbit_views": 2,
        "orbit_size": 32, "out": "out/a.ply"}])
    address = ray_local.get_runtime_context().gcs_address

    def command(*arguments: str) -> str:
        result = subprocess.run([sys.executable, "-m", "artnvg_core", "batch", *arguments, "--ray-address", address],
                                capture_output=True, text=True, timeout=300, env=child_env(),
                                cwd=str(Path(__file__).parents[1]))  # the workers import this checkout
        assert result.returncode == 0, (result.returncode, result.stdout[-2000:], result.stderr[-2000:])
        return result.stdout

    def kept_process() -> int:
        return ray_local.get(ray_local.get_actor("BatchWorker-cpu-0", namespace="artnvg").ping.remote())

    try:
        printed = command(str(jobs_path), "--devices=cpu", "--keep-workers")
        assert "summary: 1 done" in printed and "(kept after the batch" in printed, printed
        process = kept_process()
        assert f"pid {process}" in printed

        def ctrl_c(kind: str, job: Job, detail) -> None:
            if kind == "started":
                raise KeyboardInterrupt

        with BatchPool(Workers("cpu", 1), keep=True) as pool:
            assert [r.status for r in pool.run(load_jobs(jobs_path, stylize_options()), redo=True,
                                               on_event=ctrl_c)] == ["cancelled"]
        assert kept_process() == process

        printed = command(str(jobs_path), "--devices=cpu", "--keep-workers", "--redo")
        assert "summary: 1 done" in printed and f"pid {process}" in printed, printed
        assert cli.main(["batch", str(jobs_path), "--devices=cpu", "--ray-address", address]) == 0  # skipped: done
        assert ("note: workers kept by earlier batches hold their devices (BatchWorker-cpu-0); this batch's workers "
                "wait for free ones") in capsys.readouterr().out
        assert command("--release-workers") == "released 1 kept worker\n  BatchWorker-cpu-0\n"
        with pytest.raises(ValueError, match="Failed to look up actor"):
            kept_process()
    finally:
        release_workers()


KILLED_DURING_A_BATCH = """
import sys
from artnvg_core.cli.batch import BatchPool
from artnvg_core.cli.batch_jobs import load_jobs, stylize_options
from artnvg_core.cluster import Workers, ray_joined

with ray_joined(sys.argv[2], needed_by="test") as ray, BatchPool(Workers("cpu", 1), keep=True) as pool:
    ray.get(pool.actors[0].ping.remote())  # started: the job reaches it at once
    pool.run(load_jobs(sys.argv[1], stylize_options()), on_event=lambda kind, job, detail: print(kind, flush=True))
"""


def test_a_batch_runs_on_a_kept_worker_whose_last_batch_command_was_killed_mid_job(tmp_path, ray_local):
    """A batch command killed with SIGKILL as its job runs on a kept worker: the next batch's job there stops
    the job left running (it once failed at once, 'busy with another batch', until that job ended) and runs."""
    import subprocess
    import sys

    from artnvg_core.cli.batch import BatchPool
    from artnvg_core.cluster import KEPT_NAMESPACE, Workers, release_workers

    demo = DemoInputs()
    entry = {"scene": str(demo.scene), "style": str(demo.style), "stylizer": "nnfm", "orbit_views": 2,
             "orbit_size": 32}
    endless = write_jobs(tmp_path / "endless.json", [{**entry, "iters": 1000000, "out": "out/endless.ply"}])
    jobs = load_jobs(write_jobs(tmp_path / "jobs.json", [{**entry, "iters": 1, "out": "out/a.ply"}]), stylize_options())
    command = subprocess.Popen([sys.executable, "-c", KILLED_DURING_A_BATCH, str(endless),
                                ray_local.get_runtime_context().gcs_address], stdout=subprocess.PIPE, text=True,
                               env=child_env(), cwd=str(Path(__file__).parents[1]))  # the workers import this checkout
    try:
        assert command.stdout.readline() == "started\n"  # handed out; killed once the worker runs it
        kept = ray_local.get_actor("BatchWorker-cpu-0", namespace=KEPT_NAMESPACE)
        deadline = time.monotonic() + 120
        while not ray_local.get(kept.__ray_call__.remote(lambda worker: worker.running is not None)):
            assert time.monotonic() < deadline, "the job never started on the kept worker"
            time.sleep(0.05)
        command.kill()
        command.wait()
        with BatchPool(Workers("cpu", 1), keep=True) as pool:
            (result,) = pool.run(jobs)
        assert result.status == "done", result
        assert result.notes == ("its worker first stopped a job left running by a batch whose command is gone",)
        assert not (tmp_path / "out" / "endless.ply").exists()
    finally:
        command.kill()
        release_workers()


def test_batch_help_prints_its_description_without_markup(capsys):
    """'--help' once showed the module docstring's ``name`` quotes and :func:`name` cross-references."""
    from artnvg_core.cli.main import main

    with pytest.raises(SystemExit):
        main(["batch", "--help"])
    out = capsys.readouterr().out
    assert "python -m artnvg_core batch JOBS: many stylize jobs" in out and "Jobs start longest first, so" in out
    assert "``" not in out and ":func:" not in out and "(artnvg_core." not in out
