"""Published baselines of Chu et al.'s comparisons, run from the same harness as the method.

* :mod:`satloc.baselines.fabmap`: FAB-MAP (Cummins and Newman, IJRR 2008): SIFT words, a Chow-Liu tree,
  the detector model, a sampled or mean-field new place and the Bayesian update over database places.
"""
from .efm import Efm, EfmConfig, estimate_homography
from .fabmap import ChowLiuTree, FabMap, FabMapConfig, chow_liu_tree
