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
         "satloc.vectors": "satloc.geodata.vectors"}
from ._moved import alias_modules as _alias_modules  # noqa: E402

__getattr__ = _alias_modules(__name__, MOVED)

__all__ = [
    "ConfigError", "FormatError", "SatlocError", "SatlocWarning", "Pose2", "StereoCamera", "wrap_angle", "SatelliteMap",
    "Frame", "Sequence", "SequenceWriter", "__version__",
]
