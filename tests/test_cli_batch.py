"""batch: JOBS files become stylize arguments; on two CPU Ray workers a batch writes what single stylize
runs write, byte for byte, also when a worker is killed mid-job; bad jobs fail alone; a second run
skips complete outputs; a stop (Ctrl-C) cancels the running jobs without leaving a file."""

import json
import os
import signal
from pathlib import Path

import pytest

from artnvg_core.cli import main as cli
from artnvg_core.cli.batch import Job, expected_work, load_jobs, output_complete, read_jobs, stylize_options
from artnvg_core.formats import load_scene, save_scene
from artnvg_core.presets import PRESETS
from artnvg_core.stylize import DemoInputs, sheet_path
from child_process import child_env
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import write_model_files
from ray_workers import TINY_FAST


def _write_jobs(path: Path, entries) -> Path:
    path.write_text(json.dumps(entries))
    return path


def test_job_options_become_stylize_arguments_from_json_or_csv(tmp_path):
    entries = [{"scene": "a.ply", "Style": "s.jpg", "out": "out/a.ply", "iters": 3, "seed": 7, "compile": True,
                "color_transfer": False, "cameras": None, "preset": "", "orbit-size": "48x32", "up": "-y"}]
    (from_json,) = load_jobs(_write_jobs(tmp_path / "jobs.json", entries), stylize_options())
    (tmp_path / "jobs.csv").write_text("scene,Style,out,iters,seed,compile,color_transfer,cameras,preset,orbit-size,up\n"
                                       "a.ply,s.jpg,out/a.ply,3,7,yes,false,,,48x32,-y\n")
    (from_csv,) = load_jobs(tmp_path / "jobs.csv", stylize_options())
    assert from_json.error is None and from_json == from_csv
    assert from_json.argv == ("a.ply", "--style=s.jpg", "--out=out/a.ply", "--iters=3", "--seed=7", "--compile",
                              "--no-color-transfer", "--orbit-size=48x32", "--up=-y")
    assert from_json.number == 1 and from_json.folder == tmp_path.resolve()
    # a repeatable option: one value, or in JSON a list of them
    entries = [{"scene": "in.ply", "style": "s.jpg", "out": "a.ply", "lora": "x.safetensors:0.5"},
               {"scene": "in.ply", "style": "s.jpg", "out": "b.ply", "lora": ["x.safetensors", "y.safetensors:-1"]},
               {"scene": "in.ply", "style": "s.jpg", "out": "c.ply", "lora": ["x.safetensors", 2, [3]]}]
    one, two, bad = load_jobs(_write_jobs(tmp_path / "loras.json", entries), stylize_options())
    assert one.argv[-1:] == ("--lora=x.safetensors:0.5",)
    assert two.argv[-2:] == ("--lora=x.safetensors", "--lora=y.safetensors:-1")
    assert "'lora' takes a list of values, got" in bad.error
    assert from_json.out == (tmp_path / "out" / "a.ply").resolve()  # relative to the JOBS file's folder


def test_a_bad_job_carries_its_error_and_the_others_stay(tmp_path):
    good = {"scene": "in.ply", "style": "s.jpg", "out": "a.ply"}
    entries = [good, {**good, "out": "b.ply", "strength": 3}, {**good, "out": "c.ply", "devices": "cuda:0"},
               {**good, "out": "d.ply", "compile": "maybe"}, {"scene": "a.ply"}, {**good, "out": "e.ply", "preset": "slow"},
               {**good, "out": "f.ply", "iters": "many"}, "a.ply", {**good, "out": "./a.ply"},
               {**good, "out": "g.ply", "seed": [1, 2]}, {**good, "out": "i.ply", "Iters": 5, "iters": 1000},
               {**good, "out": "h.ply"}]
    jobs = load_jobs(_write_jobs(tmp_path / "jobs.json", entries), stylize_options())
    errors = [job.error for job in jobs]
    assert errors[0] is None and errors[-1] is None and jobs[-1].argv[0] == "in.ply"
    expected = ["unknown option 'strength' (stylize has no --strength", "'devices' is not a job option; give --devices",
                "'compile' is a flag; expected true or false, got 'maybe'", "no out given",
                "argument --preset: invalid choice: 'slow'", "argument --iters: expected an integer, got 'many'",
                'expected an object of stylize options, got "a.ply"', "writes " + str(tmp_path.resolve() / "a.ply") +
                ", as job 1 does", "'seed' takes one value, got [1, 2]",
                "'Iters', 'iters' name one option; give it once"]
    for number, (error, message) in enumerate(zip(errors[1:-1], expected), 2):
        assert error.startswith(f"jobs.json job {number}: ") and message in error, (error, message)
        assert jobs[number - 1].out is None and jobs[number - 1].argv == ()


def test_a_json_job_giving_one_key_twice_is_refused_naming_file_job_and_key(tmp_path):
    """json.loads keeps the last of a key given twice; the job is refused instead, as iters and Iters are."""
    (tmp_path / "jobs.json").write_text('[{"scene": "in.ply", "style": "s.jpg", "out": "a.ply"},\n'
                                        ' {"scene": "in.ply", "iters": 5, "style": "s.jpg", "out": "b.ply", "iters": 9}]')
    good, twice = load_jobs(tmp_path / "jobs.json", stylize_options())
    assert good.error is None and good.argv == ("in.ply", "--style=s.jpg", "--out=a.ply")
    assert twice.error == "jobs.json job 2: 'iters' is given twice; give it once" and twice.argv == ()


def test_jobs_writing_over_their_inputs_or_each_others_outputs_are_refused_before_work(tmp_path):
    """a.ply and a.spz share a.contact.png: the second job is refused, so a resumed batch can tell the
    first job's completion by its own outputs; so is a job whose out or contact sheet is one of its inputs
    (a hard link included). A scene named -x.ply is a scene, not an option."""
    import os

    (tmp_path / "in.ply").write_text("scene")
    os.link(tmp_path / "in.ply", tmp_path / "linked.ply")
    entries = [{"scene": "in.ply", "style": "s.jpg", "out": "a.ply"},
               {"scene": "in.ply", "style": "s.jpg", "out": "a.spz"},
               {"scene": "in.ply", "style": "s.jpg", "out": "in.ply"},
               {"scene": "in.ply", "style": "S.contact.png", "out": "S.ply"},
               {"scene": "in.ply", "style": "s.jpg", "out": "linked.ply"},
               {"scene": "-x.ply", "style": "s.jpg", "out": "b.ply"}]
    jobs = load_jobs(_write_jobs(tmp_path / "jobs.json", entries), stylize_options())
    folder = tmp_path.resolve()
    expected = [None, f"jobs.json job 2: writes {folder / 'a.contact.png'} (its contact sheet), as job 1 does",
                f"jobs.json job 3: out: {folder / 'in.ply'} is the same file as scene {folder / 'in.ply'}",
                f"jobs.json job 4: out (its contact sheet): {folder / 'S.contact.png'} is the same file as style",
                f"jobs.json job 5: out: {folder / 'linked.ply'} is the same file as scene {folder / 'in.ply'}", None]
    for job, message in zip(jobs, expected):
        assert (job.error is None) if message is None else job.error.startswith(message), (job.error, message)
    assert jobs[5].argv[0] == os.path.join(".", "-x.ply") and jobs[5].out == folder / "b.ply"


FOLDER = object()  # a jobs path that is a folder


@pytest.mark.parametrize("name, text, message", [
    ("missing.json", None, "jobs file not found"),
    ("jobs.json", "[{", "not valid JSON"),
    ("jobs.json", '{"scene": "a.ply"}', "expected a JSON list of jobs .* got a dict"),
    ("jobs.json", "[]", "no jobs"),
    ("jobs.csv", "scene,out\na.ply,a.ply,extra\n", "row 2 has more cells than the header has names"),
    ("jobs.csv", "scene,out\n", "no jobs"),
    ("jobs.csv", "scene,out,out\na.ply,a.ply,b.ply\n", "the header names 'out' twice"),
    ("jobs.json", b'\xff\xfe[{"out": "a.ply"}]', "not UTF-8 text"),
    ("jobs.csv", b"scene,out\na\xe9.ply,a.ply\n", "not UTF-8 text"),
    ("jobs.json", FOLDER, "cannot read the jobs file"),
])
def test_a_jobs_file_that_cannot_be_read_names_itself(tmp_path, name, text, message):
    if text is FOLDER:
        (tmp_path / name).mkdir()
    elif isinstance(text, bytes):
        (tmp_path / name).write_bytes(text)
    elif text is not None:
        (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=f"{name}: {message}"):
        read_jobs(tmp_path / name)


def test_expected_work_ranks_jobs_by_steps_then_iterations_then_scene_size(tmp_path):
    (tmp_path / "big.ply").write_bytes(b"x" * 300)
    (tmp_path / "small.ply").write_bytes(b"x" * 100)
    base = {"style": "s.jpg"}
    entries = [
        {**base, "scene": "small.ply", "preset": "fast", "out": "fast-small.ply"},  # 5 steps, 3 guided
        {**base, "scene": "big.ply", "preset": "fast", "out": "fast-big.ply"},
        {**base, "scene": "big.ply", "preset": "paper", "out": "paper.ply"},  # 50 steps, all guided
        {**base, "scene": "big.ply", "preset": "preview", "out": "preview.ply"},  # no diffusion, 100 iterations
        {**base, "scene": "big.ply", "stylizer": "nnfm", "out": "nnfm.ply"},  # 1000 iterations
        {**base, "scene": "small.ply", "preset": "fast", "steps": 8, "cfg_until": 1, "iters": 5, "out": "f8.ply"},
        {**base, "scene": "missing.ply", "stylizer": "nnfm", "iters": 1000, "out": "m.ply"},
    ]
    jobs = load_jobs(_write_jobs(tmp_path / "jobs.json", entries), stylize_options())
    assert [job.work for job in jobs] == [(8, 300, 100), (8, 300, 300), (100, 1000, 300), (0, 100, 300),
                                          (0, 1000, 300), (16, 5, 100), (0, 1000, 0)]
    assert expected_work(cli.build_parser().parse_args(["stylize", "--preset", "fast", "--cfg-until", "0"]),
                         tmp_path) == (5, 300, 0)
    assert [job.number for job in sorted(jobs, key=lambda job: job.work, reverse=True)] == [3, 6, 2, 1, 5, 7, 4]


def test_output_complete_needs_a_scene_that_loads_and_its_contact_sheet(tmp_path):
    out = tmp_path / "a.ply"
    assert not output_complete(out)
    save_scene(load_scene(DemoInputs().scene), out)
    assert not output_complete(out)
    sheet_path(out).write_bytes(b"png")
    assert output_complete(out)
    out.write_bytes(out.read_bytes()[:1000])  # cut short
    assert not output_complete(out)


SIGTERM_DURING_A_BATCH = """
import contextlib, os, signal, sys, time
from artnvg_core.cli import batch, main as cli
from artnvg_core.cluster import Workers

@contextlib.contextmanager
def session(devices, address, needed_by):  # as ray.init does: SIGTERM exits mid-call
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))
    yield Workers("cpu", 1)

class Pool:  # stops as BatchPool does on Ctrl-C: every job cancelled
    def __init__(self, workers): pass
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

    jobs = _write_jobs(tmp_path / "jobs.json", [{"scene": "a.ply", "style": "s.jpg", "out": "out/a.ply"}])
    result = subprocess.run([sys.executable, "-c", SIGTERM_DURING_A_BATCH, str(jobs)], capture_output=True, text=True,
                            timeout=120, env=child_env(), cwd=str(Path(__file__).parents[1]))
    assert result.returncode == 143, (result.returncode, result.stderr[-2000:])
    assert "summary: 0 done, 1 cancelled" in result.stdout and "Traceback" not in result.stderr


@pytest.mark.parametrize("where", ["finetune", "loading"])
def test_a_stop_whose_exception_is_lost_or_wrapped_still_cancels_the_job(tmp_path, monkeypatch, where):
    """The worker's stop raises Cancelled in the job's thread; when that exception never arrives (a
    finaliser running just then swallows it) the stylize's own stop check ends the job, and when a loader
    wraps it in its own error the job is still cancelled, not failed. Either way nothing is written."""
    import artnvg_core.stylize as core
    from artnvg_core.cli import stylize as command
    from artnvg_core.cli.batch import BatchWorker
    from artnvg_core.cluster import Workers

    worker = BatchWorker(Workers("cpu", 1))
    if where == "finetune":
        def finetune_as_the_stop_arrives(*args, **kwargs):
            worker.stopped.add("run")  # the stop, its exception lost
            return real_finetune(*args, **kwargs)

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
    result = worker.run("run", argv, str(tmp_path))
    assert (result["status"], result["message"]) == ("cancelled", "stopped by request"), result
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


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
    jobs_path = _write_jobs(folder / "jobs.json", entries)
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


def test_second_run_skips_complete_outputs_and_a_stop_cancels_cleanly(inputs, pool, first_batch, capsys):
    jobs_path, references = inputs
    jobs = load_jobs(jobs_path, stylize_options())
    assert all(output_complete(jobs[n - 1].out) for n in references)
    modified = {n: jobs[n - 1].out.stat().st_mtime_ns for n in references}
    # the command line, on the three good jobs and the one that cannot be parsed: no job needs a
    # worker (the module's pool holds the session's two CPUs)
    entries = json.loads(jobs_path.read_text())
    again = _write_jobs(jobs_path.parent / "again.json", entries[:3] + entries[4:])
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

    results = pool.run(jobs, on_event=ctrl_c)
    assert [r.status for r in results] == ["cancelled", "skipped", "cancelled", "cancelled", "failed"], results
    assert not jobs[0].out.exists() and not jobs[2].out.exists() and not _leftovers(jobs_path.parent / "out")
    results = pool.run(jobs)  # the workers go on: the cancelled jobs run now
    assert [r.status for r in results] == ["done", "skipped", "done", "failed", "failed"], results
    assert _same_output(jobs[0].out, references[1]) and _same_output(jobs[2].out, references[3])


def test_batch_help_prints_its_description_without_markup(capsys):
    """'--help' once showed the module docstring's ``name`` quotes and :func:`name` cross-references."""
    from artnvg_core.cli.main import main

    with pytest.raises(SystemExit):
        main(["batch", "--help"])
    out = capsys.readouterr().out
    assert "python -m artnvg_core batch JOBS: many stylize jobs" in out and "Jobs start longest first, so" in out
    assert "``" not in out and ":func:" not in out and "(artnvg_core." not in out
