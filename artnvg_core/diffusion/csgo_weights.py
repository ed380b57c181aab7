"""Load CSGO's released weights (``csgo_4_32.bin``: 4/32 tokens, ``csgo.bin``: 4/16) strictly.

File layout: a ``torch.save`` dict of key groups (or a ``.safetensors`` file whose keys
carry the group name as prefix, ``content_image_proj.latents`` ...):

* ``content_image_proj`` / ``style_image_proj``: :class:`PerceiverResampler` state dicts;
  the token counts come from the ``latents`` shapes.
* ``ip_adapter``: the UNet's image branches, ``{i}.to_k_ip.weight`` / ``{i}.to_v_ip.weight``
  (layout in :mod:`artnvg_core.diffusion.csgo`).
* ``controlnet_adapter_modules``: the ControlNet's image branches, either indexed the same
  way over the ControlNet's processors, or keyed by module path
  (``down_blocks.1.attentions.0.transformer_blocks.0.attn2.processor.to_k_ip.weight``, the
  only layout CSGO's own ``controlnet.load_state_dict(..., strict=False)`` would consume).
* optional ``conv_in_unet_sd``: a replacement ``unet.conv_in`` state dict.

Unlike the released loader (``strict=False``), every key must be consumed and every
expected parameter filled with the right shape; otherwise :class:`CSGOWeightsError`
lists the missing and unexpected keys per group and names the file.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from ..statedict import state_dict_mismatch
from .csgo import (
    CONTROLNET_ROUTES,
    UNET_ROUTES,
    CSGOProjections,
    install_processors,
    processor_key_layout,
)
from .resampler import PerceiverResampler, resampler_config_from_state_dict

REQUIRED_GROUPS = ("content_image_proj", "style_image_proj", "ip_adapter", "controlnet_adapter_modules")
OPTIONAL_GROUPS = ("conv_in_unet_sd",)


class CSGOWeightsError(ValueError):
    """A CSGO weight file does not match the expected layout."""


def read_csgo_file(path: str | Path) -> dict[str, dict[str, torch.Tensor]]:
    """Read the key groups of a CSGO file (``.bin``/``.pt`` via ``torch.load(weights_only=True)``,
    or ``.safetensors``) onto the CPU, checking that the required groups are there and no others."""
    path = Path(path)
    if not path.is_file():
        raise CSGOWeightsError(f"CSGO weights: file '{path}' does not exist")
    known = REQUIRED_GROUPS + OPTIONAL_GROUPS
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        groups: dict[str, dict[str, torch.Tensor]] = {}
        for key, tensor in load_file(str(path)).items():
            group, _, rest = key.partition(".")
            groups.setdefault(group, {})[rest] = tensor
    else:
        try:
            groups = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:  # unpickling errors have many types
            raise CSGOWeightsError(f"CSGO weights '{path}': not a readable torch file ({error})") from error
    if not isinstance(groups, dict) or not all(isinstance(g, dict) for g in groups.values()):
        raise CSGOWeightsError(f"CSGO weights '{path}': expected a dict of key groups {list(REQUIRED_GROUPS)}")
    missing = [g for g in REQUIRED_GROUPS if g not in groups]
    unexpected = [g for g in groups if g not in known]
    if missing or unexpected:
        raise CSGOWeightsError(
            f"CSGO weights '{path}': key groups missing {missing}, unexpected {unexpected}; expected "
            f"{list(REQUIRED_GROUPS)} (optional {list(OPTIONAL_GROUPS)})"
        )
    return groups


def _fill(targets: dict[str, torch.Tensor], source: dict[str, torch.Tensor], group: str, path: Path) -> None:
    """Copy ``source`` into the ``targets`` parameters; all keys must match with equal shapes."""
    mismatch = state_dict_mismatch(targets, source)
    if mismatch:
        raise CSGOWeightsError(f"CSGO weights '{path}', group '{group}': {mismatch}")
    with torch.no_grad():
        for key, param in targets.items():
            param.copy_(source[key])


def _load_resampler(state: dict[str, torch.Tensor], group: str, path: Path, dim_head: int) -> PerceiverResampler:
    try:
        config = resampler_config_from_state_dict(state, dim_head=dim_head)
    except ValueError as error:
        raise CSGOWeightsError(f"CSGO weights '{path}', group '{group}': {error}") from error
    resampler = PerceiverResampler(config)
    _fill(dict(resampler.state_dict(keep_vars=True)), state, group, path)
    return resampler


def load_csgo(
    path: str | Path,
    unet: nn.Module,
    controlnet: nn.Module,
    *,
    dim_head: int = 64,
    query_chunk_size: int | None = None,
) -> CSGOProjections:
    """Install ArtNVG processors on ``unet`` and ``controlnet``, fill them from the CSGO file at
    ``path`` and return the content/style resamplers (on the UNet's device and dtype).

    dim_head: the resamplers' head width (64 in CSGO; not stored in the file).
    Raises :class:`CSGOWeightsError` on any layout mismatch (see the module docstring).
    """
    path = Path(path)
    groups = read_csgo_file(path)
    content = _load_resampler(groups["content_image_proj"], "content_image_proj", path, dim_head)
    style = _load_resampler(groups["style_image_proj"], "style_image_proj", path, dim_head)
    cross_dim = unet.config.cross_attention_dim
    for name, resampler in (("content_image_proj", content), ("style_image_proj", style)):
        if resampler.config.output_dim != cross_dim:
            raise CSGOWeightsError(
                f"CSGO weights '{path}', group '{name}': output width {resampler.config.output_dim} "
                f"!= the UNet's cross_attention_dim {cross_dim}"
            )
    install_processors(unet, UNET_ROUTES, query_chunk_size=query_chunk_size)
    install_processors(controlnet, CONTROLNET_ROUTES, query_chunk_size=query_chunk_size)
    _fill(processor_key_layout(unet), groups["ip_adapter"], "ip_adapter", path)
    controlnet_keys = groups["controlnet_adapter_modules"]
    by_index = all(key.split(".", 1)[0].isdigit() for key in controlnet_keys)
    _fill(processor_key_layout(controlnet, by_index), controlnet_keys, "controlnet_adapter_modules", path)
    if "conv_in_unet_sd" in groups:
        _fill(dict(unet.conv_in.state_dict(keep_vars=True)), groups["conv_in_unet_sd"], "conv_in_unet_sd", path)
    weight = unet.conv_in.weight
    return CSGOProjections(content, style).to(device=weight.device, dtype=weight.dtype)
