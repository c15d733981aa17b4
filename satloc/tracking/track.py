"""Tracking: a Bayes filter over the localizer's candidate poses, driven by odometry.

A single ground image cannot tell look-alike places apart: in a grid city two street corners with a park on
the left and offices on the right give co-occurrence posteriors with two equal peaks, and the top-3 average
then lands on the wrong one (or between them). A vehicle that moves knows how far it went since its last
image. :class:`Tracker` keeps a belief over the candidate poses of a :class:`satloc.localizers.database.Localizer`:

* **predict** (odometry ``(dx, dy, dyaw)``, the motion since the previous frame in the previous vehicle
  frame, as the environment's ``odometry`` observation): every candidate is moved by the odometry and its
  probability spread over the candidates near where it lands, with a Gaussian of standard deviation
  ``sqrt(sigma_m**2 + (sigma_frac * distance)**2)`` and only onto candidates whose heading is within
  ``heading_gate_deg`` of the moved heading. Each candidate's share is renormalised over the candidates it
  reaches; a candidate that lands more than 3 sigma from any (past the end of an open path) loses its
  probability, and if all of it is lost the belief becomes uniform. A fraction ``revive`` of the mass is spread uniformly, so that a belief that
  locked onto a wrong place (or a vehicle moved without odometry) recovers once images disagree with it;
* **fuse** (a frame's co-occurrence posterior P(L | I)): belief × (P(L | I) + ``floor`` / C), normalised.
  The floor keeps candidates the localizer did not score (vote pruning gives them 0) alive.
* **global search** (``lock_m``, ``lock_mass``): a single image's posterior is scored only near the path
  positions its ground neighbours vote for most (``LocalizerConfig.prune_regions``, a speed device), and a
  candidate left unscored gets only the floor, a factor of thousands below the scored ones. On an aliased
  route the truth is often outside those regions, so a new belief pruned that way starts from look-alikes
  and the truth can only come back through ``revive``. So while the tracker is not :meth:`Tracker.locked`
  (no belief yet, or less than ``lock_mass`` of it within ``lock_m`` of its mode) the localizer scores
  every candidate; once locked, the pruned regions plus the belief's support. Measured on Table II's 3 km
  loop ring (documentation: Results, Table II): with pruning, full + track followed the ring's point-symmetric twin (a
  rectangle looks the same to odometry after a half turn) for the first 43 frames (860 m) of the
  revisit; with the global search only the first frame, a single image, is off;
* **off the map** (``off_map``, the default): probability that the odometry moves more than 3 sigma from every
  candidate is not dropped but kept as *off-map hypotheses*: poses (at most ``off_map_hypotheses``, grouped
  within 5 m) dead-reckoned by the odometry, their spread growing with the distance driven since they left
  the map. Where such a pose comes back within 3 sigma of candidates (the vehicle rejoins the mapped path),
  its probability moves onto them. A frame's evidence for an off-map hypothesis is that of an average
  candidate, (1 + ``floor``) / C, the mean of the fused likelihood over the candidates, so images neither
  favour nor disfavour leaving the map; the odometry does. :attr:`Tracker.p_on`, the probability of being on
  the mapped path, is the tracked inlier score (a frame is declared inside when it reaches
  ``inlier_threshold``): queries on a road the database never drove are recognised by the motion that led
  there, which single images of look-alike streets cannot do.

The first frame's belief is its own posterior. The localizer's estimate (top-3 average) and the bird's-eye
refinement's peaks are then taken from the fused posterior: ``Localizer.localize(frame, tracker=...)`` and
``Localizer.localize_stream(frames, tracker=..., odometry=...)``.

Measured on the Table 1 queries (documentation: Results, Table 1 on synthetic revisit queries): tracking removes the gross failures of
single images.

The spread grows with the straight-line distance of the odometry, not with the distance driven: across a
long stretch between two localized frames (a detour outside the map, a turn with ``localize_every`` > 1)
it is too confident for real odometry, whose error grows with the distance driven.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import ConfigError
from ..geometry import Pose2, wrap_angle


@dataclass(frozen=True)
class TrackConfig:
    sigma_m: float = 0.5              # spread of a prediction, metres (at least the candidate spacing)
    sigma_frac: float = 0.05          # plus this fraction of the distance travelled (odometry error)
    heading_gate_deg: float = 30.0    # a candidate receives probability only from headings this close
    floor: float = 0.05               # fuse: P(L | I) + floor / C, per candidate
    revive: float = 1e-6              # mass spread uniformly at each prediction
    prune: float = 1e-7               # candidates below this fraction of the best one are not moved
    off_map: bool = True              # keep the belief that the odometry moves off the mapped path (see above)
    off_map_hypotheses: int = 8       # at most this many off-map poses, the least probable merged
    inlier_threshold: float = 0.5     # a tracked frame is declared inside the map when P(on the map) reaches this
    lock_m: float = 10.0              # a belief is locked when this radius around its mode holds ...
    lock_mass: float = 0.9            # ... this much of it (times P(on the map)); until then every candidate is
                                      # scored (Localizer: no vote pruning); 0: only a new belief's first frame.
                                      # `satloc experiment tune` on fcn_train/town_a: 0, 0.5, 0.9, 0.99 gave the
                                      # same errors (full+track+align, 57 queries), so 0.9 stays

    def __post_init__(self):
        if self.sigma_m <= 0 or self.sigma_frac < 0:
            raise ConfigError(f"track: sigma_m > 0 and sigma_frac >= 0 are required, got {self.sigma_m}, {self.sigma_frac}")
        if not 0 < self.heading_gate_deg <= 180:
            raise ConfigError(f"track.heading_gate_deg: expected in (0, 180], got {self.heading_gate_deg}")
        if self.floor < 0 or not 0 <= self.revive < 1 or not 0 <= self.prune < 1:
            raise ConfigError("track: floor >= 0, 0 <= revive < 1 and 0 <= prune < 1 are required")
        if self.off_map_hypotheses < 1:
            raise ConfigError(f"track.off_map_hypotheses: expected an integer >= 1, got {self.off_map_hypotheses}")
        if not 0 < self.inlier_threshold <= 1:
            raise ConfigError(f"track.inlier_threshold: expected a probability in (0, 1], got {self.inlier_threshold}")
        if not self.lock_m > 0 or not 0 <= self.lock_mass <= 1:
            raise ConfigError(f"track: lock_m > 0 and lock_mass in [0, 1] are required, got {self.lock_m}, "
                              f"{self.lock_mass}")


def relative_motion(a: Pose2, b: Pose2) -> np.ndarray:
    """The odometry (dx, dy, dyaw) from pose ``a`` to pose ``b``, in ``a``'s vehicle frame."""
    d = a.between(b)
    return np.array([d.x, d.y, d.yaw])


def compose_motion(first: np.ndarray, then: np.ndarray) -> np.ndarray:
    """Odometry ``first`` followed by ``then`` (each in the frame it starts from) as one motion."""
    p = Pose2(*np.asarray(first, np.float64)) @ Pose2(*np.asarray(then, np.float64))
    return np.array([p.x, p.y, p.yaw])


def compose_between(steps: np.ndarray, idx) -> np.ndarray:
    """(len(idx), 3) the motion from frame ``idx[i - 1]`` to ``idx[i]``: the per-frame ``steps`` (N, 3; row j the
    motion from frame j - 1 to j) between them composed. Row 0, and a row whose frame does not follow the one
    before, are NaN; a NaN in a step carries into its row (the motion is unknown)."""
    idx = np.asarray(idx, np.int64)
    out = np.full((len(idx), 3), np.nan)
    for i in range(1, len(idx)):
        m = np.zeros(3)
        for j in range(int(idx[i - 1]) + 1, int(idx[i]) + 1):
            m = compose_motion(m, steps[j])
        out[i] = m if idx[i] > idx[i - 1] else np.nan
    return out


def noisy_odometry(poses: np.ndarray, noise: tuple[float, float], seed: int = 0, *, scale_error: float = 0.0,
                   yaw_bias: float = 0.0) -> np.ndarray:
    """(N, 3) simulated odometry between consecutive ``poses`` (N, 3): the true relative motion plus Gaussian
    noise of std ``noise[0]`` times the distance (each axis) and ``noise[1]`` radians (heading), the
    environment's odometry model. Row 0 (no previous pose) and rows next to a pose with NaN are NaN.

    Wheel odometry also errs systematically, so its dead reckoning drifts rather than wanders:
    ``scale_error`` multiplies every translation by ``1 + scale_error`` (a wheel radius off by that fraction:
    0.02 reports 102 m for 100 m driven), and ``yaw_bias`` adds that many radians per metre driven to each
    heading change (unequal wheel radii: the path curls by ``yaw_bias`` rad a metre, e.g. 1e-3 rad/m is
    5.7 degrees per 100 m). Both are applied to the true motion before the noise (whose std still follows the
    true distance); at 0 the output is exactly that without them, draw for draw."""
    if len(noise) != 2 or min(noise) < 0:
        raise ConfigError(f"odometry noise: expected 2 non-negative numbers (fraction, radians), got {noise}")
    if not (math.isfinite(scale_error) and scale_error > -1 and math.isfinite(yaw_bias)):
        raise ConfigError(f"odometry bias: expected scale_error > -1 and a finite yaw_bias (rad/m), got "
                          f"{scale_error}, {yaw_bias}")
    poses = np.asarray(poses, np.float64)
    out = np.full((len(poses), 3), np.nan)
    rng = np.random.default_rng(seed)
    for i in range(1, len(poses)):
        z = rng.normal(0.0, 1.0, 3)
        if np.all(np.isfinite(poses[i - 1])) and np.all(np.isfinite(poses[i])):
            m = relative_motion(Pose2(*poses[i - 1]), Pose2(*poses[i]))
            dist = math.hypot(m[0], m[1])
            if scale_error or yaw_bias:
                m = m + np.array([scale_error * m[0], scale_error * m[1], yaw_bias * dist])
            out[i] = m + z * np.array([noise[0] * dist, noise[0] * dist, noise[1]])
    return out


class Tracker:
    """Belief over fixed candidate poses (C, 3), updated by :meth:`predict` (odometry) and :meth:`fuse`
    (a frame's posterior). See the module docstring."""

    def __init__(self, candidates: np.ndarray, config: TrackConfig = TrackConfig()):
        c = np.asarray(candidates, np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or len(c) == 0:
            raise ConfigError(f"tracker: candidates must be a non-empty (C, 3) array of poses, got {c.shape}")
        self.candidates, self.config = c, config
        self._tree = cKDTree(c[:, :2])
        self.belief: np.ndarray | None = None   # over the candidates, given that the vehicle is on the map
        self.p_on = 1.0                          # P(on the mapped path)
        self.off = np.zeros((0, 5))              # off-map hypotheses: x, y, yaw, probability, metres since leaving

    def reset(self) -> None:
        """Forget: the next fused posterior starts a new belief."""
        self.belief = None
        self.p_on = 1.0
        self.off = np.zeros((0, 5))

    def locked_mass(self) -> float:
        """The belief's probability within ``lock_m`` of its most probable candidate, times :attr:`p_on`
        (0 before the first frame)."""
        if self.belief is None:
            return 0.0
        mode = self.candidates[int(np.argmax(self.belief)), :2]
        near = self._tree.query_ball_point(mode, self.config.lock_m, return_sorted=False)
        return float(self.belief[near].sum()) * self.p_on

    def locked(self) -> bool:
        """Whether the belief is concentrated: at least ``lock_mass`` of it (times :attr:`p_on`) lies within
        ``lock_m`` of its most probable candidate (:meth:`locked_mass`). No belief yet (the first frame, or after
        :meth:`reset`): not locked. The localizer scores every candidate while the tracker is not locked (see the
        module docstring)."""
        if self.belief is None:
            return False
        return self.config.lock_mass <= 0 or self.locked_mass() >= self.config.lock_mass

    def _spread(self, moved: np.ndarray, myaw: np.ndarray, sigma: np.ndarray):
        """For poses ``moved`` (n, 2) with headings ``myaw`` (n,) and spreads ``sigma`` (n,): the (source, candidate,
        share) triples of their Gaussian spread over the candidates within 3 sigma and the heading gate (shares of
        a source sum to 1) and whether each source reached any candidate."""
        c, cfg = self.candidates, self.config
        near = self._tree.query_ball_point(moved, 3.0 * np.asarray(sigma, np.float64), return_sorted=False)
        counts = np.fromiter((len(n) for n in near), np.int64, len(near))
        src = np.repeat(np.arange(len(moved)), counts)
        dst = np.concatenate([np.asarray(n, np.int64) for n in near]) if len(near) else np.zeros(0, np.int64)
        d2 = ((c[dst, :2] - moved[src]) ** 2).sum(axis=1)
        sg = np.broadcast_to(np.asarray(sigma, np.float64), (len(moved),))[src]
        ok = np.cos(wrap_angle(c[dst, 2] - myaw[src])) >= math.cos(math.radians(cfg.heading_gate_deg))
        w = np.where(ok, np.exp(-0.5 * d2 / sg ** 2), 0.0)
        norm = np.bincount(src, weights=w, minlength=len(moved))
        share = np.divide(w, norm[src], out=np.zeros_like(w), where=norm[src] > 0)
        return src, dst, share, norm > 0

    def _group(self, hyp: np.ndarray) -> np.ndarray:
        """Off-map hypotheses (n, 5) grouped: the most probable first, those within 5 m and 45 degrees of it
        added to it; at most ``off_map_hypotheses``, the rest added to the nearest kept one."""
        if len(hyp) == 0:
            return hyp
        hyp = hyp[np.argsort(-hyp[:, 3], kind="stable")]
        left = np.ones(len(hyp), bool)
        kept: list[np.ndarray] = []
        while left.any() and len(kept) < self.config.off_map_hypotheses:
            i = int(np.flatnonzero(left)[0])
            close = left & (np.hypot(hyp[:, 0] - hyp[i, 0], hyp[:, 1] - hyp[i, 1]) <= 5.0) \
                & (np.cos(wrap_angle(hyp[:, 2] - hyp[i, 2])) >= math.cos(math.radians(45.0)))
            h = hyp[i].copy()
            h[3], h[4] = hyp[close, 3].sum(), hyp[close, 4].max()
            kept.append(h)
            left &= ~close
        out = np.array(kept)
        for i in np.flatnonzero(left):
            j = int(np.argmin(np.hypot(out[:, 0] - hyp[i, 0], out[:, 1] - hyp[i, 1])))
            out[j, 3] += hyp[i, 3]
        return out

    def predict(self, odometry: np.ndarray | None) -> None:
        """Move the belief by ``odometry`` (dx, dy, dyaw); nothing before the first frame. ``None`` or a
        non-finite odometry (unknown motion) is an error: reset the tracker instead."""
        if self.belief is None:
            return
        o = np.asarray(odometry if odometry is not None else (), np.float64).ravel()
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise ConfigError(f"tracker: odometry must be 3 finite numbers (dx, dy, dyaw), got {odometry!r}; "
                              "reset() the tracker where the motion is unknown")
        cfg, c, b = self.config, self.candidates, self.belief
        live = np.flatnonzero(b > cfg.prune * b.max())
        dist = math.hypot(o[0], o[1])
        sigma = math.hypot(cfg.sigma_m, cfg.sigma_frac * dist)
        cy, sy = np.cos(c[live, 2]), np.sin(c[live, 2])
        moved = np.stack([c[live, 0] + cy * o[0] - sy * o[1], c[live, 1] + sy * o[0] + cy * o[1]], 1)
        myaw = c[live, 2] + o[2]
        src, dst, share, landed = self._spread(moved, myaw, sigma)
        bl = b[live] / b[live].sum()
        on = np.bincount(dst, weights=share * bl[src], minlength=len(c)) * self.p_on
        if not cfg.off_map:
            total = on.sum()
            new = on / total if total > 0 else np.full(len(c), 1.0 / len(c))
            self.belief = (1.0 - cfg.revive) * new + cfg.revive / len(c)
            return
        # off-map hypotheses: the old ones dead-reckoned (and landed where they meet the map again) ...
        off = self.off.copy()
        if len(off):
            cy, sy = np.cos(off[:, 2]), np.sin(off[:, 2])
            off[:, 0], off[:, 1] = off[:, 0] + cy * o[0] - sy * o[1], off[:, 1] + sy * o[0] + cy * o[1]
            off[:, 2] = wrap_angle(off[:, 2] + o[2])
            off[:, 4] += dist
            s2, d2, sh2, back = self._spread(off[:, :2], off[:, 2], np.hypot(cfg.sigma_m, cfg.sigma_frac * off[:, 4]))
            on += np.bincount(d2, weights=sh2 * off[s2, 3], minlength=len(c))
            off = off[~back]
        # ... and the probability the odometry has just moved off the map
        gone = ~landed & (bl * self.p_on > 0)
        if gone.any():
            new_off = np.column_stack([moved[gone], wrap_angle(myaw[gone]), bl[gone] * self.p_on,
                                       np.full(int(gone.sum()), dist)])
            off = self._group(np.vstack([off, new_off]))
        total = on.sum() + off[:, 3].sum()
        if total <= 0:
            self.belief, self.p_on, self.off = np.full(len(c), 1.0 / len(c)), 1.0, np.zeros((0, 5))
            return
        on, off[:, 3] = on / total * (1.0 - cfg.revive) + cfg.revive / len(c), off[:, 3] / total * (1.0 - cfg.revive)
        self.p_on = float(on.sum())
        self.belief = on / self.p_on if self.p_on > 0 else np.full(len(c), 1.0 / len(c))   # (revive 0: all off)
        self.off = off

    def fuse(self, posterior: np.ndarray) -> np.ndarray:
        """The belief times ``posterior`` (one frame's P(L | I), plus the floor), normalised; it becomes the
        new belief and is returned. The first call just takes ``posterior``."""
        p = np.asarray(posterior, np.float64)
        if p.shape != (len(self.candidates),):
            raise ConfigError(f"tracker: posterior of shape {p.shape} does not match the {len(self.candidates)} "
                              "candidates (a tracker belongs to one localizer)")
        if not np.all(np.isfinite(p)) or np.any(p < 0):
            raise ConfigError("tracker: the posterior must be finite and non-negative")
        own = p / p.sum() if p.sum() > 0 else np.full(len(p), 1.0 / len(p))
        if self.belief is None:
            self.belief, self.p_on, self.off = own, 1.0, np.zeros((0, 5))
            return self.belief.copy()
        f = self.belief * self.p_on * (own + self.config.floor / len(p))
        f_off = self.off[:, 3] * (1.0 + self.config.floor) / len(p)   # an off-map place: an average candidate
        on, total = f.sum(), f.sum() + f_off.sum()
        if on <= 0:   # no overlap at all (floor 0): start from this frame
            self.belief, self.p_on, self.off = own, 1.0, np.zeros((0, 5))
            return self.belief.copy()
        self.belief, self.p_on = f / on, float(on / total)
        self.off = self.off.copy()
        self.off[:, 3] = f_off / total
        return self.belief.copy()
