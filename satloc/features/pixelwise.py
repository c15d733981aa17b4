"""Pixel-wise feature extractors for ground and satellite images.

Every extractor has one interface: ``extractor(image, view) -> (H, W, dim) float32`` where ``image`` is an
RGB uint8 (H, W, 3) array and ``view`` is ``"ground"`` or ``"satellite"`` (an extractor may treat the views
differently, e.g. with a network trained per view). ``FeatureStack`` concatenates extractors' channels.

The interface itself (:class:`FeatureExtractor`, :data:`View`, :func:`check_image`) lives in
:mod:`satloc.features.extractor` and is re-exported here. This module stands above :mod:`satloc.features.fcn`: the named
feature sets of :func:`make_extractor` use its network extractors (imported on demand, as they load torch),
and :mod:`satloc.features.fcn` does not import this module.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..device import check_device
from ..errors import ConfigError
from .extractor import FeatureExtractor, View, check_image

__all__ = ["View", "FeatureExtractor", "check_image", "BilateralRGB", "FeatureStack", "FEATURE_SETS",
           "make_extractor", "LazyExtractor"]


class BilateralRGB:
    """RGB after edge-preserving bilateral filtering, scaled to [0, 1]."""

    name = "rgb"
    dim = 3

    def __init__(self, diameter: int = 7, sigma_color: float = 40.0, sigma_space: float = 5.0):
        self.diameter, self.sigma_color, self.sigma_space = diameter, sigma_color, sigma_space

    def __call__(self, image: np.ndarray, view: View) -> np.ndarray:
        check_image(image, f"{self.name} features")
        f = cv2.bilateralFilter(image, self.diameter, self.sigma_color, self.sigma_space)
        return f.astype(np.float32) * (1.0 / 255.0)


class FeatureStack:
    """Channel-wise concatenation of several extractors, each optionally weighted."""

    def __init__(self, extractors: Sequence[FeatureExtractor], weights: Sequence[float] | None = None):
        if not extractors:
            raise ConfigError("FeatureStack: needs at least one extractor")
        self.extractors = list(extractors)
        self.weights = list(weights) if weights is not None else [1.0] * len(self.extractors)
        if len(self.weights) != len(self.extractors):
            raise ConfigError("FeatureStack: one weight per extractor")
        self.name = "+".join(e.name for e in self.extractors)
        self.dim = sum(e.dim for e in self.extractors)

    def prefetch(self, images: Sequence[np.ndarray], view: View) -> None:
        """Let each extractor that can batch its work over several images (the FCN's) do it now for
        ``images``; the calls that follow for these images then reuse the results."""
        for e in self.extractors:
            pre = getattr(e, "prefetch", None)
            if pre is not None:
                pre(images, view)

    def __call__(self, image: np.ndarray, view: View) -> np.ndarray:
        check_image(image, "features")
        parts = []
        for e, w in zip(self.extractors, self.weights):
            f = e(image, view)
            if f.shape != image.shape[:2] + (e.dim,):
                raise ConfigError(f"feature extractor {e.name!r}: returned shape {f.shape}, expected "
                                  f"{image.shape[:2] + (e.dim,)}")
            parts.append(f * np.float32(w) if w != 1.0 else f)
        return np.concatenate(parts, axis=2) if len(parts) > 1 else parts[0]


FEATURE_SETS = ("rgb", "semantic", "default")
#: the shipped FCN weights the sets with the FCN load (``satloc.features.fcn.DEFAULT_WEIGHTS``, named here without
#: importing torch)
DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "fcn.pt"
_IDENTITY: dict[tuple, str] = {}


def features_identity(name: str = "default") -> str:
    """What a named feature set computes, for cache keys and stage stamps: the name, and for the sets with the
    FCN (``semantic``, ``default``) the SHA-256 (first 16 hex digits) of the shipped weights file it loads, so
    that retrained weights never meet features (map features, dictionaries, localizations) cached with others.
    Reads the file once per process for each size and modification time; no torch."""
    if name not in FEATURE_SETS:
        raise ConfigError(f"features: expected one of {list(FEATURE_SETS)}, got {name!r}")
    if name == "rgb":
        return name
    import hashlib
    import os

    try:
        st = os.stat(DEFAULT_WEIGHTS)
    except OSError:
        return f"{name}:missing"   # the extractor itself says what is wrong when it loads
    key = (str(DEFAULT_WEIGHTS), st.st_size, st.st_mtime_ns)
    if key not in _IDENTITY:
        with open(DEFAULT_WEIGHTS, "rb") as f:
            _IDENTITY[key] = hashlib.sha256(f.read()).hexdigest()[:16]
    return f"{name}:fcn-{_IDENTITY[key]}"


class LazyExtractor:
    """A named feature set (:func:`make_extractor`) made on first use: its ``name`` is known at once, its network
    (and torch) loaded only when an image is first given or ``dim`` first asked. For callers that may never run
    it, such as the no-database localizer over cached map features with its learned channels."""

    def __init__(self, name: str = "default", device: str = "auto"):
        if name not in FEATURE_SETS:
            raise ConfigError(f"features: expected one of {list(FEATURE_SETS)}, got {name!r}")
        check_device(device)
        self.name, self.device = name, device
        self._made: FeatureExtractor | None = None

    @property
    def extractor(self) -> FeatureExtractor:
        if self._made is None:
            self._made = make_extractor(self.name, self.device)
        return self._made

    @property
    def dim(self) -> int:
        return self.extractor.dim

    def prefetch(self, images: Sequence[np.ndarray], view: View) -> None:
        pre = getattr(self.extractor, "prefetch", None)
        if pre is not None:
            pre(images, view)

    def __call__(self, image: np.ndarray, view: View) -> np.ndarray:
        return self.extractor(image, view)


def make_extractor(name: str = "default", device: str = "auto") -> FeatureExtractor:
    """A named feature set: ``rgb`` (bilateral RGB), ``semantic`` (the FCN's class probabilities and edge
    potentials) or ``default`` (all three stacked: RGB, edge potentials, semantic attributes). ``device``:
    where the FCN runs (:mod:`satloc.device`; checked for every set, used by those with the FCN)."""
    check_device(device)
    if name == "rgb":
        return BilateralRGB()
    if name in ("semantic", "default"):
        from .fcn import EdgeFeatures, SemanticFeatures

        parts: list[FeatureExtractor] = [EdgeFeatures(device=device), SemanticFeatures(device=device)]
        if name == "default":
            parts.insert(0, BilateralRGB())
        stack = FeatureStack(parts)
        stack.name = name
        return stack
    raise ConfigError(f"features: expected one of {list(FEATURE_SETS)}, got {name!r}")
