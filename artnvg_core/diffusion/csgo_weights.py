"""Load CSGO's weights (``csgo_4_32.bin``: 4/32 tokens, ``csgo.bin``: 4/16) in every layout the
released loader reads, strictly where it would keep a random weight.

File layout: a ``torch.save`` dict of key groups (or a ``.safetensors`` file whose keys
carry the group name as prefix, ``content_image_proj.latents`` ...):

* ``content_image_proj`` / ``style_image_proj``: :class:`PerceiverResampler` state dicts;
  the token counts come from the ``latents`` shapes. Strict, as in the released loader.
* ``ip_adapter``: the UNet's image branches, ``{i}.to_k_ip.weight`` / ``{i}.to_v_ip.weight``
  (layout in :mod:`artnvg_core.diffusion.csgo`). The up blocks' style entries are required.
  The down blocks' content entries are optional: a file saved from the released class has
  none (its down blocks are text-only); when all are there they are loaded and the
  ``"paper"`` content routing becomes available.
* ``controlnet_adapter_modules``: the ControlNet's style branches, either indexed the same
  way over the ControlNet's processors, or keyed by module path
  (``down_blocks.1.attentions.0.transformer_blocks.0.attn2.processor.to_k_ip.weight``, the
  layout CSGO's own ``controlnet.load_state_dict(..., strict=False)`` consumes; by module path,
  other ControlNet weights in the group are loaded too, as that call does).
* optional ``conv_in_unet_sd``: a replacement ``unet.conv_in`` state dict.

Like the released loader, other top-level groups and keys no layer reads are ignored, with a
warning naming them on the ``artnvg_core.diffusion.csgo_weights`` logger. Unlike it (``strict=False``),
a missing style, resampler or ControlNet key, or a wrong shape, is a :class:`CSGOWeightsError`
that lists the keys and names the file. The layout found is logged once per load (INFO).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from ..counted import counted
from ..statedict import listed_keys, parameters_on_meta, state_dict_mismatch
from ..tensor_files import load_failure, read_tensors, read_torch_file
from .csgo import (
    CONTROLNET_ROUTES,
    UNET_ROUTES,
    UNET_STYLE_ROUTES,
    CSGOProjections,
    install_processors,
    processor_key_layout,
    routed_keys,
)
from .resampler import PerceiverResampler, resampler_config_from_state_dict

REQUIRED_GROUPS = ("content_image_proj", "style_image_proj", "ip_adapter", "controlnet_adapter_modules")
OPTIONAL_GROUPS = ("conv_in_unet_sd",)

_log = logging.getLogger(__name__)


class CSGOWeightsError(ValueError):
    """A CSGO weight file does not match the expected layout."""


def read_csgo_file(path: str | Path, device: str | torch.device = "cpu") -> dict[str, dict[str, torch.Tensor]]:
    """Read the key groups of a CSGO file (``.bin``/``.pt`` via ``torch.load(weights_only=True)``,
    or ``.safetensors``) straight onto ``device`` (:mod:`artnvg_core.tensor_files`); the required groups
    must be there, others are dropped with a warning."""
    path = Path(path)
    if not path.is_file():
        raise CSGOWeightsError(f"CSGO weights: file '{path}' does not exist")
    if path.suffix == ".safetensors":
        groups: dict[str, dict[str, torch.Tensor]] = {}
        for key, tensor in read_tensors(path, device).items():
            group, _, rest = key.partition(".")
            groups.setdefault(group, {})[rest] = tensor
    else:
        try:
            groups = read_torch_file(path, device)
        except Exception as error:  # unpickling errors have many types
            raise CSGOWeightsError(
                f"CSGO weights '{path}': not a readable torch file ({load_failure(error)})") from error
    if not isinstance(groups, dict):
        raise CSGOWeightsError(f"CSGO weights '{path}': expected a dict of key groups {list(REQUIRED_GROUPS)}")
    missing = [g for g in REQUIRED_GROUPS if g not in groups]
    if missing:
        raise CSGOWeightsError(
            f"CSGO weights '{path}': key groups missing {missing}; expected {list(REQUIRED_GROUPS)} "
            f"(optional {list(OPTIONAL_GROUPS)})"
        )
    ignored = [g for g in groups if g not in REQUIRED_GROUPS + OPTIONAL_GROUPS]
    if ignored:
        _log.warning("CSGO weights '%s': ignored key groups %s (the released loader reads only %s)", path, ignored,
                     list(REQUIRED_GROUPS + OPTIONAL_GROUPS))
    groups = {g: groups[g] for g in REQUIRED_GROUPS + OPTIONAL_GROUPS if g in groups}
    bad = [g for g, value in groups.items() if not isinstance(value, dict)]
    if bad:
        raise CSGOWeightsError(f"CSGO weights '{path}': key groups {bad} are not dicts of tensors")
    return groups


def _fill(
    targets: dict[str, torch.Tensor],
    source: dict[str, torch.Tensor],
    group: str,
    path: Path,
    *,
    optional: dict[str, torch.Tensor] | None = None,
    strict: bool = False,
) -> list[str]:
    """Copy ``source`` into the ``targets`` parameters (every one must be there with its shape) and into
    those of ``optional`` it holds; returns the keys it ignored (with ``strict``, any is an error)."""
    optional = {k: v for k, v in (optional or {}).items() if k in source and k not in targets}
    known = {**targets, **optional}
    ignored = [k for k in source if k not in known]
    mismatch = state_dict_mismatch(known, source if strict else {k: v for k, v in source.items() if k in known})
    if mismatch:
        raise CSGOWeightsError(f"CSGO weights '{path}', group '{group}': {mismatch}")
    with torch.no_grad():
        for key, param in known.items():
            param.copy_(source[key])
    if ignored:
        _log.warning("CSGO weights '%s', group '%s': ignored %s no layer reads %s", path, group, counted(len(ignored), "key"),
                     listed_keys(ignored))
    return ignored


def _load_resampler(state: dict[str, torch.Tensor], group: str, path: Path, dim_head: int) -> PerceiverResampler:
    try:
        config = resampler_config_from_state_dict(state, dim_head=dim_head)
    except ValueError as error:
        raise CSGOWeightsError(f"CSGO weights '{path}', group '{group}': {error}") from error
    with parameters_on_meta():
        resampler = PerceiverResampler(config)
    mismatch = state_dict_mismatch(resampler.state_dict(), state)
    if mismatch:
        raise CSGOWeightsError(f"CSGO weights '{path}', group '{group}': {mismatch}")
    resampler.load_state_dict(state, assign=True)
    return resampler


def _unet_routes(unet: nn.Module, ip_adapter: dict[str, torch.Tensor], path: Path) -> dict[str, str | None]:
    """UNET_ROUTES when ``ip_adapter`` holds every content entry of the down blocks, else UNET_STYLE_ROUTES
    (a partial set is ignored with a warning, as the released loader ignores them all)."""
    content = routed_keys(unet, UNET_ROUTES, "content")
    present = [key for key in content if key in ip_adapter]
    if present and len(present) < len(content):
        _log.warning("CSGO weights '%s': only %d of the %d UNet content entries; all ignored (missing %s)", path,
                     len(present), len(content), listed_keys([k for k in content if k not in ip_adapter]))
    return UNET_ROUTES if len(present) == len(content) else UNET_STYLE_ROUTES


@dataclass
class CSGOFile:
    """A CSGO file read and checked as far as it can be without the models it patches: the two resamplers
    built, the image-branch groups kept as the file's tensors (see the module docstring)."""

    path: Path
    content: PerceiverResampler
    style: PerceiverResampler
    unet_branches: dict[str, torch.Tensor]  # the ``ip_adapter`` group
    controlnet_branches: dict[str, torch.Tensor]  # the ``controlnet_adapter_modules`` group
    conv_in: dict[str, torch.Tensor] | None = None  # the optional ``conv_in_unet_sd`` group


def read_csgo(path: str | Path, dim_head: int = 64, device: str | torch.device = "cpu") -> CSGOFile:
    """The CSGO file at ``path`` read onto ``device`` with its resamplers built (head width ``dim_head``: 64 in
    CSGO, not stored). Raises :class:`CSGOWeightsError` naming the file and group on a missing group or a
    bad resampler."""
    path = Path(path)
    groups = read_csgo_file(path, device)
    return CSGOFile(
        path=path,
        content=_load_resampler(groups["content_image_proj"], "content_image_proj", path, dim_head),
        style=_load_resampler(groups["style_image_proj"], "style_image_proj", path, dim_head),
        unet_branches=groups["ip_adapter"],
        controlnet_branches=groups["controlnet_adapter_modules"],
        conv_in=groups.get("conv_in_unet_sd"),
    )


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
    Raises :class:`CSGOWeightsError` on a missing or mis-shaped key (see the module docstring).
    """
    csgo = read_csgo(path, dim_head, unet.conv_in.weight.device)
    path, content, style = csgo.path, csgo.content, csgo.style
    cross_dim = unet.config.cross_attention_dim
    for name, resampler in (("content_image_proj", content), ("style_image_proj", style)):
        if resampler.config.output_dim != cross_dim:
            raise CSGOWeightsError(
                f"CSGO weights '{path}', group '{name}': output width {resampler.config.output_dim} "
                f"!= the UNet's cross_attention_dim {cross_dim}"
            )
    unet_routes = _unet_routes(unet, csgo.unet_branches, path)
    install_processors(unet, unet_routes, query_chunk_size=query_chunk_size, initialise=False)
    install_processors(controlnet, CONTROLNET_ROUTES, query_chunk_size=query_chunk_size, initialise=False)
    _fill(processor_key_layout(unet), csgo.unet_branches, "ip_adapter", path)
    controlnet_keys = csgo.controlnet_branches
    by_index = all(key.split(".", 1)[0].isdigit() for key in controlnet_keys)
    others = {} if by_index else dict(controlnet.state_dict(keep_vars=True))
    ignored = _fill(processor_key_layout(controlnet, by_index), controlnet_keys, "controlnet_adapter_modules", path,
                    optional=others)
    if csgo.conv_in is not None:
        _fill(dict(unet.conv_in.state_dict(keep_vars=True)), csgo.conv_in, "conv_in_unet_sd", path,
              strict=True)
    replaced = len(controlnet_keys) - len(ignored) - len(processor_key_layout(controlnet, by_index))
    _log.info(
        "CSGO weights '%s': %d content / %d style tokens; UNet content entries %s; ControlNet entries keyed by %s%s%s",
        path, content.config.num_queries, style.config.num_queries,
        "loaded (content routing 'paper' available)" if unet_routes is UNET_ROUTES else "absent (as saved by the "
        "released code; content routing 'released' only)", "processor index" if by_index else "module path",
        f", {counted(replaced, 'other ControlNet weight')} replaced" if replaced else "",
        ", UNet conv_in replaced" if csgo.conv_in is not None else "",
    )
    weight = unet.conv_in.weight
    projections = CSGOProjections(content, style, unet_content=unet_routes is UNET_ROUTES)
    return projections.to(device=weight.device, dtype=weight.dtype)
