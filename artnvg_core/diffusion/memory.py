"""Memory savers of the diffusion stage for small GPUs (a 15-view group at 1024x1024 in 12 GiB).

The compute device is the UNet's. Any other model left on another device (the CPU) *visits*
the compute device only while it runs (:func:`visiting`; the sampler and
:func:`artnvg_core.diffusion.conditioning.prepare_conditioning` do this for the text
encoders, the image encoder and the VAE), so :func:`enable_low_memory` keeps just the UNet
and the ControlNet resident. With :attr:`SamplerSettings.sequential_cfg` the two
classifier-free-guidance halves also run one after the other. All of it is exact: results
change by floating-point rounding only (batch sizes differ), at the cost of host-device copies.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from .models import DiffusionModels


@contextmanager
def visiting(module: nn.Module | None, device: torch.device) -> Iterator[None]:
    """``module`` on ``device`` inside the block and back on its own device afterwards
    (a no-op for None or a module already there)."""
    home = None if module is None else next(module.parameters()).device
    if home is None or home == device:
        yield
        return
    module.to(device)
    try:
        yield
    finally:
        module.to(home)


def enable_low_memory(models: DiffusionModels, device: str | torch.device | None = None) -> None:
    """Keep only the UNet, the ControlNet and the CSGO resamplers on ``device`` (default: the UNet's),
    the rest on the CPU (it visits the device, see the module docstring), and run the transformer
    feed-forward layers one sample at a time. Load the models on the CPU and call this to never
    hold them all on the GPU."""
    base = models.base
    device = base.unet.device if device is None else torch.device(device)
    for idle in (base.text_encoder, base.text_encoder_2, base.vae, models.image_encoder):
        if idle is not None:
            idle.to("cpu")
    for model in (base.unet, models.controlnet, models.csgo):
        if model is None:
            continue
        model.to(device)
        for module in model.modules():
            if hasattr(module, "set_chunk_feed_forward"):  # diffusers' BasicTransformerBlock
                module.set_chunk_feed_forward(1, 0)
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
