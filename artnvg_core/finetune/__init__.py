"""The finetune stage: the original Gaussians' appearance finetuned toward stylized views and a style
image (:mod:`.loop`), with its settings (:mod:`.config`), one step's loss (:mod:`.step_loss`), an Adam
that writes finite values only (:mod:`.finite_steps`) and ARF's colour transfer (:mod:`.color_transfer`).
It renders through :class:`~artnvg_core.raster.step_renderer.StepRenderer` and knows no backend's internals."""

from .config import NNFM_MIN_SIDE, OPTIMIZE_CHOICES, FinetuneConfig
from .loop import camera_extent, check_stylized_views, compile_kernels, finetune

__all__ = ["OPTIMIZE_CHOICES", "FinetuneConfig", "camera_extent", "check_stylized_views", "compile_kernels", "finetune"]
