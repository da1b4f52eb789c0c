"""CropCraft's Nerfacto, registered with nerfstudio as ``cropcraft-nerfacto`` (imports nerfstudio).

The stock ``nerfacto`` method with one change: its LPIPS image metric is built on first use
instead of when the model is built. nerfstudio's ``NerfactoModel.populate_modules`` builds
torchmetrics' LPIPS, which fetches AlexNet's weights (233 MB) from download.pytorch.org, every time
a model is built: for training and again for every ``eval_setup`` that renders from it. A GPU
worker without internet access (the ones this project is checked on have none) then fails before
its first step, although CropCraft never asks for the metric (it renders depth; nerfstudio's own
evaluation images, the only callers, are switched off by ``train_command``).

``NerfactoSurfaces`` selects it for ``ns-train`` through nerfstudio's
``NERFSTUDIO_METHOD_CONFIGS`` environment variable (``nerfacto.METHOD_ENV``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields
from typing import Any

from nerfstudio.configs.method_configs import method_configs
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.plugins.types import MethodSpecification

from cropcraft_core.surfaces.nerfacto import METHOD


class LazyLPIPS:
    """torchmetrics' ``LearnedPerceptualImagePatchSimilarity``, built (and its weights fetched)
    at the first call, on the first call's device. Not a module: it adds nothing to the
    checkpoint, so training and loading agree whichever of them ever calls it."""

    def __init__(self, **kwargs: Any) -> None:
        self._kwargs = kwargs
        self._metric = None

    def __call__(self, a, b):
        if self._metric is None:
            from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

            self._metric = LearnedPerceptualImagePatchSimilarity(**self._kwargs)
        return self._metric.to(a.device)(a, b)


class CropNerfactoModel(NerfactoModel):
    """``NerfactoModel`` with :class:`LazyLPIPS` in place of the eager metric."""

    def populate_modules(self) -> None:
        import torchmetrics.image.lpip as lpip

        eager = lpip.LearnedPerceptualImagePatchSimilarity
        lpip.LearnedPerceptualImagePatchSimilarity = LazyLPIPS  # read inside populate_modules
        try:
            super().populate_modules()
        finally:
            lpip.LearnedPerceptualImagePatchSimilarity = eager


@dataclass
class CropNerfactoModelConfig(NerfactoModelConfig):
    _target: type = field(default_factory=lambda: CropNerfactoModel)


def _config():
    config = copy.deepcopy(method_configs["nerfacto"])
    config.method_name = METHOD
    stock = config.pipeline.model
    config.pipeline.model = CropNerfactoModelConfig(
        **{f.name: getattr(stock, f.name) for f in fields(stock) if f.init and f.name != "_target"}
    )
    return config


method = MethodSpecification(
    config=_config(),
    description="nerfacto whose LPIPS metric is built on first use (offline GPU workers)",
)
