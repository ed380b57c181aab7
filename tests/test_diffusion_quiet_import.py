"""transformers' torchvision fallback notice is silenced where diffusers' SDXL pipeline is imported,
and nothing else is (artnvg_core.diffusion.quiet_import)."""

import logging
import subprocess
import sys
from pathlib import Path

from artnvg_core.diffusion.quiet_import import NOTICE_LOGGER, torchvision_fallback_notice_silenced

REPO = Path(__file__).resolve().parents[1]
NOTICE = ("`CLIPImageProcessor` requires torchvision (not installed); falling back to `CLIPImageProcessorPil` "
          "for backward compatibility.")


def test_models_module_imports_without_the_notice_when_torchvision_is_missing():
    """A fresh Python in which torchvision cannot be imported (a None entry in sys.modules makes
    find_spec answer None, as for an absent package) imports the models module silently."""
    code = "import sys; sys.modules['torchvision'] = None; import artnvg_core.diffusion.models"
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "torchvision" not in result.stderr, result.stderr


class _Records(logging.Handler):
    def __init__(self):
        super().__init__()
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def test_only_the_notice_is_dropped_and_only_inside_the_block():
    logger, records = logging.getLogger(NOTICE_LOGGER), _Records()
    logger.addHandler(records)
    try:
        with torchvision_fallback_notice_silenced():
            logger.warning(NOTICE)
            logger.warning("`CLIPImageProcessor` could not be loaded")
        logger.warning(NOTICE)
    finally:
        logger.removeHandler(records)
    assert records.messages == ["`CLIPImageProcessor` could not be loaded", NOTICE]
