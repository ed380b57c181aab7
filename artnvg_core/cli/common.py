"""What the ``python -m artnvg_core`` commands share while they run: SIGTERM taken as Ctrl-C, progress bars,
the rasterizer, the scene and the style image loaded with what the user needs to know. (Their shared
options: :mod:`.options`.)"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import time
from typing import TYPE_CHECKING

import torch

from ..counted import counted

if TYPE_CHECKING:
    from ..cameras import CameraSet
    from ..notes import NoteFn
    from ..progress import StopFn
    from ..scene import GaussianScene


@contextlib.contextmanager
def terminate_as_interrupt():
    """For the block, SIGTERM (``kill``, a scheduler's stop) raises KeyboardInterrupt in the main thread, so
    a command stops as on Ctrl-C: its temporaries removed, nothing half-written (and a batch's running jobs
    cancelled, Ray shut down). Yields a list that holds the signal once one came. Outside the main thread,
    or without SIGTERM, nothing changes."""
    received: list[int] = []

    def interrupt(signum, frame):
        received.append(signum)
        raise KeyboardInterrupt

    if not hasattr(signal, "SIGTERM") or threading.current_thread() is not threading.main_thread():
        yield received
        return
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield received
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def printed_above_bars():
    """For the block, what is printed on stdout goes out line by line through ``tqdm.write`` (tqdm's
    ``DummyTqdmFile``, its recipe for printing beside bars): a bar on screen is lifted out of the line's way and
    drawn again below it. A status line printed while another thread's bar is drawn (the scene loading beside
    the diffusion models' load) was glued to the end of the bar's line."""
    from tqdm.contrib import DummyTqdmFile

    with contextlib.redirect_stdout(DummyTqdmFile(sys.stdout)):
        yield


# A scene file's load or save shorter than this (s) shows no bar: the line printed after it gives its time.
SCENE_FILE_BAR_DELAY = 0.5
_drawn: list[ProgressBar] = []  # those whose bar is on screen and not yet closed
_closings = 0  # close_progress_bars calls so far: a ProgressBar made before the latest draws nothing more


def close_progress_bars() -> None:
    """Close every bar still on screen (a command stopped or failed mid-step), so that the message printed
    next starts on a line of its own and no bar is drawn again below it, and silence every ProgressBar made so
    far: a background thread's (the diffusion models' load) reporting later would draw its bar below the
    message."""
    from tqdm import tqdm

    global _closings
    with tqdm.get_lock():
        _closings += 1
        while _drawn:
            _drawn[-1].close()


class ProgressBar:
    """A tqdm bar (rate and ETA, on stderr) fed by core progress callbacks; float ``info`` values follow it.
    ``unit``: what the steps count ("it"; others, such as "B" for bytes or "Gaussian", shown scaled: 6.5G/13.8GB,
    1.50M/3.00MGaussian). Callbacks whose
    ``info["stage"]`` changes (the finetune's renders before and after its steps) start a new bar,
    described as ``DESCRIPTION (STAGE)``. A bar starts at its first callback's step: its rate counts the work
    done after that (a first callback at the end shows none, where it once divided the work by no time).

    Bars may run in several threads at once (the models loading in the background below the content views'
    renders): each has a line of its own (tqdm's positions, drawn under tqdm's lock), and a bar that ends
    leaves its last state above those still running (``tqdm.write``), not over whichever line the cursor is
    on, as tqdm's own ``leave`` draws it. With ``delay`` (seconds, tqdm's), a bar shows only once its work has
    lasted that long, and work that ends sooner leaves nothing on screen (a scene file of thousands of
    Gaussians, read in milliseconds)."""

    def __init__(self, description: str, unit: str = "it", delay: float = 0.0):
        self.description = description
        self.unit = unit
        self.delay = delay
        self.bar = None
        self.stage = None
        self.made_after = _closings

    def __call__(self, step: int, total: int, info: dict) -> None:
        from tqdm import tqdm

        with tqdm.get_lock():
            if self.made_after != _closings:
                return
            stage = info.get("stage")
            if self.bar is None or stage != self.stage:
                self.close()
                self.stage = stage
                description = self.description if stage is None else f"{self.description} ({stage})"
                self.bar = tqdm(total=total, initial=step, desc=description, unit=self.unit,
                                unit_scale=self.unit != "it", dynamic_ncols=True, leave=False, delay=self.delay)
                _drawn.append(self)
            self.bar.set_postfix({k: f"{v:.4g}" for k, v in info.items() if isinstance(v, float)}, refresh=False)
            self.bar.update(step - self.bar.n)
            if step >= total:
                self.close()

    def close(self) -> None:
        """Close the bar on screen, if any, leaving its last state (its rate over the whole run, as tqdm's
        ``leave`` shows it) on a line above the bars still running, unless its work ended within its ``delay``."""
        from tqdm import tqdm

        with tqdm.get_lock():
            if self not in _drawn:
                return
            _drawn.remove(self)
            last = self.bar.format_meter(**{**self.bar.format_dict, "rate": None})
            shown = self.bar.format_dict["elapsed"] >= self.delay
            self.bar.close()  # its line cleared; the cursor may be left mid-line, hence the "\r"
            if shown:
                tqdm.write("\r" + last, file=self.bar.fp)


def print_note(note: str) -> None:
    """A note for the user from the library (what a scene file's format changes of the scene, what its read did:
    ``save_scene``'s and ``load_scene``'s ``notes``), printed on a line of its own."""
    print(f"note: {note}", flush=True)


def prepare_rasterizer(device: torch.device, backend: str = "auto") -> None:
    """Load the rasterizer ``backend`` renders with on ``device`` before the first render; gsplat's
    first-use kernel build (minutes; BENCHMARKS.md, "First look") is announced on stdout before it starts."""
    from ..raster import prepare_backend

    prepare_backend(device, backend, announce=lambda message: print(message, flush=True))


def load_scene_verbose(path: str | os.PathLike, device: torch.device, *, drop_invalid: bool = False,
                       spz_axes: str = "auto", cameras: CameraSet | None = None,
                       should_stop: StopFn | None = None, notes: NoteFn = print_note) -> GaussianScene:
    """:func:`~artnvg_core.formats.load_scene` onto ``device`` (``drop_invalid``, ``spz_axes``, ``cameras``,
    ``should_stop`` passed on), printing the file size first, one progress bar of the whole load in the file's
    bytes where it lasts (seconds for millions of Gaussians; :data:`SCENE_FILE_BAR_DELAY`), the read's notes
    (to ``notes``, once the bar is gone: printed by default) and the count and time after. The library's advice on invalid Gaussians
    is given as the ``--drop-invalid`` option; running out of memory while loading says so (the other
    options cannot make a scene file smaller)."""
    from ..formats import load_scene
    from ..scene import DROP_INVALID_HINT

    size = os.path.getsize(path) if os.path.isfile(path) else None
    print(f"loading {path} ({size / 2**20:,.1f} MiB)" if size is not None else f"loading {path}", flush=True)
    start, told = time.perf_counter(), []
    try:
        scene = load_scene(path, drop_invalid=drop_invalid, spz_axes=spz_axes, cameras=cameras,
                           progress=ProgressBar("loading", "B", SCENE_FILE_BAR_DELAY),
                           should_stop=should_stop, notes=told.append).to(device)
    except ValueError as error:
        if DROP_INVALID_HINT not in str(error):
            raise
        raise ValueError(str(error).replace(DROP_INVALID_HINT, "give --drop-invalid to drop them")) from None
    except (MemoryError, RuntimeError) as error:
        if is_out_of_memory(error):
            error.advice = f"{path} needs more memory to load than is free on {device}"
        raise
    for note in told:
        notes(note)
    print(f"loaded {counted(len(scene), 'Gaussian')} (SH degree {scene.sh_degree}) in {time.perf_counter() - start:.1f} s",
          flush=True)
    return scene


def is_out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is running out of memory (torch's CPU allocator raises a bare RuntimeError)."""
    return isinstance(error, (MemoryError, torch.OutOfMemoryError)) or (
        isinstance(error, RuntimeError) and "can't allocate memory" in str(error))


@contextlib.contextmanager
def named_option(option: str):
    """For the block, a ValueError names ``option`` first (``--cameras: FILE: ...``): the library's message names
    the file and its field, this the option that gave the file."""
    try:
        yield
    except ValueError as error:
        raise ValueError(f"{option}: {error}") from None


def read_style_image(path: str | os.PathLike, option: str = "--style") -> torch.Tensor:
    """:func:`artnvg_core.style_image.read_style_image` (the image checked and decoded before any other work: a
    scene's load, a model's), its ValueError naming ``option``."""
    from ..style_image import read_style_image as read

    with named_option(option):
        return read(path)


def load_camera_option(args: argparse.Namespace) -> CameraSet | None:
    """The cameras of ``args.cameras`` (:func:`artnvg_core.cameras.load_cameras`), None when it is left out; a
    ValueError names ``--cameras``, or an option of the views built around the scene given beside it
    (``args.orbit_options``, which the cameras would leave unread). The load's notes (the lens distortion ignored)
    go to ``args.notes`` where the command has one (stylize: a batch job keeps them), else are printed."""
    from ..cameras import load_cameras

    if not args.cameras:
        return None
    unread = getattr(args, "orbit_options", [])
    if unread:
        raise ValueError(f"{unread[0]}: the views orbiting the scene are built only without --cameras, whose views "
                         "are used here; give one or the other")
    with named_option("--cameras"):
        return load_cameras(args.cameras, notes=getattr(args, "notes", None) or print_note)
