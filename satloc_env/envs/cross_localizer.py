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

:class:`CrossEnvLocalizer` gives the interface the environments' localization loop
(:class:`satloc_env.envs.drive.LocalizationState`) uses: ``localize(frame, tracker=None, prior=...)``
returning a :class:`satloc.localizers.database.Localization` (candidates: the posterior's strongest positions and
headings; inlier score: the best correlation), ``tracker()``, ``camera``, ``satfeat``, ``extractor`` and
``config``.
"""
from __future__ import annotations

import hashlib
import json
import logging
import threading
from dataclasses import dataclass, field

import numpy as np

from satloc import __version__ as SATLOC_VERSION
from satloc.errors import ConfigError, FormatError
from satloc.features import make_extractor
from satloc.features.dictionary import SatelliteFeatures
from satloc.geometry import StereoCamera
from satloc.localizers.crossview import CrossViewConfig, CrossViewLocalizer, CrossViewTracker, Prior
from satloc.localizers.database import Localization

__all__ = ["CrossEnvConfig", "CrossEnvLocalizer", "cross_localizer", "map_features"]


@dataclass(frozen=True)
class CrossEnvConfig:
    posterior_k: int = 32                 # posterior entries in info (as LocalizerConfig.posterior_k)
    depth_source: str = "stereo"          # the query's depth: stereo matching of the pair
    mode: str = "cross"
    refine: bool = False
    track: bool = False
    crossview: CrossViewConfig = field(default_factory=CrossViewConfig)


class CrossEnvLocalizer:
    """A :class:`satloc.localizers.crossview.CrossViewLocalizer` in an environment's localization loop (see the module
    docstring)."""

    needs_prior = True

    def __init__(self, cross: CrossViewLocalizer, config: CrossEnvConfig = CrossEnvConfig()):
        self.cross, self.config = cross, config
        self.camera, self.satfeat, self.extractor = cross.camera, cross.satfeat, cross.extractor

    def prefetch(self, frames) -> None:
        """Nothing to batch: no network runs on the ground image (the grey level or the learned channels of
        the bilateral RGB)."""

    def tracker(self) -> CrossViewTracker:
        return CrossViewTracker(self.cross)

    def localize(self, frame, tracker: CrossViewTracker | None = None, prior: Prior | None = None) -> Localization:
        if prior is None:
            raise ConfigError("localizer 'cross': a localization needs a prior (position and heading within a radius)")
        r = tracker.localize(frame, prior) if tracker is not None else self.cross.localize(frame, prior)
        if r.pose is None:
            raise ConfigError(f"localizer 'cross': too little ground seen ({r.cells} bird's-eye cells) or no drivable "
                              "position within the prior")
        return Localization(r.pose, np.asarray(r.candidates, np.float64), np.asarray(r.posterior, np.float64),
                            float(r.correlation), True, int(r.cells))


_CACHE: dict = {}
_LOCK = threading.Lock()


log = logging.getLogger(__name__)


def map_features(satmap, progress: bool = False) -> SatelliteFeatures:
    """The default extractor's features of ``satmap``, from the disk cache when computed before (keyed by the
    map's pixels, resolution and origin, and the satloc version), else computed and stored there."""
    from .auto_localizer import cache_root

    ext = make_extractor("default")
    h = hashlib.sha256(np.ascontiguousarray(satmap.image).tobytes())
    h.update(json.dumps([float(satmap.meters_per_pixel), [float(v) for v in satmap.origin], ext.name,
                         SATLOC_VERSION]).encode())
    path = cache_root() / "cross" / f"satellite_features-{h.hexdigest()[:24]}.npz"
    if path.is_file():
        try:
            return SatelliteFeatures.load(path)
        except FormatError as e:   # damaged: computed again below
            log.warning("cross-view feature cache %s unreadable (%s): computing again", path, e)
    sf = SatelliteFeatures.compute(satmap, ext)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        sf.save(path)
    except OSError as e:   # a read-only cache: the features are still used
        log.warning("cross-view feature cache %s not written: %s", path, e)
    return sf


def cross_localizer(satmap, camera: StereoCamera, key: tuple, config: CrossEnvConfig = CrossEnvConfig()
                    ) -> CrossEnvLocalizer:
    """The cross-view localizer of ``satmap`` for ``camera`` (:func:`map_features`), made once per process for
    ``key`` (what identifies the map: scene, aliasing, satellite gap)."""
    k = (key, camera, config.crossview)
    with _LOCK:
        cv = _CACHE.get(k)
        if cv is None:
            cv = _CACHE[k] = CrossViewLocalizer(camera, map_features(satmap), make_extractor("default"),
                                                config.crossview, labels=satmap.labels)
    return CrossEnvLocalizer(cv, config)
