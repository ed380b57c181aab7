"""Third-party log records that say nothing to ArtNVG's users, dropped exactly, only while a block runs.

* transformers' torchvision notice: without torchvision, transformers (5.x) answers a request for
  ``CLIPImageProcessor`` or ``SiglipImageProcessor`` with their PIL versions and logs, once per class,
  "`CLIPImageProcessor` requires torchvision (not installed); falling back to `CLIPImageProcessorPil`
  ...". diffusers' SDXL pipeline module (and its IP-Adapter loader) ask for both when imported. ArtNVG
  never uses them (its image preprocessing is in torch: :mod:`.images`):
  :func:`torchvision_fallback_notice_silenced` around that import.
* Loading SDXL (:func:`sdxl_loading_notices_silenced`): a diffusers model's ``to(dtype)`` logs "There
  are modules in UNet2DConditionModel that should be kept in float32: []. Casting directly with `to()`
  ..." even when that list is empty, as it is for every SDXL model, and ``from_single_file`` casts that
  way: records whose list is empty are dropped (a non-empty list is still logged). diffusers 0.42
  warns (FutureWarning) that ``torch_dtype`` will be renamed ``dtype`` in 1.0; the versions we support
  (0.39 on) know only ``torch_dtype``: that warning is ignored.
* Fusing LoRAs (:func:`lora_loading_notices_silenced`): diffusers logs "No LoRA keys associated to
  CLIPTextModel ..." for each model a LoRA leaves alone (most LoRAs change the UNet only), and an error
  record for a LoRA it cannot load, which :func:`~artnvg_core.diffusion.lora.fuse_loras` raises itself,
  naming the file: both are dropped, as is PEFT's warning that a model holds several adapters (it does,
  by request, until they are fused).
* Loading the models (:func:`library_progress_bars_hidden`): transformers draws a "Loading weights" bar for
  each model its ``from_pretrained`` loads (SDXL's text encoders), diffusers one for sharded weights. The
  loader follows the models itself (bytes of every file), often in a background thread beside the caller's
  own bar (the content views' renders): theirs are hidden (each library's switch, restored after).

Each drops its records from the one logger (or warning) that emits them; everything else is logged.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

NOTICE_LOGGER = "transformers.utils.import_utils"
NOTICE_TEXT = "requires torchvision (not installed); falling back to"
FLOAT32_LOGGER = "diffusers.models.modeling_utils"
FLOAT32_TEXT = "that should be kept in float32: []."
TORCH_DTYPE_WARNING = "`torch_dtype` is deprecated"
LORA_LOGGERS = ("diffusers.loaders.lora_base", "diffusers.loaders.peft")
LORA_TEXTS = ("No LoRA keys associated to", "was unsuccessful with the following error")
SEVERAL_ADAPTERS_WARNING = "Already found a `peft_config` attribute in the model"


@contextmanager
def _dropped(logger_name: str, *texts: str) -> Iterator[None]:
    """Within the block, records of ``logger_name`` whose message contains one of ``texts`` are not logged."""
    logger = logging.getLogger(logger_name)

    def record_filter(record: logging.LogRecord) -> bool:
        return not any(text in record.getMessage() for text in texts)

    logger.addFilter(record_filter)
    try:
        yield
    finally:
        logger.removeFilter(record_filter)


def torchvision_fallback_notice_silenced():
    """Within the block, transformers' image-processor torchvision fallback notice is not logged."""
    return _dropped(NOTICE_LOGGER, NOTICE_TEXT)


@contextmanager
def sdxl_loading_notices_silenced() -> Iterator[None]:
    """Within the block, diffusers' "should be kept in float32: []" notice (an empty list) is not logged
    and its ``torch_dtype`` FutureWarning not shown."""
    with _dropped(FLOAT32_LOGGER, FLOAT32_TEXT), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=TORCH_DTYPE_WARNING, category=FutureWarning)
        yield


@contextmanager
def lora_loading_notices_silenced() -> Iterator[None]:
    """Within the block, diffusers' "No LoRA keys associated to ..." notices and its error record for a LoRA
    it cannot load are not logged, and PEFT's several-adapters warning is not shown."""
    with _dropped(LORA_LOGGERS[0], *LORA_TEXTS), _dropped(LORA_LOGGERS[1], *LORA_TEXTS), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=SEVERAL_ADAPTERS_WARNING, category=UserWarning)
        yield


@contextmanager
def library_progress_bars_hidden() -> Iterator[None]:
    """Within the block, transformers' and diffusers' own progress bars are not drawn (in any thread: each
    library has one switch); those that were on are switched on again after it."""
    from diffusers.utils import logging as diffusers_logging
    from transformers.utils import logging as transformers_logging

    switched = [library for library in (transformers_logging, diffusers_logging) if library.is_progress_bar_enabled()]
    for library in switched:
        library.disable_progress_bar()
    try:
        yield
    finally:
        for library in switched:
            library.enable_progress_bar()
