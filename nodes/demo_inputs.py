"""The demo inputs the shipped workflows name, put into ComfyUI's input folder when the pack loads.

The workflows read ``artnvg_demo/bear.ply`` and ``artnvg_demo/transforms.json`` (with the demo's
README and licences beside them) and the style image ``artnvg_demo_style.jpg``, which sits at the top
of the input folder because Load Image lists only that level. :func:`install_demo_inputs` copies
whichever of them is missing from the pack's ``artnvg_core/demo``; it never overwrites a file, so
a user's edits stay, and a deleted file comes back at the next start.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from artnvg_core.fileio import write_atomically
from artnvg_core.stylize import DEMO_DIR

DEMO_FOLDER = "artnvg_demo"
DEMO_STYLE = "artnvg_demo_style.jpg"
DEMO_SCENE = f"{DEMO_FOLDER}/bear.ply"
DEMO_CAMERAS = f"{DEMO_FOLDER}/transforms.json"

_log = logging.getLogger("artnvg")


def demo_files() -> dict[str, Path]:
    """Path relative to the input folder (POSIX) -> the pack's file it is copied from."""
    files = {f"{DEMO_FOLDER}/{source.name}": source for source in sorted(DEMO_DIR.iterdir())
             if source.is_file() and source.name != "style.jpg"}
    files[DEMO_STYLE] = DEMO_DIR / "style.jpg"
    return files


def _copy(source: Path, target: Path) -> None:
    """Copy ``source`` to ``target`` whole or not at all (:func:`~artnvg_core.fileio.write_atomically`)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    with source.open("rb") as original:
        write_atomically(target, lambda stream: shutil.copyfileobj(original, stream))


def install_demo_inputs(input_dir: Path) -> list[str]:
    """Copy the demo files missing from ``input_dir`` (module docstring); returns the names copied.

    Logs one line naming them when any were copied. An unwritable input folder is logged, not raised:
    the pack still loads, and the loaders' errors then say where the files belong.
    """
    missing = {name: source for name, source in demo_files().items() if not (input_dir / name).exists()}
    try:
        for name, source in missing.items():
            _copy(source, input_dir / name)
    except OSError as error:
        _log.warning("ArtNVG: could not put the demo inputs into %s (%s); the shipped workflows need "
                     "%s/ and %s there (copies of the pack's artnvg_core/demo)", input_dir, error, DEMO_FOLDER, DEMO_STYLE)
        return []
    if missing:
        _log.warning("ArtNVG: put the demo inputs of the shipped workflows into %s: %s", input_dir, ", ".join(missing))
    return list(missing)
