"""The JOBS file of ``python -m artnvg_core batch`` (its format: :mod:`artnvg_core.cli.batch`): its entries read
from JSON or CSV, each turned into ``stylize``'s arguments and parsed by ``stylize``'s own parser, checked
before any work (a job that would write over its inputs or another job's output carries its error), and
ranked by the work it should take; and whether a job's output is already complete.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..diffusion.settings import guided_steps
from ..json_objects import parse_json
from ..presets import PRESETS
from .stylize import add_stylize_arguments

NOT_PER_JOB = {"device": "--devices", "devices": "--devices", "ray-address": "--ray-address", "help": None}
TRUE, FALSE = {"true", "1", "yes", "on"}, {"false", "0", "no", "off"}


@dataclass(frozen=True)
class Job:
    """One line of JOBS: ``number`` (from 1), ``argv`` (stylize's arguments), ``folder`` (where relative
    paths start), ``out`` (absolute output scene), ``error`` (why it cannot run, else None) and ``work``
    (:func:`expected_work`: larger runs longer)."""

    number: int
    argv: tuple[str, ...]
    folder: Path
    out: Path | None
    error: str | None = None
    work: tuple[int, int, int] = (0, 0, 0)


def read_jobs(path: str | os.PathLike) -> list:
    """The entries of a JOBS file: dicts of option name -> value (CSV: strings, "" for an empty cell; JSON:
    :class:`~artnvg_core.json_objects.JsonObject`, whose ``twice`` :func:`job_arguments` refuses).

    ValueError naming the file when it cannot be read (missing, a folder, not UTF-8) or is not a JSON list
    or a CSV table with a header; an entry that is not an object is returned as it is (its job fails alone)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ValueError(f"{path}: jobs file not found") from None
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not UTF-8 text (at byte offset {error.start}); save it as UTF-8") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read the jobs file ({error.strerror or error})") from None
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(io.StringIO(text))
        try:
            header = reader.fieldnames or []
            rows = list(reader)
        except csv.Error as error:  # e.g. a cell over csv's field size limit
            raise ValueError(f"{path}: not a readable CSV table ({error})") from None
        repeated = next((name for name in header if header.count(name) > 1), None)
        if repeated is not None:  # a dict keeps one of its cells: refused, not chosen for the user
            raise ValueError(f"{path}: the header names '{repeated}' twice")
        for number, row in enumerate(rows, 1):
            if None in row:
                raise ValueError(f"{path}: row {number + 1} has more cells than the header has names")
        entries = rows
    else:
        entries = parse_json(text, str(path), None, once=False, hint=(
            '; expected a list of jobs, e.g. [{"scene": "a.ply", "style": "s.jpg", "out": "out/a.ply"}], or a .csv file'))
        if not isinstance(entries, list):
            raise ValueError(f"{path}: expected a JSON list of jobs (objects of stylize options), "
                             f"got a {'dict' if isinstance(entries, dict) else type(entries).__name__}")
    if not entries:
        raise ValueError(f"{path}: no jobs")
    return entries


def job_arguments(entry, options: dict[str, argparse.Action], label: str) -> list[str]:
    """``stylize``'s command-line arguments for one entry of JOBS (``options``: stylize's actions by option
    string). ValueError starting with ``label`` for an unknown option, one the batch decides, one named twice
    (``iters`` twice, or ``iters`` and ``Iters``), a bad flag value or a missing ``out``."""
    if not isinstance(entry, dict):
        raise ValueError(f"{label}: expected an object of stylize options, got {json.dumps(entry)[:80]}")
    if getattr(entry, "twice", None) is not None:  # a dict keeps one of its values: refused, not chosen for the user
        raise ValueError(f"{label}: '{entry.twice}' is given twice; give it once")
    names = [str(key).strip().lower().replace("_", "-") for key in entry]
    repeated = [f"'{key}'" for key, name in zip(entry, names) if names.count(name) > 1]
    if repeated:
        raise ValueError(f"{label}: {', '.join(repeated)} name one option; give it once")
    if "out" not in names or _empty(entry[list(entry)[names.index("out")]]):
        raise ValueError(f"{label}: no out given (each job writes its own output scene)")
    argv = []
    for name, (key, value) in zip(names, entry.items()):
        if name in NOT_PER_JOB:
            where = f"; give {NOT_PER_JOB[name]} to the batch" if NOT_PER_JOB[name] else ""
            raise ValueError(f"{label}: '{key}' is not a job option{where}")
        if _empty(value):
            continue
        if name == "scene":  # a name starting with "-" would read as an option
            argv.insert(0, os.path.join(os.curdir, str(value)) if str(value).startswith("-") else str(value))
            continue
        action = options.get(f"--{name}")
        if action is None:
            raise ValueError(f"{label}: unknown option '{key}' (stylize has no --{name}; "
                             "see python -m artnvg_core stylize --help)")
        if action.nargs == 0:
            text = str(value).strip().lower()
            if text not in TRUE | FALSE:
                raise ValueError(f"{label}: '{key}' is a flag; expected true or false, got {value!r}")
            if text in TRUE:
                argv.append(f"--{name}")
            elif f"--no-{name}" in options:
                argv.append(f"--no-{name}")
        elif isinstance(value, list) and isinstance(action, argparse._AppendAction):  # --lora: one value each
            for item in value:
                if isinstance(item, (bool, list, dict)) or _empty(item):
                    raise ValueError(f"{label}: '{key}' takes a list of values, got {json.dumps(value)}")
                argv.append(f"--{name}={item}")
        elif isinstance(value, (bool, list, dict)):
            raise ValueError(f"{label}: '{key}' takes one value, got {json.dumps(value)}")
        else:
            argv.append(f"--{name}={value}")
    return argv


def _empty(value) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def parse_stylize(argv: Sequence[str], label: str) -> argparse.Namespace:
    """``python -m artnvg_core stylize ARGV`` parsed by stylize's own options; ValueError starting with
    ``label`` with argparse's message instead of an exit."""
    message = io.StringIO()
    try:
        with contextlib.redirect_stderr(message):
            return stylize_parser().parse_args(argv)
    except SystemExit:
        text = message.getvalue().strip().splitlines()
        raise ValueError(f"{label}: {text[-1].split('error: ', 1)[-1] if text else 'cannot be parsed'}") from None


def expected_work(args: argparse.Namespace, folder: Path) -> tuple[int, int, int]:
    """How long a job of stylize's ``args`` should run, compared as a tuple: its denoising steps per view
    (guided steps count twice: they sample a double batch; 0 for the NNFM stylizer and ``preview``), its
    finetune iterations, then its scene file's size in bytes (0 when missing). Steps and iterations
    follow the preset and the options that replace them; the views' count and size are not read."""
    preset = PRESETS[args.preset]
    sampler = None if args.stylizer == "nnfm" else preset.sampler  # "auto": diffusion, as when its files load
    steps = 0
    if sampler is not None:
        count = args.steps or sampler.steps
        cfg_until = sampler.cfg_until if args.cfg_until is None else args.cfg_until
        steps = count + guided_steps(count, cfg_until, sampler.guidance_scale)
    if args.iters is not None:
        iterations = args.iters
    else:  # the NNFM stylizer's 1000 unless the preset is diffusion-free (preview)
        iterations = preset.finetune_iterations if sampler is not None or preset.sampler is None else 1000
    scene = folder / args.scene if args.scene else None
    return steps, iterations, scene.stat().st_size if scene is not None and scene.is_file() else 0


def load_jobs(path: str | os.PathLike, options: dict[str, argparse.Action]) -> list[Job]:
    """The jobs of a JOBS file (its format: :mod:`artnvg_core.cli.batch`). A job that cannot be parsed, that would write
    over one of its own inputs, or whose output or contact sheet another job writes too (``a.ply`` and
    ``a.spz`` share ``a.contact.png``), carries its error; only a file that cannot be read raises ValueError."""
    from ..fileio import file_identity, refuse_overwrites
    from ..stylize import DemoInputs, sheet_path

    path = Path(path)
    folder = path.resolve().parent
    jobs, owners = [], {}
    for number, entry in enumerate(read_jobs(path), 1):
        label = f"{path.name} job {number}"
        try:
            argv = job_arguments(entry, options, label)
            args = parse_stylize(argv, label)
            out = (folder / args.out).resolve()
            outputs = {out: "", sheet_path(out): " (its contact sheet)"}
            demo = DemoInputs()
            inputs = (args.scene, args.style, args.cameras) if args.scene or args.style else (
                demo.scene, demo.style, demo.cameras)
            try:
                refuse_overwrites([(f"out{what}", file) for file, what in outputs.items()],
                                  [(name, folder / given) for name, given in zip(("scene", "style", "cameras"), inputs)
                                   if given])
            except ValueError as error:
                raise ValueError(f"{label}: {error}") from None
            for file, what in outputs.items():
                owner = owners.get(file_identity(file))
                if owner is not None:
                    raise ValueError(f"{label}: writes {file}{what}, as job {owner} does; give each job its own out "
                                     "(a.ply and a.spz share a.contact.png)")
        except ValueError as error:
            jobs.append(Job(number, (), folder, None, str(error)))
            continue
        owners.update((file_identity(file), number) for file in outputs)
        jobs.append(Job(number, tuple(argv), folder, out, work=expected_work(args, folder)))
    return jobs


def output_complete(out: Path) -> bool:
    """Whether ``out`` holds a finished job's output: the scene loads and its contact sheet exists. What the read
    would tell of the scene (a .spz names no axes) is no news here: the job told it when it ran."""
    from ..formats import load_scene
    from ..stylize import sheet_path

    if not (out.is_file() and sheet_path(out).is_file()):
        return False
    try:
        load_scene(out, notes=lambda note: None)
    except (ValueError, OSError):
        return False
    return True


def stylize_parser() -> argparse.ArgumentParser:
    """A parser of stylize's options alone (:func:`~artnvg_core.cli.stylize.add_stylize_arguments`)."""
    parser = argparse.ArgumentParser(prog="python -m artnvg_core stylize")
    add_stylize_arguments(parser)
    return parser


def stylize_options() -> dict[str, argparse.Action]:
    """stylize's argparse actions by option string (``--preset``, ``--no-color-transfer``, ...)."""
    return {string: action for action in stylize_parser()._actions for string in action.option_strings}
