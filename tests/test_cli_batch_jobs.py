"""batch's JOBS files: JSON or CSV entries become stylize arguments, bad jobs carry their error before any work,
jobs are ranked by their expected work, and a complete output is told from a partial one."""

import json
import os
from pathlib import Path

import pytest

from artnvg_core.cli import main as cli
from artnvg_core.cli.batch_jobs import expected_work, load_jobs, output_complete, read_jobs, stylize_options
from artnvg_core.formats import load_scene, save_scene
from artnvg_core.stylize import DemoInputs, sheet_path


def write_jobs(path: Path, entries) -> Path:
    """``entries`` written to ``path`` as a JSON JOBS file."""
    path.write_text(json.dumps(entries))
    return path


def test_job_options_become_stylize_arguments_from_json_or_csv(tmp_path):
    entries = [{"scene": "a.ply", "Style": "s.jpg", "out": "out/a.ply", "iters": 3, "seed": 7, "compile": True,
                "color_transfer": False, "cameras": None, "preset": "", "orbit-size": "48x32", "up": "-y"}]
    (from_json,) = load_jobs(write_jobs(tmp_path / "jobs.json", entries), stylize_options())
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
    one, two, bad = load_jobs(write_jobs(tmp_path / "loras.json", entries), stylize_options())
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
    jobs = load_jobs(write_jobs(tmp_path / "jobs.json", entries), stylize_options())
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
    jobs = load_jobs(write_jobs(tmp_path / "jobs.json", entries), stylize_options())
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
    # found by fuzzing: RecursionError and csv.Error escaped
    ("jobs.json", "[" * 100_000, r"not valid JSON \(it nests too deeply\)"),
    ("jobs.csv", "scene,out\n" + "a" * 200_000 + ",a.ply\n", r"not a readable CSV table \(field larger than field limit"),
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
    jobs = load_jobs(write_jobs(tmp_path / "jobs.json", entries), stylize_options())
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


def test_output_complete_reads_a_spz_without_telling_its_axes(tmp_path, caplog):
    """A .spz output names no axes: the check, on every run of the batch, does not log that it takes the PLY's."""
    out = tmp_path / "a.spz"
    save_scene(load_scene(DemoInputs().scene).select(slice(0, None, 40)), out)
    sheet_path(out).write_bytes(b"png")
    with caplog.at_level("INFO"):
        assert output_complete(out)
    assert caplog.records == []
