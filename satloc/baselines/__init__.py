"""Published baselines of Chu et al.'s comparisons, run from the same harness as the method.

* :mod:`satloc.baselines.fabmap`: FAB-MAP (Cummins and Newman, IJRR 2008): SIFT words, a Chow-Liu tree,
  the detector model, a sampled or mean-field new place and the Bayesian update over database places.
* :mod:`satloc.baselines.efm`: EFM, local features matched exhaustively against every database image and
  verified with a RANSAC homography.

* :mod:`satloc.baselines.localizers`: both as localizers of the common interface
  (:mod:`satloc.localizers.interface`), which is how the tables run them.

They may import satloc's data model and the localizers, never the evaluation nor :mod:`satloc_env` (the
import-linter contracts in ``pyproject.toml`` check it).
"""
from .efm import Efm, EfmConfig, estimate_homography
from .fabmap import ChowLiuTree, FabMap, FabMapConfig, chow_liu_tree
from .localizers import EfmLocalizer, FabMapLocalizer

__all__ = ["Efm", "EfmConfig", "estimate_homography", "ChowLiuTree", "FabMap", "FabMapConfig", "chow_liu_tree",
           "EfmLocalizer", "FabMapLocalizer"]
