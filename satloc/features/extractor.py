"""The feature-extractor interface, shared by :mod:`satloc.features` and the extractors built on it.

Every extractor has one interface: ``extractor(image, view) -> (H, W, dim) float32`` where ``image`` is an
RGB uint8 (H, W, 3) array and ``view`` is ``"ground"`` or ``"satellite"``. This module holds only that
interface (:class:`FeatureExtractor`, :data:`View`, :func:`check_image`) so that the extractors
(:mod:`satloc.features`, :mod:`satloc.features.fcn`) depend on it and :mod:`satloc.features`, which names the feature
sets, can depend on :mod:`satloc.features.fcn` without the two importing each other.
"""
from __future__ import annotations

from typing import Literal, Protocol, runtime_checkable

import numpy as np

from ..errors import ConfigError

__all__ = ["View", "FeatureExtractor", "check_image"]

View = Literal["ground", "satellite"]


@runtime_checkable
class FeatureExtractor(Protocol):
    name: str
    dim: int

    def __call__(self, image: np.ndarray, view: View) -> np.ndarray: ...


def check_image(image: np.ndarray, where: str = "image") -> None:
    """Raise :class:`satloc.ConfigError` (naming ``where``) unless ``image`` is an (H, W, 3) uint8 array."""
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ConfigError(f"{where}: expected an (H, W, 3) uint8 RGB image, got {got}")
