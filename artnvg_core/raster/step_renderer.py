"""Renders for a loop that takes step after step on one scene (the finetune), none of which waits for the
device: the backend resolved and the inputs checked once, and on the Triton backend the tile lists given
room from earlier renders' counts, with the step redone where a render outgrew it."""

from __future__ import annotations

import torch

from ..cameras import CameraSet
from ..progress import StopFn
from ..scene import GaussianScene
from . import RenderOutput, check_render_inputs, choose_backend, render


class StepRenderer:
    """Renders views of ``cameras`` at each step of a loop that changes ``scene``'s values, neither its
    size, device nor SH degree, and keeps them finite (the finetune, whose optimiser writes finite values
    only).

    Made once before the steps: resolves ``backend`` (:attr:`backend`; see
    :func:`~artnvg_core.raster.render`) and checks the inputs (:func:`~artnvg_core.raster.check_render_inputs`,
    ValueError), which waits for the device; the steps' renders skip both. On the Triton backend the renders'
    tile lists get room from earlier counts (:class:`.triton_tiles.ListCapacity`) instead of waiting for
    their own; a render that outgrew that room is incomplete: :meth:`render` says so on the device, so that the
    step can be skipped there, and :meth:`redo`, asked once the step is queued, says on the host that the
    step must be taken again (with room grown). ``should_stop`` is asked within each render, its backward pass
    included, as :func:`~artnvg_core.raster.render` asks it."""

    def __init__(self, scene: GaussianScene, cameras: CameraSet, backend: str = "auto",
                 should_stop: StopFn | None = None):
        self.backend = choose_backend(backend, scene.device, scene.means.dtype)
        self.should_stop = should_stop
        check_render_inputs(scene, cameras)
        self.cameras = cameras.to(scene.device)
        self._capacity = self._list_capacity()

    def _list_capacity(self):
        """The Triton renders' shared room for tile lists; None for the other backends."""
        if self.backend != "triton":
            return None
        from .triton_tiles import ListCapacity  # imports Triton: only when the steps render with it

        return ListCapacity()

    def render(self, scene: GaussianScene, views: list[int],
               views_on_device: torch.Tensor | None = None) -> tuple[RenderOutput, torch.Tensor | None]:
        """``scene`` (with :meth:`__init__`'s scene's size, device and degree) from the cameras at ``views``
        (``views_on_device``: the same as a long tensor on the device, see :meth:`CameraSet.subset`).
        Returns the :class:`~artnvg_core.raster.RenderOutput` and whether it is incomplete (a device bool
        scalar; None where a render cannot be)."""
        out = render(scene, self.cameras.subset(views, views_on_device), backend=self.backend, checked=True,
                     list_capacity=self._capacity, should_stop=self.should_stop)
        return out, None if self._capacity is None else self._capacity.take_overflow()

    def redo(self) -> bool:
        """Whether a render since the last call was incomplete, so that its step must be taken again (the
        room has grown to fit it). Waits for those renders' intersection counts, not for the work queued
        after them."""
        return self._capacity is not None and self._capacity.overflowed()
