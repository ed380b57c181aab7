"""Triton launches as a compilation sees them: what Triton specializes a kernel on (interpreted in Triton's CPU
interpreter or compiled for a GPU: the same arguments either way), and the launches a test makes, recorded."""

import torch
from triton.runtime.interpreter import InterpretedFunction
from triton.runtime.jit import JITFunction


def _argument(value, specialize: bool):
    """Triton's specialization of one argument: a tensor's dtype and 16-byte alignment, an int's type and whether
    it is 1 or a multiple of 16 (neither nor the alignment where the kernel does not specialize on it)."""
    if isinstance(value, torch.Tensor):
        return ("tensor", value.dtype, specialize and value.data_ptr() % 16 == 0)
    if isinstance(value, bool):
        return ("bool",)
    if isinstance(value, int):
        kind = "i32" if -2**31 <= value < 2**31 else "i64"
        return (kind, specialize and value == 1, specialize and value % 16 == 0)
    if isinstance(value, float):
        return ("fp32",)
    raise TypeError(f"no specialization known for {value!r}")


def _unspecialized(kernel: InterpretedFunction | JITFunction) -> set[str]:
    """The names of the arguments ``kernel`` is told not to specialize on (``do_not_specialize``: names or
    positions)."""
    given = kernel.kwargs.get("do_not_specialize") if isinstance(kernel, InterpretedFunction) else kernel.do_not_specialize
    return {kernel.arg_names[n] if isinstance(n, int) else n for n in given or ()}


def specialization(kernel: InterpretedFunction | JITFunction, args: tuple, kwargs: dict) -> tuple:
    """What Triton compiles ``kernel`` launched with ``args`` and ``kwargs`` (constants, warps) for."""
    unspecialized = _unspecialized(kernel)
    arguments = tuple(_argument(value, name not in unspecialized) for name, value in zip(kernel.arg_names, args))
    assert len(args) == len([name for name in kernel.arg_names if name not in kwargs]), "every argument given"
    return f"{kernel.fn.__module__}.{kernel.fn.__name__}", arguments, tuple(sorted(kwargs.items()))


def warmed(warmups) -> set:
    """The specializations ``warmups`` (:class:`~artnvg_core.triton_runtime.Warmup`) compile."""
    return {specialization(w.kernel, w.args, w.kwargs) for w in warmups}


def _recording(run, launched: set):
    """``run`` (a kernel class's launch) that first adds each launch's specialization to ``launched``."""
    def recording(self, *args, grid, warmup, **kwargs):
        if not warmup:
            launched.add(specialization(self, args, kwargs))
        return run(self, *args, grid=grid, warmup=warmup, **kwargs)

    return recording


def record_launches(monkeypatch) -> set:
    """The specializations of every Triton launch made from now on (in the test; interpreted or compiled, not
    the warm-ups' compilations), filled as they are made."""
    launched = set()
    for kind in (InterpretedFunction, JITFunction):
        monkeypatch.setattr(kind, "run", _recording(kind.run, launched))
    return launched
