"""See what a localizer did: episodes and experiment folders as Rerun recordings (``.rrd``).

`Rerun <https://rerun.io>`_ (``pip install 'satloc[viewer]'``, the ``rerun-sdk`` package) records images, 2-D
geometry and scalars on a timeline and replays them in its viewer (``rerun episode.rrd``), scrubbing back and
forth. What is logged, on the timeline ``step`` (an environment's steps) or ``query`` (a folder's queries):

* ``camera/left``, ``camera/right``: the stereo pair the localizer saw (JPEG-compressed);
* ``map/image``: the satellite map, once, in its pixels (x right, y down), and over it ``map/truth`` and
  ``map/estimate`` (the true and the estimated trails so far, red and green), ``map/posterior`` (the posterior's
  strongest candidates, coloured and sized by probability), ``map/prior`` (the query's prior disc, where there is
  one) and ``map/car`` (the true pose);
* ``error_m``: the error against time (one series per method for a folder: ``error_m/<method>``).

:class:`RerunViewer` wraps an environment (SatLoc-v0, SatLocReplay-v0) and logs every reset and step from the
observation and ``info`` (``satloc view --scene SCENE``); ``satloc view FOLDER`` writes a recording of every method localized
in an experiment folder (``satloc demo``, a Table I scene folder, ``satloc evaluate``), one sub-tree per method
(``methods/<method>/...``), with the query frames' stereo pairs where the folder holds the recording
(:mod:`satloc_env.experiments.view`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from satloc.errors import ConfigError

__all__ = ["RerunViewer", "EpisodeRecording", "episode_to_rrd", "require_rerun", "METHOD_RGB", "TRUTH_RGB"]

#: colours of the trails (RGB)
TRUTH_RGB = (255, 60, 60)
ESTIMATE_RGB = (60, 230, 60)
PRIOR_RGB = (80, 170, 255)
#: method colours of a folder's recording, in turn
METHOD_RGB = [(60, 230, 60), (255, 200, 40), (80, 170, 255), (230, 90, 230), (40, 220, 220), (255, 130, 60),
              (180, 180, 180), (150, 110, 255), (255, 255, 120), (120, 255, 160)]


def require_rerun():
    """The ``rerun`` module; :class:`ConfigError` saying how to install it where it is missing."""
    try:
        import rerun
    except ImportError:
        raise ConfigError("the episode viewer needs rerun-sdk: pip install 'satloc[viewer]' (or pip install "
                          "rerun-sdk)") from None
    return rerun


class EpisodeRecording:
    """A Rerun recording stream over one satellite map: :meth:`log_map` once, then frames, trails, posteriors and
    errors at times the caller sets (:meth:`at`). ``path``: the ``.rrd`` file written (None: the recording is
    kept in memory, e.g. to :meth:`spawn` a viewer)."""

    def __init__(self, path: str | Path | None, application: str = "satloc"):
        rr = require_rerun()
        self.rr = rr
        self.rec = rr.RecordingStream(application)
        self.path = None if path is None else Path(path)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self.path))
        self.satmap = None

    # --- coordinates -------------------------------------------------------------------------------------
    def px(self, xy) -> np.ndarray:
        """Map metres (..., 2) as the map image's pixel coordinates (x right, y down; pixel centres at +0.5)."""
        return self.satmap.world_to_pixel(np.asarray(xy, np.float64)[..., :2]) + 0.5

    # --- logging -----------------------------------------------------------------------------------------
    def at(self, timeline: str, value: int) -> None:
        self.rec.set_time(timeline, sequence=int(value))

    def log_map(self, satmap, max_px: int = 4096) -> None:
        """The satellite map as a static image (JPEG), its pixels the 2-D view's coordinates."""
        import cv2

        self.satmap = satmap
        img = np.ascontiguousarray(satmap.image)
        h, w = img.shape[:2]
        if max(h, w) > max_px:   # the trails stay in the full map's pixels: the image is drawn scaled back
            s = max_px / max(h, w)
            img = cv2.resize(img, (int(round(w * s)), int(round(h * s))), interpolation=cv2.INTER_AREA)
        image = self.rr.Image(img).compress(jpeg_quality=85)
        self.rec.log("map/image", image, static=True)
        if img.shape[:2] != (h, w):
            self.rec.log("map/image", self.rr.Transform3D(scale=[w / img.shape[1], h / img.shape[0], 1.0]),
                         static=True)

    def log_views(self, left: np.ndarray, right: np.ndarray | None = None, prefix: str = "camera") -> None:
        self.rec.log(f"{prefix}/left", self.rr.Image(np.ascontiguousarray(left)).compress(jpeg_quality=85))
        if right is not None:
            self.rec.log(f"{prefix}/right", self.rr.Image(np.ascontiguousarray(right)).compress(jpeg_quality=85))

    def log_trail(self, path: str, xy: np.ndarray, rgb) -> None:
        """A trail (N, 2) map metres as line strips, broken where a point is not finite."""
        p = self.px(np.asarray(xy, np.float64).reshape(-1, 2))
        ok = np.all(np.isfinite(p), axis=1)
        strips, cur = [], []
        for q, good in zip(p, ok):
            if good:
                cur.append(q)
            elif cur:
                strips.append(np.array(cur))
                cur = []
        if cur:
            strips.append(np.array(cur))
        strips = [s for s in strips if len(s) > 1] or [np.zeros((0, 2))]
        self.rec.log(path, self.rr.LineStrips2D(strips, colors=[rgb], radii=[1.5]))

    def log_pose(self, path: str, pose, rgb, size_px: float = 12.0) -> None:
        """A pose (x, y, yaw) as an arrow on the map (nothing where it is not finite)."""
        p = np.asarray(pose, np.float64).reshape(-1)
        if p.shape[0] < 3 or not np.all(np.isfinite(p[:3])):
            self.rec.log(path, self.rr.Clear(recursive=False))
            return
        o = self.px(p[:2])
        d = np.array([math.cos(p[2]), -math.sin(p[2])]) * size_px
        self.rec.log(path, self.rr.Arrows2D(origins=[o], vectors=[d], colors=[rgb], radii=[2.0]))

    def log_posterior(self, path: str, poses: np.ndarray, probs: np.ndarray) -> None:
        """The posterior's entries (K, 3) and probabilities (K,) as points: brighter and larger where more
        probable (entries of probability 0 are left out)."""
        poses, probs = np.asarray(poses, np.float64).reshape(-1, 3), np.asarray(probs, np.float64).reshape(-1)
        keep = (probs > 0) & np.all(np.isfinite(poses[:, :2]), axis=1)
        if not keep.any():
            self.rec.log(path, self.rr.Clear(recursive=False))
            return
        rel = probs[keep] / probs[keep].max()
        c = np.stack([255 * np.ones_like(rel), 80 + 175 * rel, 40 * np.ones_like(rel)], 1).astype(np.uint8)
        self.rec.log(path, self.rr.Points2D(self.px(poses[keep, :2]), colors=c, radii=1.0 + 3.0 * rel))

    def log_prior(self, path: str, prior: np.ndarray | None) -> None:
        """A prior (x, y, yaw, radius_m, yaw_deg) as its disc's outline; nothing where there is none."""
        if prior is None or not np.all(np.isfinite(prior[:4])) or prior[3] <= 0:
            self.rec.log(path, self.rr.Clear(recursive=False))
            return
        a = np.linspace(0.0, 2.0 * math.pi, 65)
        ring = np.stack([prior[0] + prior[3] * np.cos(a), prior[1] + prior[3] * np.sin(a)], 1)
        self.rec.log(path, self.rr.LineStrips2D([self.px(ring)], colors=[PRIOR_RGB], radii=[1.0]))

    def log_scalar(self, path: str, value: float) -> None:
        if np.isfinite(value):
            self.rec.log(path, self.rr.Scalars(float(value)))

    def close(self) -> None:
        self.rec.flush()
        if self.path is not None:
            self.rec.disconnect()


class RerunViewer(gym.Wrapper):
    """Log an environment's episodes to a Rerun recording (see the module docstring): ``RerunViewer(env,
    "episode.rrd")``; every ``reset`` and ``step`` adds the stereo pair, the true and estimated trails on the
    satellite map, the posterior's strongest candidates, the prior and the error, on the timeline ``step``
    (an ``episode`` counter too). Open the file with ``rerun episode.rrd``. Works on SatLoc-v0 and
    SatLocReplay-v0 (the map: ``env.unwrapped.scene.satmap`` or ``env.unwrapped.map``)."""

    def __init__(self, env: gym.Env, path: str | Path = "episode.rrd"):
        super().__init__(env)
        self.recording = EpisodeRecording(path)
        self._episode = -1
        self._truth: list = []
        self._est: list = []
        self._map_id = None

    def _satmap(self):
        u = self.env.unwrapped
        scene = getattr(u, "_scene", None)
        return scene.satmap if scene is not None else getattr(u, "map", None)

    def _log(self, obs: dict, info: dict) -> None:
        r = self.recording
        sm = self._satmap()
        if sm is not None and id(sm) != self._map_id:
            r.log_map(sm)
            self._map_id = id(sm)
        r.at("step", int(info.get("step", 0)))
        r.at("episode", self._episode)
        if isinstance(obs, dict) and "left" in obs:
            r.log_views(obs["left"], obs.get("right"))
        if sm is None:
            return
        pose = np.asarray(info.get("pose", np.full(3, np.nan)), np.float64)
        self._truth.append(pose[:2])
        r.log_trail("map/truth", np.array(self._truth), TRUTH_RGB)
        r.log_pose("map/car", pose, TRUTH_RGB)
        if "estimate" in info:
            est = np.asarray(info["estimate"], np.float64)
            if int(info.get("localized_step", -1)) == int(info.get("step", -2)):
                self._est.append(est[:2])
            r.log_trail("map/estimate", np.array(self._est), ESTIMATE_RGB)
            r.log_pose("map/estimate_pose", est, ESTIMATE_RGB)
            r.log_posterior("map/posterior", info.get("posterior_poses", np.zeros((0, 3))),
                            info.get("posterior_probs", np.zeros(0)))
            prior = getattr(self.env.unwrapped, "last_prior", None)
            r.log_prior("map/prior", None if prior is None else prior.as_array())
            r.log_scalar("error_m", float(info.get("error_m", np.nan)))

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._episode += 1
        self._truth, self._est = [], []
        self._log(obs, info)
        return obs, info

    def step(self, action):
        out = self.env.step(action)
        self._log(out[0], out[4])
        return out

    def close(self):
        self.recording.close()
        return super().close()


def episode_to_rrd(env_id: str, out: str | Path, steps: int = 100, seed: int = 0, **kwargs: Any) -> dict:
    """Drive ``steps`` steps of ``env_id`` (made with ``kwargs``) with its autopilot, logged to ``out`` by
    :class:`RerunViewer`; returns the mean error over the steps localized."""
    env = RerunViewer(gym.make(env_id, **kwargs), out)
    errors = []
    try:
        _, info = env.reset(seed=seed)
        for _ in range(steps):
            u = env.unwrapped
            action = u.autopilot_action() if hasattr(u, "autopilot_action") else 1
            _, _, term, trunc, info = env.step(action)
            if "error_m" in info and int(info["localized_step"]) == int(info["step"]):
                errors.append(float(info["error_m"]))
            if term or trunc:
                break
    finally:
        env.close()
    return {"steps": len(errors), "mean_error_m": float(np.nanmean(errors)) if errors else None, "output": str(out)}
