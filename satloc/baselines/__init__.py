"""Published baselines of Chu et al.'s comparisons, run from the same harness as the method.

* :mod:`satloc.baselines.fabmap`: FAB-MAP (Cummins and Newman, IJRR 2008): SIFT words, a Chow-Liu tree,
  the detector model, a sampled or mean-field new place and the Bayesian update over database places.
* :mod:`satloc.baselines.efm`: EFM, local features matched exhaustively against every database image and
  verified with a RANSAC homography.

They may import satloc's data model and the localizer's configuration and persistence, never
:mod:`satloc_env` (an import-linter contract in ``pyproject.toml`` checks it).
"""
from .efm import Efm, EfmConfig, estimate_homography
from .fabmap import ChowLiuTree, FabMap, FabMapConfig, chow_liu_tree

__all__ = ["Efm", "EfmConfig", "estimate_homography", "ChowLiuTree", "FabMap", "FabMapConfig", "chow_liu_tree"]
