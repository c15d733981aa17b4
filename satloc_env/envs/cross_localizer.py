"""The environment's ``localizer="cross"``: localization with no database (:mod:`satloc.localizers.crossview`).

Nothing is built before the first step but the satellite map's features (the shipped extractor's: 2-4 s for
``city``'s 1800 x 1800 px on 2 cores, not the minutes of a database pass and a build), cached on disk under
``$SATLOC_CACHE/cross/`` (default ``~/.cache/satloc``) by the map's pixels and georeference, and in memory
once per process. Every localization starts from a
prior as a GPS fix would give it: the environment draws it around the true pose, within ``prior_radius_m``
metres and ``prior_yaw_deg`` degrees (:func:`satloc.localizers.crossview.draw_prior`, from a generator seeded by the
episode's seed). The drivable area is the map's label raster (the scene's roads, as a real place's road vectors
give them; :class:`satloc.localizers.crossview.CrossViewConfig` ``drivable: auto``). With ``localizer_track`` a :class:`satloc.localizers.crossview.CrossViewTracker` carries the answer from
one localization to the next with the odometry observations.

The environment uses it through the common interface, as every localizer
(:class:`satloc.localizers.crossview.NoDatabaseLocalizer`, :meth:`CrossViewLocalizer.as_localizer`).
"""
from __future__ import annotations

import hashlib
import json
import logging
import threading

import numpy as np

from satloc import __version__ as SATLOC_VERSION
from satloc.errors import FormatError
from satloc.features.dictionary import SatelliteFeatures
from satloc.features.pixelwise import LazyExtractor, features_identity
from satloc.geometry import StereoCamera
from satloc.localizers.crossview import CrossViewConfig, CrossViewLocalizer

__all__ = ["cross_localizer", "map_features"]


_CACHE: dict = {}
_LOCK = threading.Lock()


log = logging.getLogger(__name__)


def map_features(satmap, progress: bool = False) -> SatelliteFeatures:
    """The default extractor's features of ``satmap``, from the disk cache when computed before (keyed by the
    map's pixels, resolution and origin, the satloc version and the FCN weights' content), else computed and
    stored there."""
    from .auto_localizer import cache_root

    ext = LazyExtractor("default")   # its network (and torch) loaded only when the map's features are computed
    h = hashlib.sha256(np.ascontiguousarray(satmap.image).tobytes())
    h.update(json.dumps([float(satmap.meters_per_pixel), [float(v) for v in satmap.origin], ext.name,
                         SATLOC_VERSION, features_identity(ext.name)]).encode())
    path = cache_root() / "cross" / f"satellite_features-{h.hexdigest()[:24]}.npz"
    if path.is_file():
        try:
            return SatelliteFeatures.load(path)
        except FormatError as e:   # damaged: computed again below
            log.warning("cross-view feature cache %s unreadable (%s): computing again", path, e)
    sf = SatelliteFeatures.compute(satmap, ext)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # float16 features barely compress (city: 86 of 104 MB): stored as they are, read with no inflating
        sf.save(path, compress=False)
    except OSError as e:   # a read-only cache: the features are still used
        log.warning("cross-view feature cache %s not written: %s", path, e)
    return sf


def cross_localizer(satmap, camera: StereoCamera, key: tuple, config: CrossViewConfig = CrossViewConfig()
                    ) -> CrossViewLocalizer:
    """The cross-view localizer of ``satmap`` for ``camera`` (:func:`map_features`), made once per process for
    ``key`` (what identifies the map: scene, aliasing, satellite gap); each environment wraps it in a
    :class:`satloc.localizers.crossview.NoDatabaseLocalizer` of its own (its own track)."""
    k = (key, camera, config)
    with _LOCK:
        cv = _CACHE.get(k)
        if cv is None:
            cv = _CACHE[k] = CrossViewLocalizer(camera, map_features(satmap), LazyExtractor("default"), config,
                                                labels=satmap.labels, projections=_projections(config))
    return cv


def _projections(config: CrossViewConfig):
    """The learned channels ``config.projections`` names, from a plain copy in ``$SATLOC_CACHE/cross`` (keyed by
    the ``.pt`` file's content) when made before: no torch to import at an environment's first reset."""
    if config.projections is None:
        return None
    from pathlib import Path

    from satloc.features.crossview_channels import CrossViewProjections
    from satloc.localizers.crossview import SHIPPED_PROJECTIONS

    from .auto_localizer import cache_root

    src = Path(SHIPPED_PROJECTIONS if config.projections == "shipped" else config.projections)
    try:
        digest = hashlib.sha256(src.read_bytes()).hexdigest()[:24]
    except OSError:
        return None   # the localizer reads it and says what is wrong
    path = cache_root() / "cross" / f"projections-{digest}.npz"
    if path.is_file():
        try:
            return CrossViewProjections.load_npz(path)
        except FormatError as e:
            log.warning("cross-view projections cache %s unreadable (%s): read again", path, e)
    p = CrossViewProjections.load(src)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        p.save_npz(path)
    except OSError as e:
        log.warning("cross-view projections cache %s not written: %s", path, e)
    return p
