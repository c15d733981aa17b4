"""satloc: vehicle localization against georeferenced satellite imagery (Chu, Mei, Bansal, Walter).

The method package. It defines the shared data model (poses, camera, frames, sequences, satellite maps)
and never imports the simulator (:mod:`satloc_env`).
"""
from .errors import ConfigError, FormatError, SatlocError, SatlocWarning
from .geometry import Pose2, StereoCamera, wrap_angle
from .satmap import SatelliteMap
from .sequence import Frame, Sequence, SequenceWriter

__version__ = "0.1.0"

# modules that moved after 0.1.0: the old names still import, with a FutureWarning naming the new one
MOVED = {"satloc.georef": "satloc.geodata.georef", "satloc.radiometry": "satloc.geodata.radiometry",
         "satloc.vectors": "satloc.geodata.vectors"}
from ._moved import alias_modules as _alias_modules  # noqa: E402

__getattr__ = _alias_modules(__name__, MOVED)

__all__ = [
    "ConfigError", "FormatError", "SatlocError", "SatlocWarning", "Pose2", "StereoCamera", "wrap_angle", "SatelliteMap",
    "Frame", "Sequence", "SequenceWriter", "__version__",
]
