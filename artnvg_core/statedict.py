"""Strict state-dict matching with readable errors (:func:`assign_strict` gives a module a state dict's
tensors, every key checked), and building modules without random weights for a state dict to fill: shared
by every weight loader."""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager

import torch

from .counted import counted

LISTED_KEYS = 8  # keys shown per kind of mismatch


def listed_keys(keys: list[str]) -> str:
    """``keys`` sorted, as ``[a, b, ... (n more)]`` (at most LISTED_KEYS shown)."""
    more = len(keys) - LISTED_KEYS
    return f"[{', '.join(sorted(keys)[:LISTED_KEYS])}{f', ... ({more} more)' if more > 0 else ''}]"


def is_state_dict(value) -> bool:
    """True for a dict of names (str) to tensors, what ``torch.load`` of a weights file should give; a loader
    refuses anything else (a list, a key that is no string, a value that is no tensor), naming the file."""
    return isinstance(value, dict) and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in value.items())


def state_dict_mismatch(expected: Mapping[str, torch.Tensor], state: Mapping[str, torch.Tensor]) -> str | None:
    """None when ``state`` has exactly the keys of ``expected``, each with the same shape;
    otherwise a message counting and listing the missing, unexpected and mis-shaped keys."""
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    wrong = [f"{k} {list(state[k].shape)} != {list(v.shape)}" for k, v in expected.items()
             if k in state and state[k].shape != v.shape]
    if not (missing or unexpected or wrong):
        return None
    text = (f"{counted(len(missing), 'missing key')} {listed_keys(missing)}, "
            f"{counted(len(unexpected), 'unexpected key')} {listed_keys(unexpected)}")
    return text + (f", {counted(len(wrong), 'wrong shape')} {wrong[:LISTED_KEYS]}" if wrong else "")


def assign_strict(model: torch.nn.Module, state: dict[str, torch.Tensor], what: str) -> None:
    """Make ``state``'s tensors ``model``'s (``load_state_dict(assign=True)``: no copy); every key must match
    in name and shape, else ValueError starting with ``what`` and listing the missing, unexpected and
    mis-shaped keys. Entries for the model's non-persistent buffers (e.g. CLIP ``position_ids`` in older
    files) are ignored: the model computes them itself, and they follow the state's tensors to their device."""
    expected = model.state_dict(keep_vars=True)
    recomputed = {name for name, _ in model.named_buffers()} - set(expected)
    state = {k: v for k, v in state.items() if k not in recomputed}
    mismatch = state_dict_mismatch(expected, state)
    if mismatch:
        raise ValueError(f"{what} do not fit {type(model).__name__}: {mismatch}")
    modules = dict(model.named_modules(remove_duplicate=False))
    _assign(model, modules, state)
    device = next(iter(state.values())).device if state else None
    for name in recomputed:
        owner, _, buffer = name.rpartition(".")
        modules[owner]._buffers[buffer] = modules[owner]._buffers[buffer].to(device)


def _assign(model: torch.nn.Module, modules: dict[str, torch.nn.Module], state: dict[str, torch.Tensor]) -> None:
    """``model.load_state_dict(state, assign=True)`` for a ``state`` that fits it (``modules``: its modules by
    name): each tensor made its module's parameter (keeping its ``requires_grad``) or buffer, without
    load_state_dict's work per module and tensor (checks, hooks, a no_grad block: 27 ms of the interpreter lock
    for SDXL's UNet against 7 ms). A model with a module that loads its own way (load hooks, its class's own
    ``_load_from_state_dict`` or ``set_extra_state``) goes through load_state_dict."""
    base = torch.nn.Module
    if any(module._load_state_dict_pre_hooks or module._load_state_dict_post_hooks
           or type(module)._load_from_state_dict is not base._load_from_state_dict
           or type(module).set_extra_state is not base.set_extra_state for module in modules.values()):
        model.load_state_dict(state, assign=True)
        return
    for key, tensor in state.items():
        owner, _, name = key.rpartition(".")
        module = modules[owner]
        if name in module._parameters:
            module._parameters[name] = torch.nn.Parameter(tensor, requires_grad=module._parameters[name].requires_grad)
        else:
            module._buffers[name] = tensor


_this_thread = threading.local()  # .blocks: this thread's open parameters_on_meta blocks
_patch_lock = threading.Lock()  # guards _open_blocks and _replaced
_open_blocks = 0  # every thread's open blocks: PyTorch is patched while > 0
_replaced: dict[tuple[type, str], Callable] = {}  # (class, function name): the function the patch replaced


@contextmanager
def parameters_on_meta() -> Iterator[None]:
    """Modules that this thread builds inside this context get their parameters on the meta device: no memory
    and no random initialisation, for weights a file is about to replace (the :data:`UNINITIALISED` layers skip
    their ``reset_parameters``, which would only run on meta tensors). Buffers stay real (a model's
    computed buffers, e.g. CLIP's position ids, keep their values). The parameters are marked initialised
    (``_is_hf_initialized``), so transformers' initialisation of a model it builds leaves them alone: on meta
    tensors it ran PyTorch's meta kernels in Python, 0.23 s of the interpreter lock for SDXL's text encoders and
    the image encoder. Fill them with :func:`assign_strict` (``load_state_dict(state, assign=True)``), which
    takes the state's tensors.

    Threads: PyTorch is patched (``Module.register_parameter`` and the layers' ``reset_parameters``) from the
    first entry of any thread to the last exit, and the patches act only for a thread inside a block, so a
    module another thread builds meanwhile (a load runs beside the caller's thread and ComfyUI's server) gets
    real, initialised parameters. Blocks nest and run in several threads at once; once no thread is inside,
    PyTorch's functions are again the very ones the first entry found."""
    global _open_blocks
    with _patch_lock:
        if _open_blocks == 0:
            _patch()
        _open_blocks += 1
    _this_thread.blocks = getattr(_this_thread, "blocks", 0) + 1
    try:
        yield
    finally:
        _this_thread.blocks -= 1
        with _patch_lock:
            _open_blocks -= 1
            if _open_blocks == 0:
                _unpatch()


def _on_meta_or(original: Callable, on_meta: Callable) -> Callable:
    """``original``, but ``on_meta`` for a thread inside :func:`parameters_on_meta`."""
    @functools.wraps(original)
    def patched(*args, **kwargs):
        return (on_meta if getattr(_this_thread, "blocks", 0) else original)(*args, **kwargs)
    return patched


def _patch() -> None:
    """Replace ``Module.register_parameter`` and the :data:`UNINITIALISED` layers' ``reset_parameters`` (noted
    in ``_replaced``) by functions that act only for a thread inside :func:`parameters_on_meta`."""
    register = torch.nn.Module.register_parameter

    def register_on_meta(module: torch.nn.Module, name: str, param: torch.nn.Parameter | None) -> None:
        if param is not None:
            if not param.is_meta:
                param = torch.nn.Parameter(param.to("meta"), requires_grad=param.requires_grad)
            param._is_hf_initialized = True
        register(module, name, param)

    on_meta = {(torch.nn.Module, "register_parameter"): register_on_meta,
               **{(layer, "reset_parameters"): _no_reset for layer in UNINITIALISED}}
    for (owner, name), replacement in on_meta.items():
        _replaced[owner, name] = owner.__dict__[name]
        setattr(owner, name, _on_meta_or(owner.__dict__[name], replacement))


def _unpatch() -> None:
    """Put back the functions :func:`_patch` replaced."""
    for (owner, name), original in _replaced.items():
        setattr(owner, name, original)
    _replaced.clear()


def _no_reset(self: torch.nn.Module) -> None:
    """A layer's ``reset_parameters`` inside :func:`parameters_on_meta`: its parameters are meta, nothing to set."""


# the layers whose reset_parameters sets their own parameters only (kept within parameters_on_meta)
UNINITIALISED = (torch.nn.Linear, torch.nn.modules.conv._ConvNd, torch.nn.Embedding, torch.nn.LayerNorm,
                 torch.nn.GroupNorm)
