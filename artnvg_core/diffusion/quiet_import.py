"""Importing diffusers' SDXL pipeline without transformers' torchvision notice.

Without torchvision, transformers (5.x) answers a request for ``CLIPImageProcessor`` or
``SiglipImageProcessor`` with their PIL versions and logs, once per class, "`CLIPImageProcessor`
requires torchvision (not installed); falling back to `CLIPImageProcessorPil` ...". diffusers'
SDXL pipeline module (and its IP-Adapter loader) ask for both when imported. ArtNVG never uses
them (its image preprocessing is in torch: :mod:`.images`), so the notice says nothing to our
users: :func:`torchvision_fallback_notice_silenced` drops exactly these records, from the one
transformers logger that emits them, while a ``with`` block runs. Everything else is logged.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

NOTICE_LOGGER = "transformers.utils.import_utils"
NOTICE_TEXT = "requires torchvision (not installed); falling back to"


class _FallbackNoticeFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return NOTICE_TEXT not in record.getMessage()


@contextmanager
def torchvision_fallback_notice_silenced() -> Iterator[None]:
    """Within the block, transformers' image-processor torchvision fallback notice is not logged."""
    logger, notice_filter = logging.getLogger(NOTICE_LOGGER), _FallbackNoticeFilter()
    logger.addFilter(notice_filter)
    try:
        yield
    finally:
        logger.removeFilter(notice_filter)
