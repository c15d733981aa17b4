"""Readers of real datasets in their original layouts, each producing the shared data model
(:class:`satloc.sequence.Sequence` with its :class:`satloc.geometry.StereoCamera`), one module per dataset.

:func:`open_sequence` opens any of them, or a sequence in satloc's own layout, by looking at the folder.
:mod:`satloc.datasets.lidar_mosaic` makes a satellite stand-in from a KITTI drive's own images and LiDAR (for a
self-consistency check where no satellite image is at hand). They may import satloc's data model and
:mod:`satloc.geodata`, never :mod:`satloc_env` (an import-linter contract in ``pyproject.toml`` checks it)."""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import ConfigError
from ..geoframe import GeoFrame
from ..sequence import Sequence
from .kitti import load_kitti
from .malaga import load_malaga

__all__ = ["load_kitti", "load_malaga", "open_sequence", "sequence_kind"]


def sequence_kind(path: str | os.PathLike) -> str | None:
    """``"satloc"`` (a folder with ``sequence.json``), ``"kitti"`` (a raw drive: ``oxts/`` beside
    ``image_0x/``), ``"malaga"`` (an extract: a ``*_GPS.txt`` log) or None."""
    p = Path(path)
    if (p / "sequence.json").is_file():
        return "satloc"
    if (p / "oxts").is_dir() and any((p / f"image_0{i}").is_dir() for i in range(4)):
        return "kitti"
    if p.is_dir() and any(p.glob("*_GPS.txt")):
        return "malaga"
    return None


def open_sequence(path: str | os.PathLike, frame: GeoFrame | None = None, **options) -> Sequence:
    """A sequence from ``path``: satloc's layout (:meth:`Sequence.load`), a KITTI raw drive
    (:func:`load_kitti`) or a Malaga Urban extract (:func:`load_malaga`); ``frame`` and ``options`` go to the
    dataset reader (a satloc-layout sequence keeps the frame it was written in)."""
    kind = sequence_kind(path)
    if kind == "kitti":
        return load_kitti(path, frame, **options)
    if kind == "malaga":
        return load_malaga(path, frame, **options)
    if kind == "satloc" and not options:
        seq = Sequence.load(path)
        if frame is not None and seq.meta.get("geo_frame") != frame.to_dict():
            raise ConfigError(f"{path}: a satloc sequence stays in the frame it was written in "
                              f"({seq.meta.get('geo_frame')}), not {frame.to_dict()}")
        return seq
    if kind == "satloc":
        raise ConfigError(f"{path}: reader options {sorted(options)} do not apply to a satloc sequence")
    raise ConfigError(f"{path}: not a sequence: expected a satloc sequence folder (sequence.json), a KITTI raw "
                      "drive folder (<date>_drive_<nnnn>_sync with oxts/ and image_02/...) or a Malaga Urban "
                      "extract folder (with its *_GPS.txt log)")
