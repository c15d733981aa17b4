"""The one interface every localizer implements, built-in or a user's.

A localizer is any object with two methods (duck-typed: nothing to subclass, no private attributes)::

    class MyLocalizer:
        name = "my localizer"                 # optional: names its rows and files (default: the class name)

        def reset(self, context):             # a new episode, drive or table: the place and the camera
            ...

        def localize(self, query):            # one stereo frame: where was it taken?
            return Pose2(x, y, yaw)           # or an Estimate, or None (no answer)

:meth:`LocalizerProtocol.reset` receives a :class:`Context`: the camera, the georeferenced satellite map
(:class:`satloc.satmap.SatelliteMap`, with its label raster where the place has one), the episode's seed, and
where the protocol has one the database drive (a :class:`satloc.sequence.Sequence`; ``None`` where the place
is known only from above). :meth:`LocalizerProtocol.localize` receives a :class:`Query`: the stereo
:class:`satloc.sequence.Frame` (no pose: that is the question), the odometry since the previous query (a
:class:`satloc.geometry.Pose2` increment in the previous vehicle frame; ``None`` at the first query and where
the motion is unknown, e.g. visual odometry lost), and the prior where there is one (a :class:`Prior`: a
position within a radius and a heading within a range, as a GPS fix gives it; ``None`` where there is none).

``localize`` returns ``None`` (no answer for this frame; so does raising :class:`satloc.errors.ConfigError`,
whose message is kept), a :class:`satloc.geometry.Pose2`, or an object with ``pose`` and optionally
``candidates`` ((K, 3) poses), ``posterior`` ((K,) probabilities), ``inlier_score`` and ``inlier`` (whether the
frame is believed to lie on the map), such as an :class:`Estimate`. Any other exception propagates: a bug in a
localizer stops the run that meets it.

Optional attributes a localizer may have: ``name`` (str), ``posterior_k`` (how many posterior entries the
environments and the results files keep, default 32), ``wants_depth`` (True: the simulator's frames carry the
true depth) and ``close()`` (called once when an environment that holds it closes).

Every consumer (the environments, the tables, the sweep, ``satloc evaluate``) goes through this interface and
grades every localizer with the same code (:func:`satloc.evaluation.run.run_localizer`). The built-in ones
implement it too: the paper's method (:class:`satloc.localizers.database.DatabaseLocalizer`), localizing with no
database (:class:`satloc.localizers.crossview.NoDatabaseLocalizer`) and the reference floors
(:mod:`satloc.localizers.reference`).

A localizer is named on the command line and in configurations as ``module:Name`` (an importable module) or
``path/to/file.py:Name``; ``Name`` is a class or a function that makes one with no arguments, or an instance
(:func:`resolve_localizer`).
"""
from __future__ import annotations

import importlib
import importlib.util
import inspect
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ..errors import ConfigError
from ..geometry import Pose2, StereoCamera
from ..satmap import SatelliteMap
from ..sequence import Frame, Sequence

__all__ = ["Prior", "Context", "Query", "Estimate", "LocalizerProtocol", "as_estimate", "check_localizer",
           "localizer_name", "resolve_localizer", "import_object", "DEFAULT_POSTERIOR_K"]

#: the widest prior (metres): the no-database localizer's search grows with the square of the radius
MAX_RADIUS_M = 100.0
#: posterior entries the environments report for a localizer without ``posterior_k``
DEFAULT_POSTERIOR_K = 32


@dataclass(frozen=True)
class Prior:
    """Where the vehicle is believed to be: within ``radius_m`` of (``x``, ``y``) (map metres), heading within
    ``yaw_deg`` degrees of ``yaw`` (radians, counter-clockwise from east). ``sigma_m``: the accuracy the receiver
    reports for its fix (one standard deviation per axis, metres), where it reports one: the position is then
    likelier near the centre; None: equally likely anywhere within the radius."""

    x: float
    y: float
    yaw: float
    radius_m: float = 20.0
    yaw_deg: float = 10.0
    sigma_m: float | None = None

    def __post_init__(self):
        for k in ("x", "y", "yaw", "radius_m", "yaw_deg"):
            v = getattr(self, k)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(float(v)):
                raise ConfigError(f"prior.{k}: expected a finite number, got {v!r}")
        s = self.sigma_m
        if s is not None and (not isinstance(s, (int, float, np.floating, np.integer)) or not 0 < float(s) < math.inf):
            raise ConfigError(f"prior.sigma_m: expected metres > 0 or None, got {s!r}")
        if not 0 < self.radius_m <= MAX_RADIUS_M:
            raise ConfigError(f"prior.radius_m: expected metres in (0, {MAX_RADIUS_M:g}], got {self.radius_m!r}")
        if not 0 <= self.yaw_deg <= 180:
            raise ConfigError(f"prior.yaw_deg: expected degrees in [0, 180], got {self.yaw_deg!r}")

    @property
    def pose(self) -> Pose2:
        """The prior's centre as a pose."""
        return Pose2(self.x, self.y, self.yaw)

    def as_array(self) -> np.ndarray:
        """(5,) x, y, yaw, radius_m, yaw_deg."""
        return np.array([self.x, self.y, self.yaw, self.radius_m, self.yaw_deg], np.float64)


@dataclass(frozen=True)
class Context:
    """What a localizer is told when a run begins (:meth:`LocalizerProtocol.reset`).

    ``camera``: the stereo rig of the frames to come. ``satmap``: the satellite map of the place (its
    ``labels``, an (H, W) class raster, where the place has them: the simulated scenes' roads, real road
    vectors rasterised). ``seed``: the episode's seed, for a localizer's own randomness (``None``: not seeded).
    ``database``: a drive through the place with posed frames, where the protocol has one (Table I's revisit,
    city and residential protocols; ``satloc evaluate``); ``None`` where the place is known only from above
    (the environments, the cross-area protocol). ``roads``: road centre lines in the map's frame,
    ``(lines, widths)`` (a list of (N_i, 2) arrays of map metres and each road's width in metres, what
    :func:`satloc.localizers.crossview.drivable_from_roads` takes), where the run has them; the environments
    and the tables give None: there the map's ``labels`` carry the roads. ``place``: a name for messages."""

    camera: StereoCamera
    satmap: SatelliteMap
    seed: int | None = None
    database: Sequence | None = None
    roads: Any = None
    place: str = ""


@dataclass(frozen=True)
class Query:
    """One frame to localize (:meth:`LocalizerProtocol.localize`).

    ``frame``: the stereo pair (``left``, ``right``; ``depth`` where the source gives it), without its pose.
    ``odometry``: the motion since the previous query (a :class:`Pose2` increment in the previous vehicle frame:
    x forward, y left), ``None`` at the first query of a run and where the motion is not known. ``prior``: a
    :class:`Prior`, or ``None`` where there is none. ``index``: the query's number in the run (0 first);
    ``timestamp``: the frame's time in seconds."""

    frame: Frame
    odometry: Pose2 | None = None
    prior: Prior | None = None
    index: int = 0
    timestamp: float = 0.0


@dataclass
class Estimate:
    """A localizer's answer for one query: ``pose``, and optionally the posterior over candidate poses
    (``candidates`` (K, 3) x, y, yaw; ``posterior`` (K,), summing to at most 1), an ``inlier_score`` (higher: more
    confident; NaN: none) and ``inlier`` (False: the frame is believed to lie off the map)."""

    pose: Pose2
    candidates: np.ndarray | None = None
    posterior: np.ndarray | None = None
    inlier_score: float = float("nan")
    inlier: bool = True

    def top(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` most probable candidates (k, 3) and their probabilities (k,), zero-padded; without a
        posterior, the pose with probability 1."""
        poses, probs = np.zeros((k, 3)), np.zeros(k)
        if self.candidates is None or self.posterior is None or len(self.posterior) == 0:
            if k:
                poses[0], probs[0] = self.pose.as_array(), 1.0
            return poses, probs
        d = np.diff(self.posterior)
        # already sorted, most probable first (the no-database localizer's): as given; else numpy's default sort
        # (the paper's method's own order of tied entries)
        order = np.arange(min(k, len(self.posterior))) if np.all(d <= 0) else np.argsort(-self.posterior)[:k]
        poses[: len(order)] = self.candidates[order]
        probs[: len(order)] = self.posterior[order]
        return poses, probs


@runtime_checkable
class LocalizerProtocol(Protocol):
    """The interface (see the module docstring). ``isinstance(obj, LocalizerProtocol)`` checks only that both
    methods exist."""

    def reset(self, context: Context) -> None:
        """A new run begins at the place of ``context``: forget any state of an earlier run."""

    def localize(self, query: Query) -> Pose2 | Estimate | None:
        """The pose ``query.frame`` was taken from (None: no answer)."""


def localizer_name(obj: Any) -> str:
    """The name a localizer's rows and files carry: its ``name`` attribute when a non-empty string, else its
    class name."""
    name = getattr(obj, "name", None)
    return name if isinstance(name, str) and name.strip() else type(obj).__name__


def check_localizer(obj: Any, where: str = "localizer") -> Any:
    """``obj`` if it has callable ``reset`` and ``localize``; :class:`ConfigError` naming what is missing."""
    missing = [m for m in ("reset", "localize") if not callable(getattr(obj, m, None))]
    if missing:
        raise ConfigError(f"{where}: {type(obj).__name__} {_short(obj)} is not a localizer: it has no "
                          f"{' and no '.join(missing)} method (a localizer has reset(context) and localize(query); "
                          "see satloc.localizers.interface)")
    return obj


def _short(obj: Any) -> str:
    r = repr(obj)
    return r if len(r) <= 80 else r[:77] + "..."


def _pose(value: Any, where: str) -> Pose2:
    if isinstance(value, Pose2):
        p = value
    else:
        try:
            a = np.asarray(value, np.float64).reshape(-1)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape != (3,):
            raise ConfigError(f"{where}: expected a satloc.Pose2 (or x, y, yaw), got {type(value).__name__} "
                              f"{_short(value)}")
        p = Pose2(*a)
    if not (math.isfinite(p.x) and math.isfinite(p.y) and math.isfinite(p.yaw)):
        raise ConfigError(f"{where}: the pose is not finite: {p}; return None for no answer")
    return p


def as_estimate(answer: Any, where: str = "localizer") -> Estimate | None:
    """A localizer's answer as an :class:`Estimate` (None stays None): a :class:`Pose2` (or 3 numbers x, y, yaw),
    or an object with ``pose`` (or, for the paper's method's :class:`satloc.localizers.database.Localization`,
    ``estimate``) and optionally ``candidates``, ``posterior``, ``inlier_score`` and ``inlier``.
    :class:`ConfigError` naming ``where`` for anything else: a non-finite pose, a posterior whose shape does not
    match its candidates or with negative or non-finite entries."""
    if answer is None:
        return None
    if isinstance(answer, Estimate):
        pose, cand, post = answer.pose, answer.candidates, answer.posterior
        score, inl = answer.inlier_score, answer.inlier
    elif hasattr(answer, "pose") or hasattr(answer, "estimate"):
        pose = getattr(answer, "pose", None)
        if pose is None:
            pose = getattr(answer, "estimate", None)
        if pose is None:
            return None
        cand, post = getattr(answer, "candidates", None), getattr(answer, "posterior", None)
        score, inl = getattr(answer, "inlier_score", float("nan")), getattr(answer, "inlier", True)
    else:
        return Estimate(_pose(answer, f"{where}: localize() returned"))
    pose = _pose(pose, f"{where}: localize() returned an answer whose pose")
    if (cand is None) != (post is None):
        raise ConfigError(f"{where}: localize() returned candidates without a posterior or a posterior without "
                          "candidates; give both or neither")
    if cand is not None:
        cand = np.asarray(cand, np.float64)
        post = np.asarray(post, np.float64).reshape(-1)
        if cand.ndim != 2 or cand.shape[1] != 3 or cand.shape[0] != post.shape[0]:
            raise ConfigError(f"{where}: localize() returned candidates of shape {cand.shape} and a posterior of "
                              f"shape {post.shape}; expected (K, 3) and (K,)")
        if not (np.all(np.isfinite(post)) and np.all(post >= 0)):
            raise ConfigError(f"{where}: localize() returned a posterior with negative or non-finite entries")
    try:
        score = float(score) if score is not None else float("nan")
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: localize() returned an inlier_score that is not a number: {score!r}") from None
    return Estimate(pose, cand, post, score, bool(True if inl is None else inl))


# --- naming a localizer: module:Name ---------------------------------------------------------------------------

def import_object(spec: str, where: str = "localizer") -> Any:
    """The object ``spec`` names: ``package.module:Name`` (imported) or ``path/to/file.py:Name`` (the file
    loaded as a module of its own); ``Name`` may be dotted (``module:Outer.Name``). :class:`ConfigError` naming
    the spec for anything that cannot be found."""
    if not isinstance(spec, str) or spec.count(":") < 1:
        raise ConfigError(f"{where}: expected 'module:Name' or 'path/to/file.py:Name', got {spec!r}")
    mod_name, _, attr = spec.rpartition(":")
    if not mod_name or not attr:
        raise ConfigError(f"{where}: expected 'module:Name' or 'path/to/file.py:Name', got {spec!r}")
    if mod_name.endswith(".py") or "/" in mod_name or "\\" in mod_name:
        path = Path(mod_name).expanduser().resolve()
        if not path.is_file():
            raise ConfigError(f"{where}: {spec!r}: no file {path}")
        key = "satloc_user_" + "".join(c if c.isalnum() else "_" for c in str(path))
        module = sys.modules.get(key)
        if module is None or getattr(module, "__file__", None) != str(path):
            s = importlib.util.spec_from_file_location(key, path)
            module = importlib.util.module_from_spec(s)
            sys.modules[key] = module
            try:
                s.loader.exec_module(module)
            except BaseException:
                sys.modules.pop(key, None)
                raise
    else:
        try:
            module = importlib.import_module(mod_name)
        except ModuleNotFoundError as e:
            if e.name and mod_name.startswith(e.name):
                raise ConfigError(f"{where}: {spec!r}: no module named {e.name!r} (is it on the Python path? a "
                                  "file is given as path/to/file.py:Name)") from None
            raise
    obj: Any = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ConfigError(f"{where}: {spec!r}: {getattr(module, '__name__', mod_name)} has no attribute "
                              f"{attr!r}")
        obj = getattr(obj, part)
    return obj


def resolve_localizer(value: Any, where: str = "localizer") -> Any:
    """A localizer instance from ``value``: a ``module:Name`` string (:func:`import_object`), a class or a function
    that makes one with no arguments (called), or an instance (returned). :class:`ConfigError` naming ``where``
    when the result has no ``reset`` and ``localize``."""
    obj = import_object(value, where) if isinstance(value, str) else value
    if inspect.isclass(obj) or (callable(obj) and not callable(getattr(obj, "localize", None))):
        try:
            inspect.signature(obj).bind()
        except TypeError as e:
            raise ConfigError(f"{where}: {getattr(obj, '__name__', obj)!r} cannot be made with no arguments "
                              f"({e}); name a class or function that needs none, or pass an instance") from None
        except ValueError:   # no signature to read (a builtin): try it
            pass
        obj = obj()
    return check_localizer(obj, where)

