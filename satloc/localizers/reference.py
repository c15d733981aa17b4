"""Reference localizers: the floors every table runs beside the methods.

They look at no image. A method that does not beat them has learned nothing from the pictures:

* :class:`PriorAlone` answers each query with its prior's centre. With the uniform disc prior of radius r that
  the simulator and the tables draw (:func:`satloc.localizers.crossview.draw_prior`), its mean error is 2r/3
  (13.3 m for r = 20 m).
* :class:`DeadReckoning` starts at the first query's prior and then adds up the odometry: its error is the
  prior's at first and grows with the odometry's drift. Where the motion is unknown (visual odometry lost) it
  starts again at that query's prior.

Both implement the common interface (:mod:`satloc.localizers.interface`) as a user's localizer would; neither
subclasses anything. A query without a prior gets no answer from :class:`PriorAlone`, and none from
:class:`DeadReckoning` until one comes.
"""
from __future__ import annotations

from ..geometry import Pose2

__all__ = ["PriorAlone", "DeadReckoning", "REFERENCES", "reference_localizer"]


class PriorAlone:
    """Each query's answer is its prior's centre (see the module docstring)."""

    name = "Prior alone"

    def reset(self, context) -> None:
        pass

    def localize(self, query) -> Pose2 | None:
        return None if query.prior is None else query.prior.pose


class DeadReckoning:
    """The first query's prior, moved by the odometry ever after (see the module docstring)."""

    name = "Dead reckoning"

    def __init__(self) -> None:
        self.pose: Pose2 | None = None

    def reset(self, context) -> None:
        self.pose = None

    def localize(self, query) -> Pose2 | None:
        if self.pose is not None and query.odometry is not None:
            self.pose = self.pose @ query.odometry
        elif query.prior is not None:   # the first query, or the motion since the last one is unknown
            self.pose = query.prior.pose
        else:
            self.pose = None
        return self.pose


#: the reference localizers by the key configurations name them with (``references: [prior, dead-reckoning]``)
REFERENCES = {"prior": PriorAlone, "dead-reckoning": DeadReckoning}


def reference_localizer(key: str):
    """A new reference localizer by its key of :data:`REFERENCES`."""
    from ..errors import ConfigError

    if key not in REFERENCES:
        raise ConfigError(f"references: unknown {key!r}; expected some of {list(REFERENCES)}")
    return REFERENCES[key]()
