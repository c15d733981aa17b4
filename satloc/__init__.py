"""satloc: vehicle localization against georeferenced satellite imagery (Chu, Mei, Bansal, Walter).

The method package. It defines the shared data model (poses, camera, frames, sequences, satellite maps)
and never imports the simulator (:mod:`satloc_env`).
"""
from .errors import ConfigError, FormatError, SatlocError, SatlocWarning
from .geometry import Pose2, StereoCamera, wrap_angle
from .satmap import SatelliteMap
from .sequence import Frame, Sequence, SequenceWriter


def _version() -> str:
    """The installed distribution's version (``pip show satloc``); run from a checkout that is not installed,
    the ``version`` of the ``pyproject.toml`` beside the package, else ``"unknown"``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("satloc")
    except PackageNotFoundError:
        import re
        from pathlib import Path

        p = Path(__file__).resolve().parent.parent / "pyproject.toml"
        m = re.search(r'^version\s*=\s*"([^"]+)"', p.read_text(), re.M) if p.is_file() else None
        return m.group(1) if m else "unknown"


__version__ = _version()

# modules that moved after 0.1.0: the old names still import, with a FutureWarning naming the new one
MOVED = {"satloc.georef": "satloc.geodata.georef", "satloc.radiometry": "satloc.geodata.radiometry",
         "satloc.vectors": "satloc.geodata.vectors",
         # 0.2.0: the method arranged by trade (localizers, tracking, features, evaluation)
         "satloc.localizer": "satloc.localizers.database", "satloc.crossview": "satloc.localizers.crossview",
         "satloc.track": "satloc.tracking.track", "satloc.vo": "satloc.tracking.vo",
         "satloc.align": "satloc.tracking.align", "satloc.extractor": "satloc.features.extractor",
         "satloc.fcn": "satloc.features.fcn", "satloc.context": "satloc.features.context",
         "satloc.dictionary": "satloc.features.dictionary", "satloc.projection": "satloc.features.projection",
         "satloc.crossview_learn": "satloc.features.crossview_learn", "satloc.nn": "satloc.features.nn",
         "satloc.metrics": "satloc.evaluation.metrics", "satloc.plots": "satloc.evaluation.plots"}
from ._moved import alias_modules as _alias_modules  # noqa: E402

__getattr__ = _alias_modules(__name__, MOVED)

__all__ = [
    "ConfigError", "FormatError", "SatlocError", "SatlocWarning", "Pose2", "StereoCamera", "wrap_angle", "SatelliteMap",
    "Frame", "Sequence", "SequenceWriter", "__version__",
]
