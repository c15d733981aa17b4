"""Readers of real datasets in their original layouts, each producing the shared data model
(:class:`satloc.sequence.Sequence` with its :class:`satloc.geometry.StereoCamera`), one module per dataset."""

from .kitti import load_kitti
from .malaga import load_malaga

__all__ = ["load_kitti", "load_malaga"]
