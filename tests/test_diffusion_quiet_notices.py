"""transformers' torchvision fallback notice is silenced where diffusers' SDXL pipeline is imported,
diffusers' empty float32 notice where SDXL is loaded, the libraries' progress bars while the models load,
and nothing else is (artnvg_core.diffusion.quiet_notices)."""

import logging
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from artnvg_core.diffusion.models import load_sdxl
from artnvg_core.diffusion.quiet_notices import (
    FLOAT32_LOGGER,
    NOTICE_LOGGER,
    library_progress_bars_hidden,
    sdxl_loading_notices_silenced,
    torchvision_fallback_notice_silenced,
)
from diffusion_tiny import diffusers_pipeline, tiny_base, tiny_scheduler

REPO = Path(__file__).resolve().parents[1]
NOTICE = ("`CLIPImageProcessor` requires torchvision (not installed); falling back to `CLIPImageProcessorPil` "
          "for backward compatibility.")


@pytest.mark.slow
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


def test_only_the_empty_float32_notice_is_dropped():
    logger, records = logging.getLogger(FLOAT32_LOGGER), _Records()
    empty = ("There are modules in UNet2DConditionModel that should be kept in float32: []. Casting directly with "
             "`to()` can lead to inconsistent results")
    listed = empty.replace("[]", "['norm_out']")
    logger.addHandler(records)
    try:
        with sdxl_loading_notices_silenced():
            logger.warning(empty)
            logger.warning(listed)
        logger.warning(empty)
    finally:
        logger.removeHandler(records)
    assert records.messages == [listed, empty]


def test_loading_sdxl_in_another_dtype_shows_no_notice(tmp_path):
    """From a diffusers folder, diffusers 0.42 warns that ``torch_dtype`` is deprecated (the versions
    we support know no other keyword) unless it is ignored; nothing is logged."""
    import warnings

    diffusers_pipeline(tiny_base(), tiny_scheduler()).save_pretrained(tmp_path / "sdxl")
    logger, records = logging.getLogger("diffusers"), _Records()
    logger.addHandler(records)
    try:
        with warnings.catch_warnings(record=True) as shown:
            warnings.simplefilter("always")
            base = load_sdxl(tmp_path / "sdxl", dtype=torch.bfloat16)
    finally:
        logger.removeHandler(records)
    assert base.unet.dtype == torch.bfloat16
    assert not records.messages and not [str(w.message) for w in shown], (records.messages, shown)


def test_the_libraries_progress_bars_are_hidden_within_the_block_only():
    """Switched on again after it; one the user switched off stays off. (Their absence from a stylize's
    terminal: tests/test_stylize.py.)"""
    from diffusers.utils import logging as diffusers_logging
    from transformers.utils import logging as transformers_logging

    with library_progress_bars_hidden():
        assert not transformers_logging.is_progress_bar_enabled() and not diffusers_logging.is_progress_bar_enabled()
    assert transformers_logging.is_progress_bar_enabled() and diffusers_logging.is_progress_bar_enabled()
    diffusers_logging.disable_progress_bar()
    try:
        with library_progress_bars_hidden():
            pass
        assert transformers_logging.is_progress_bar_enabled() and not diffusers_logging.is_progress_bar_enabled()
    finally:
        diffusers_logging.enable_progress_bar()
