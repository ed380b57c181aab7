"""Triton launches as a compilation sees them: what Triton specializes a kernel on (for the interpreter's
kernels, which take the same arguments as compiled ones), and the launches a test makes, recorded."""

import torch
from triton.runtime.interpreter import InterpretedFunction


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


def specialization(kernel: InterpretedFunction, args: tuple, kwargs: dict) -> tuple:
    """What Triton compiles ``kernel`` launched with ``args`` and ``kwargs`` (constants, warps) for."""
    unspecialized = set(kernel.kwargs.get("do_not_specialize") or ())
    arguments = tuple(_argument(value, name not in unspecialized) for name, value in zip(kernel.arg_names, args))
    assert len(args) == len([name for name in kernel.arg_names if name not in kwargs]), "every argument given"
    return f"{kernel.fn.__module__}.{kernel.fn.__name__}", arguments, tuple(sorted(kwargs.items()))


def warmed(warmups) -> set:
    """The specializations ``warmups`` (:class:`~artnvg_core.triton_runtime.Warmup`) compile."""
    return {specialization(w.kernel, w.args, w.kwargs) for w in warmups}


def record_launches(monkeypatch) -> set:
    """The specializations of every Triton launch made from now on (in the test), filled as they are made."""
    launched = set()
    run = InterpretedFunction.run

    def recording(self, *args, grid, warmup, **kwargs):
        launched.add(specialization(self, args, kwargs))
        return run(self, *args, grid=grid, warmup=warmup, **kwargs)

    monkeypatch.setattr(InterpretedFunction, "run", recording)
    return launched
