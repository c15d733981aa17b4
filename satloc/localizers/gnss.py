"""Priors as a GNSS receiver gives them: where a car believes it is before it looks.

A localizer that has no database searches around a prior (:class:`satloc.localizers.interface.Prior`: a position
within ``radius_m``, a heading within ``yaw_deg``). How the prior's centre strays from the truth is a model of
the receiver, :class:`GnssConfig`:

* ``model: uniform`` (the default): each fix's centre uniform within the prior's radius of the truth, its heading
  uniform within the prior's heading range, independently from fix to fix (:func:`draw_prior`). This is the
  protocol of the cross-view benchmarks on KITTI (a uniform +-20 m / +-10 degree prior); the truth is always
  inside the prior, and an error never persists from one fix to the next.
* ``model: receiver``: a single-frequency receiver in a street, its fixes ``rate_hz`` a second. The error of a fix
  is the sum of
  - a slowly varying bias, on each axis a first-order Gauss-Markov (Ornstein-Uhlenbeck) process of stationary
    standard deviation ``bias_sigma_m`` and correlation time ``bias_tau_s``: stationary single-frequency GPS
    positions are better modelled so than as white noise (Sensors 2020, 20(21), 6050), and the autocorrelation
    of a consumer receiver's horizontal error bends at about one minute (D. L. Wilson, "GPS horizontal position
    accuracy", www.erols.com/dlwilson);
  - white noise of ``noise_sigma_m`` on each axis;
  - multipath episodes (reflections off buildings): they begin ``multipath_per_min`` times a minute on average
    and last ``multipath_mean_s`` on average (exponential), each a jump of one direction and a heavy-tailed
    length (the absolute value of a Cauchy variable of scale ``multipath_scale_m``, at most
    ``multipath_max_m``) held for the episode. These put the truth outside a 20 m prior now and then;
  - outages (a tunnel, an underpass, a street canyon): they begin ``outage_per_min`` times a minute and last
    ``outage_mean_s`` on average; the receiver gives no fix meanwhile (``None``);
  - a heading (course) error, Gaussian of ``heading_sigma_deg``.
  The prior keeps its radius and heading range (the search's extent): the truth lies outside it where the error
  is larger. Each fix reports the receiver's accuracy (``Prior.sigma_m``: the bias and the noise together, as a
  receiver estimates it from its satellites; multipath is what it cannot see). The defaults give a median
  horizontal error of 5.3 m and a mean of 7.1 m, 4 % of fixes beyond 20 m and 3.4 % of the time without a fix
  (ten hours at 10 Hz, seed 1). For scale: an iPhone 6's horizontal error averaged 7-13 m in a city (Merry and
  Bettinger, "Smartphone GPS accuracy study in an urban environment", PLOS ONE 2019, 14(7): e0219890).

The error is a function of the time alone (a track of the receiver's outputs from ``start`` on, drawn in order
from one generator), so a fix does not depend on which other frames are asked for: :class:`GnssReceiver` answers
any time at or after its start, and :func:`gnss_priors` gives the priors of a pass's frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import ConfigError
from ..geometry import Pose2, wrap_angle
from .interface import Prior

__all__ = ["GnssConfig", "GnssReceiver", "draw_prior", "gnss_priors", "MODELS"]

MODELS = ("uniform", "receiver")
#: receiver outputs drawn at a time (a chunk of the track)
_CHUNK = 600


def draw_prior(pose, radius_m: float = 20.0, yaw_deg: float = 10.0, rng: np.random.Generator | None = None) -> Prior:
    """A prior as the ``uniform`` model gives it around the true ``pose`` (a Pose2 or x, y, yaw): centred uniformly
    within ``radius_m`` of it, its heading uniformly within ``yaw_deg`` degrees, with those widths."""
    x, y, yaw = (pose.x, pose.y, pose.yaw) if isinstance(pose, Pose2) else (float(v) for v in np.asarray(pose)[:3])
    rng = rng if rng is not None else np.random.default_rng()
    r, a = radius_m * math.sqrt(rng.uniform()), rng.uniform(0.0, 2.0 * math.pi)
    heading = float(wrap_angle(yaw + math.radians(rng.uniform(-yaw_deg, yaw_deg))))
    return Prior(x + r * math.cos(a), y + r * math.sin(a), heading, radius_m, yaw_deg)


@dataclass(frozen=True)
class GnssConfig:
    """How a prior's centre strays from the truth (see the module docstring)."""

    model: Literal["uniform", "receiver"] = "uniform"
    rate_hz: float = 10.0
    bias_sigma_m: float = 4.0
    bias_tau_s: float = 60.0
    noise_sigma_m: float = 1.0
    heading_sigma_deg: float = 3.0
    multipath_per_min: float = 1.0
    multipath_mean_s: float = 10.0
    multipath_scale_m: float = 8.0
    multipath_max_m: float = 60.0
    outage_per_min: float = 0.2
    outage_mean_s: float = 10.0
    reports_accuracy: bool = True   # receiver: each fix carries its accuracy (Prior.sigma_m); False: a bare position

    def __post_init__(self):
        if self.model not in MODELS:
            raise ConfigError(f"gnss.model: expected one of {list(MODELS)}, got {self.model!r}")
        for k in ("rate_hz", "bias_tau_s", "multipath_mean_s", "outage_mean_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"gnss.{k}: expected a number > 0, got {v!r}")
        for k in ("bias_sigma_m", "noise_sigma_m", "heading_sigma_deg", "multipath_per_min", "multipath_scale_m",
                  "multipath_max_m", "outage_per_min"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"gnss.{k}: expected a number >= 0, got {v!r}")


class GnssReceiver:
    """The fixes of one receiver over one drive: :meth:`fix` gives the prior at a time (``None`` in an outage).

    ``radius_m``, ``yaw_deg``: the priors' extent. ``rng``: the generator of the receiver's errors (the
    ``uniform`` model draws from it fix by fix, in the order asked, as :func:`draw_prior` does; the ``receiver``
    model draws its track from it in order of time, chunk by chunk). ``start``: the time of the first output
    (seconds); a fix is the last output at or before its time."""

    def __init__(self, config: GnssConfig | None = None, radius_m: float = 20.0, yaw_deg: float = 10.0,
                 rng: np.random.Generator | None = None, start: float = 0.0):
        self.config = config or GnssConfig()
        Prior(0.0, 0.0, 0.0, radius_m, yaw_deg)   # the extent's own checks
        self.radius_m, self.yaw_deg = float(radius_m), float(yaw_deg)
        self.rng = rng if rng is not None else np.random.default_rng()
        self.start = float(start)
        c = self.config
        self._dt = 1.0 / c.rate_hz
        self._err = np.zeros((0, 2))       # per output: the position error (x, y) in metres
        self._head = np.zeros(0)           # the heading error, radians
        self._up = np.zeros(0, bool)       # a fix was given
        self._bias: np.ndarray | None = None
        self._episodes: list[tuple[int, int, np.ndarray]] = []   # multipath episodes: (end, first output, jump)
        self._outage_end = -1                               # the first output after the running outage

    # -- the receiver model's track ----------------------------------------------------------------------------
    def _grow(self, upto: int) -> None:
        """Draw the track's outputs up to index ``upto`` (inclusive), a chunk at a time."""
        c, rng, dt = self.config, self.rng, self._dt
        while len(self._up) <= upto:
            k0, n = len(self._up), _CHUNK
            a = math.exp(-dt / c.bias_tau_s)
            q = c.bias_sigma_m * math.sqrt(1.0 - a * a)
            if self._bias is None:   # the bias starts in its stationary distribution
                self._bias = rng.normal(0.0, c.bias_sigma_m, 2)
            eps = rng.normal(0.0, 1.0, (n, 2))
            bias = np.empty((n, 2))
            b = self._bias
            for i in range(n):
                b = a * b + q * eps[i] if (k0 + i) > 0 else b
                bias[i] = b
            self._bias = b
            err = bias + rng.normal(0.0, c.noise_sigma_m, (n, 2))
            head = np.radians(rng.normal(0.0, c.heading_sigma_deg, n))
            up = np.ones(n, bool)
            # multipath: episodes begun before this chunk, then those begun in it
            starts = np.flatnonzero(rng.uniform(size=n) < c.multipath_per_min / 60.0 * dt)
            for i in starts:
                length = max(1, int(math.ceil(rng.exponential(c.multipath_mean_s) / dt)))
                size = min(abs(float(rng.standard_cauchy())) * c.multipath_scale_m, c.multipath_max_m)
                ang = rng.uniform(0.0, 2.0 * math.pi)
                jump = np.array([math.cos(ang), math.sin(ang)]) * size
                self._episodes.append((k0 + int(i) + length, k0 + int(i), jump))
            keep = []
            for end, begin, jump in self._episodes:
                lo, hi = max(begin, k0) - k0, min(end, k0 + n) - k0
                if hi > lo:
                    err[lo:hi] += jump
                if end > k0 + n:
                    keep.append((end, begin, jump))
            self._episodes = keep
            # outages
            begin = rng.uniform(size=n) < c.outage_per_min / 60.0 * dt
            for i in range(n):
                if k0 + i < self._outage_end:
                    up[i] = False
                elif begin[i]:
                    self._outage_end = k0 + i + max(1, int(math.ceil(rng.exponential(c.outage_mean_s) / dt)))
                    up[i] = False
            self._err = np.concatenate([self._err, err])
            self._head = np.concatenate([self._head, head])
            self._up = np.concatenate([self._up, up])

    def _index(self, t: float) -> int:
        if not math.isfinite(t) or t < self.start - 1e-9:
            raise ConfigError(f"gnss: a fix at {t!r} s, before the receiver's first output at {self.start} s")
        return int(math.floor((t - self.start) / self._dt + 1e-9))

    def error(self, t: float) -> tuple[np.ndarray, float] | None:
        """The ``receiver`` model's error at time ``t``: ((dx, dy) metres, heading radians), None in an outage."""
        if self.config.model != "receiver":
            raise ConfigError("gnss.error: only the 'receiver' model has a track of errors")
        k = self._index(float(t))
        self._grow(k)
        return (self._err[k].copy(), float(self._head[k])) if self._up[k] else None

    def fix(self, pose, t: float = 0.0) -> Prior | None:
        """The prior around the true ``pose`` (a Pose2 or x, y, yaw) at time ``t``; None where there is no fix."""
        if self.config.model == "uniform":
            return draw_prior(pose, self.radius_m, self.yaw_deg, self.rng)
        x, y, yaw = (pose.x, pose.y, pose.yaw) if isinstance(pose, Pose2) else (float(v) for v in np.asarray(pose)[:3])
        e = self.error(t)
        if e is None:
            return None
        (dx, dy), dh = e
        return Prior(x + float(dx), y + float(dy), float(wrap_angle(yaw + dh)), self.radius_m, self.yaw_deg,
                     self.reported_sigma_m)

    @property
    def reported_sigma_m(self) -> float | None:
        """The accuracy the receiver reports with each fix (``receiver``: its bias and noise together, one standard
        deviation per axis; it does not know when multipath misleads it); None for the ``uniform`` model."""
        c = self.config
        if c.model != "receiver" or not c.reports_accuracy:
            return None
        return math.hypot(c.bias_sigma_m, c.noise_sigma_m) or None


def gnss_priors(truth, times, config: GnssConfig | None = None, radius_m: float = 20.0, yaw_deg: float = 10.0,
                seed: int = 0, keys=None, start: float | None = None) -> list[Prior | None]:
    """The priors of frames with true poses ``truth`` (N, 3) at ``times`` (N,) seconds; a frame without a finite
    pose gets None. ``uniform``: each frame's prior from a generator seeded by (``seed``, its key: ``keys``, e.g.
    the frame's index in its pass; default its row), so a frame's prior does not depend on the others asked.
    ``receiver``: one receiver seeded by ``seed``, its track starting at ``start`` (default: the earliest of
    ``times``; give the pass's first timestamp so that a frame's fix does not depend on which frames are asked)."""
    cfg = config or GnssConfig()
    truth = np.asarray(truth, np.float64).reshape(-1, 3)
    n = len(truth)
    keys = np.arange(n) if keys is None else np.asarray(keys)
    if len(keys) != n:
        raise ConfigError(f"gnss_priors: {len(keys)} keys for {n} poses")
    ok = np.all(np.isfinite(truth), axis=1)
    if cfg.model == "uniform":
        return [draw_prior(t, radius_m, yaw_deg, np.random.default_rng([int(seed), int(k)])) if good else None
                for t, k, good in zip(truth, keys, ok)]
    if times is None:
        raise ConfigError("gnss_priors: the 'receiver' model needs the frames' times")
    times = np.asarray(times, np.float64).reshape(-1)
    if len(times) != n or not np.all(np.isfinite(times)):
        raise ConfigError(f"gnss_priors: expected {n} finite times, got {len(times)}")
    rx = GnssReceiver(cfg, radius_m, yaw_deg, np.random.default_rng(int(seed)),
                      float(times.min()) if start is None and n else float(start or 0.0))
    return [rx.fix(t, s) if good else None for t, s, good in zip(truth, times, ok)]
