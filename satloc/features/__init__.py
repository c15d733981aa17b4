"""Features and learning: what the method computes of images before it localizes anything.

* :mod:`satloc.features.extractor`: the extractor interface (``extractor(image, view) -> (H, W, D)``);
* :mod:`satloc.features.pixelwise`: the pixel-wise extractors (bilateral-filtered RGB, edge potentials) and the
  named feature sets (:func:`make_extractor`);
* :mod:`satloc.features.fcn`: the fully convolutional network of the semantic channels;
* :mod:`satloc.features.context`, :mod:`satloc.features.dictionary`: ground samples, their satellite pairs and
  the ground-satellite dictionary;
* :mod:`satloc.features.nn`: nearest-neighbour indexes;
* :mod:`satloc.features.projection`: the learned location-discriminative projections W_g, W_s;
* :mod:`satloc.features.crossview_learn`: the learned channels of the no-database localizer.

It may import the data model and :mod:`satloc.tracking` (the bird's-eye warp), never the localizers.
``satloc.features`` was a module before it was this package: its names (``make_extractor``, ``BilateralRGB``,
...) still import from here.
"""
from .extractor import FeatureExtractor, View, check_image
from .pixelwise import FEATURE_SETS, BilateralRGB, FeatureStack, make_extractor

__all__ = ["View", "FeatureExtractor", "check_image", "BilateralRGB", "FeatureStack", "FEATURE_SETS",
           "make_extractor"]
