"""Make a template thumbnail for ComfyUI's template browser from a real run of a shipped workflow.

    python tools/workflow_thumbnail.py example_workflows/NAME.jpg --before CONTENT.png [--after STYLIZED.png] --style STYLE.jpg

The card is SIZE x SIZE pixels: the content render on the left half and the stylized render on the
right half (without ``--after``, the content render alone), the style image inset in the lower
right corner; JPEG, quality 85 (a few tens of kB). The renders come from the workflow's preview
nodes (ComfyUI's temp folder after a run); the style image is the one the workflow loads.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from PIL import Image, ImageOps

SIZE = 256
INSET = 96  # side of the style image's square, px
BORDER = 3


def thumbnail(before: Path, style: Path, after: Path | None = None, size: int = SIZE) -> Image.Image:
    """The card described in the module docstring."""
    card = Image.new("RGB", (size, size))
    halves = [before] if after is None else [before, after]
    width = size // len(halves)
    for index, path in enumerate(halves):
        card.paste(ImageOps.fit(Image.open(path).convert("RGB"), (width, size)), (index * width, 0))
    inset = ImageOps.fit(Image.open(style).convert("RGB"), (INSET, INSET))
    framed = ImageOps.expand(inset, border=BORDER, fill="white")
    card.paste(framed, (size - framed.width - 6, size - framed.height - 6))
    return card


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the thumbnail to write (.jpg beside the workflow)")
    parser.add_argument("--before", type=Path, required=True, help="a content render")
    parser.add_argument("--after", type=Path, help="the same view stylized")
    parser.add_argument("--style", type=Path, required=True, help="the style image")
    args = parser.parse_args(argv)
    thumbnail(args.before, args.style, args.after).save(args.out, "JPEG", quality=85, optimize=True)


if __name__ == "__main__":
    main()
