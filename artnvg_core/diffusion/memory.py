"""Memory savers of the diffusion stage for small GPUs (a 15-view group at 1024x1024 in 12 GiB).

The compute device is the UNet's. Any other model left on another device (the CPU) *visits*
the compute device only while it runs (:func:`visiting`: the ControlNet for each denoising
pass, the text encoders, the image encoder and the VAE when they are needed), so
:func:`enable_low_memory` keeps just the UNet resident; the visitors' CPU weights are pinned so
that each visit is one fast host-to-device copy and leaving is free. With
:attr:`SamplerSettings.sequential_cfg` the two classifier-free-guidance halves also run one after
the other. All of it is exact (batch sizes differ, so results change by rounding at most), at the
cost of the copies: about 2.3 GiB per ControlNet pass for SDXL's.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from .models import DiffusionModels


def _same_device(a: torch.device, b: torch.device) -> bool:
    return a.type == b.type and (a.index or 0) == (b.index or 0)


def _slots(module: nn.Module) -> list[tuple[dict, str]]:
    """(dictionary, key) of every parameter and buffer of ``module`` and its submodules."""
    return [(store, key) for sub in module.modules() for store in (sub._parameters, sub._buffers)
            for key, value in store.items() if value is not None]


@contextmanager
def visiting(module: nn.Module | None, device: torch.device) -> Iterator[None]:
    """``module``'s weights copied to ``device`` inside the block; afterwards it holds its own
    weights again and the copies are freed (a no-op for None or a module already on ``device``).
    Inference only: changes made to the copies are dropped."""
    slots = [] if module is None else _slots(module)
    device = torch.device(device)
    if not slots or _same_device(slots[0][0][slots[0][1]].device, device):
        yield
        return
    homes = [store[key] for store, key in slots]
    for (store, key), home in zip(slots, homes):
        copy = home.detach().to(device, non_blocking=True)
        store[key] = nn.Parameter(copy, requires_grad=home.requires_grad) if isinstance(home, nn.Parameter) else copy
    try:
        yield
    finally:
        for (store, key), home in zip(slots, homes):
            store[key] = home


def enable_low_memory(models: DiffusionModels, device: str | torch.device | None = None) -> None:
    """Keep only the UNet and the CSGO resamplers on ``device`` (default: the UNet's); move the
    ControlNet, the text encoders, the image encoder and the VAE to pinned CPU memory (they visit
    the device, see the module docstring); run the transformer feed-forward layers one sample at a
    time. Load the models on the CPU and call this to never hold them all on the GPU.
    Calling it again is cheap: nothing is moved or pinned twice."""
    base = models.base
    device = base.unet.device if device is None else torch.device(device)
    for resident in (base.unet, models.csgo):
        if resident is not None:
            resident.to(device)
    for idle in (models.controlnet, base.text_encoder, base.text_encoder_2, base.vae, models.image_encoder):
        if idle is None:
            continue
        idle.to("cpu")
        if torch.cuda.is_available():
            for store, key in _slots(idle):
                if not store[key].is_pinned():
                    store[key].data = store[key].data.pin_memory()
    for model in (base.unet, models.controlnet):
        for module in model.modules():
            if hasattr(module, "set_chunk_feed_forward"):  # diffusers' BasicTransformerBlock
                module.set_chunk_feed_forward(1, 0)
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
