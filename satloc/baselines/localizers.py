"""The baselines as localizers of the common interface (:mod:`satloc.localizers.interface`).

Both need a database drive: :meth:`reset` indexes ``context.database`` (once per database: a later reset with
the same drive only forgets the sequential belief) and :class:`satloc.errors.ConfigError` says so where the
context has none (the places known only from above).

* :class:`EfmLocalizer`: EFM (:class:`satloc.baselines.efm.Efm`), each query's left image against every database
  image.
* :class:`FabMapLocalizer`: FAB-MAP (:class:`satloc.baselines.fabmap.FabMap`) from a trained model, the database's
  frames added as its places; with ``sequential`` the paper's motion model carries each posterior to the next
  query ("FAB-MAP + seq").
"""
from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError
from .efm import Efm, EfmConfig
from .fabmap import FabMap

__all__ = ["EfmLocalizer", "FabMapLocalizer"]


def _database(context, who: str):
    db = getattr(context, "database", None)
    if db is None:
        raise ConfigError(f"{who} localizes against a database drive, and this run has none (a place known only "
                          "from above)")
    return db


class EfmLocalizer:
    """EFM on ``context.database`` (see the module docstring)."""

    name = "EFM"

    def __init__(self, config: EfmConfig = EfmConfig(), progress: bool = False):
        self.config, self.progress = config, progress
        self.model: Efm | None = None
        self._db = None

    def reset(self, context) -> None:
        db = _database(context, self.name)
        if self.model is None or self._db is not db:
            self.model, self._db = Efm.build(db, self.config, self.progress), db

    def localize(self, query):
        return self.model.localize(query.frame)


class FabMapLocalizer:
    """FAB-MAP from the trained ``model`` (the path of its npz, read anew for each database; or a :class:`FabMap`
    without places, which gets the database's) on ``context.database``'s frames as places (see the module
    docstring); ``sequential`` with ``motion_window`` database places (None: the model's)."""

    def __init__(self, model: FabMap | str | Path, sequential: bool = False, motion_window: int | None = None,
                 progress: bool = False, name: str | None = None):
        self.trained = model
        self.sequential, self.motion_window, self.progress = bool(sequential), motion_window, progress
        self.name = name or ("FAB-MAP + seq" if self.sequential else "FAB-MAP")
        self.model: FabMap | None = None
        self._db = None

    def reset(self, context) -> None:
        db = _database(context, self.name)
        if self.model is None or self._db is not db:
            fm = self.trained if isinstance(self.trained, FabMap) else FabMap.load(self.trained)
            fm.add_places(db, self.progress)
            if self.sequential:
                changes = {"sequential": True}
                if self.motion_window is not None:
                    changes["motion_window"] = int(self.motion_window)
                fm = fm.with_config(**changes)
            self.model, self._db = fm, db
        self.model.reset()

    def localize(self, query):
        if self.sequential:
            return self.model.localize_next(query.frame, f"query frame {query.index}")
        return self.model.localize(query.frame)
