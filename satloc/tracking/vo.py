"""Stereo visual odometry: the vehicle's planar motion between consecutive stereo frames, from the images.

The localizer's tracking (:mod:`satloc.tracking.track`) needs odometry ``(dx, dy, dyaw)``: the motion from frame
``i - 1`` to frame ``i`` in frame ``i - 1``'s vehicle frame (:func:`satloc.tracking.track.relative_motion`). This module
measures it from the same stereo pairs the localizer sees, frame to frame:

1. **depth** of frame ``i - 1`` from its stereo pair (:class:`satloc.stereo.StereoDepth`, 3-way SGBM). The
   simulator's true depth is not a sensor; ``depth_source="frame"`` uses a frame's stored depth instead, for
   comparison only;
2. **features** of frame ``i - 1`` where that depth is valid and locally smooth (the disparity over the 3x3
   neighbourhood spans at most ``depth_edge_px``, so a corner on a depth edge is not given the background's
   depth; on SGBM depth 0.5 px also keeps the features whose depth the matcher resolved best, while the exact
   depth of flat ground spans 2 x baseline / mounting height, about 0.65 px), back-projected to 3-D points in
   its left camera. ``detector="gftt"``: Shi-Tomasi corners, tracked into frame ``i``'s left image by pyramidal
   Lucas-Kanade and kept when tracking back lands within ``lk_fb_px`` of the start; ``detector="orb"``: ORB
   keypoints of both frames matched by Hamming distance (mutual best, Lowe ratio ``orb_ratio``);
3. **pose** of frame ``i``'s left camera from those 3-D -> 2-D matches: ``cv2.solvePnPRansac`` (AP3P minimal
   sets, ``ransac_px`` reprojection threshold), SQPnP on its inliers, then Levenberg-Marquardt
   (``cv2.solvePnPRefineLM``) on them, the inliers taken again at the refined pose and refined once more;
4. the camera's 6-DoF motion is carried into the vehicle frame (:meth:`StereoCamera.vehicle_from_camera`) and
   reduced to the plane: ``dx``, ``dy`` of the vehicle origin and the heading change ``dyaw``.

A step fails, giving NaN (unknown motion, as :func:`satloc.tracking.track.noisy_odometry` marks it) and never an
exception, when fewer than ``min_inliers`` matches agree (a blank or untextured image, a frame with no valid
depth), when PnP finds no pose, or when the motion exceeds ``max_step_m`` / ``max_step_yaw_deg``. The first
frame has no predecessor: NaN. A failed step still computes the current frame's depth and features, so the
next step measures again from there.

Choices measured on five 200 m simulator drives (residential, city and loop, 0.8 m steps at 620x188; KITTI-style
100 m segments): Shi-Tomasi + LK drifted 0.16-0.40 % of the distance and 0.11-0.51 degrees per 100 m, while ORB
matching (OpenCV's default detector settings) failed 31-34 of city's 250 steps. LK's window matters: under
forward motion the image expands and a translation-only window tracks short, so with the simulator's true depth
a 21 px window measured the steps 1.4 % short on average, 15 px 1.0 %, 9 px 0.3 %. Those drives were on test
scenes with lane-exact passes; ``satloc experiment tune`` now chooses the detector and the window on the
calibration scene ``fcn_train/town_a`` (its query pass, 695 frames, 1072 m, drifting, with the revisit's
occluders and appearance change, stereo depth). At the default world (varied streets over hills, cambered roads,
the car pitching and rolling), KITTI's translation error over 50 m segments: 3.04 % (gftt, 15 px), 13.5 % (ORB),
then 2.75 % at 9 px, 3.04 % at 15 px and 3.76 % at 21 px: 9 px. (On the plain world of earlier releases 15 px
had been chosen: 4.59 % at 9 px, 2.98 % at 15, 4.02 % at 21.) With AP3P samples,
RANSAC's own final EPnP fit on nearly coplanar points (road markings) was at times far enough off for LM to
diverge from it; SQPnP on the inliers removed those failures.

:func:`visual_odometry` runs over a :class:`satloc.sequence.Sequence`; :class:`StereoVO` is the same one
stereo pair at a time (``StereoVO(camera).step(left, right)``), for an environment. :func:`integrate_odometry`
and :func:`odometry_drift` dead-reckon odometry and measure its drift against true poses (``satloc bench vo``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from ..errors import ConfigError
from ..geometry import Pose2, StereoCamera, arc_length, wrap_angle
from ..sequence import Sequence
from ..stereo import StereoConfig, StereoDepth


@dataclass(frozen=True)
class VOConfig:
    detector: Literal["gftt", "orb"] = "gftt"   # corners tracked by pyramidal LK, or ORB matched by descriptor
    max_features: int = 1000            # features detected per frame (where depth is valid)
    gftt_quality: float = 0.001         # Shi-Tomasi: corners at least this fraction of the strongest one
    min_distance_px: float = 7.0        # Shi-Tomasi: corners at least this far apart (pixels)
    lk_window_px: int = 9               # Lucas-Kanade window (pixels, odd): chosen on a calibration pass (above)
    lk_levels: int = 3                  # Lucas-Kanade pyramid levels above the image
    lk_fb_px: float = 1.0               # keep a track when tracking it back lands this close to its start
    orb_ratio: float = 0.8              # ORB: best match distance below this fraction of the second best
    depth_edge_px: float = 0.5          # a feature's 3x3 neighbourhood spans at most this disparity (pixels;
                                        # exact depth of flat ground spans 0.65: use 1 with depth_source frame)
    max_depth_m: float = 60.0           # features farther than this are not used
    ransac_px: float = 2.0              # PnP RANSAC reprojection threshold (pixels)
    ransac_iterations: int = 200
    ransac_confidence: float = 0.999
    min_inliers: int = 15               # fewer PnP inliers: the step fails (NaN)
    max_step_m: float = 10.0            # a larger motion between two frames is a failure (NaN)
    max_step_yaw_deg: float = 45.0      # likewise a larger heading change
    depth_source: Literal["stereo", "frame"] = "stereo"  # "frame": the frame's stored depth (comparison only)
    stereo: StereoConfig = field(default_factory=StereoConfig)

    def __post_init__(self):
        if self.detector not in ("gftt", "orb"):
            raise ConfigError(f"detector: expected 'gftt' or 'orb', got {self.detector!r}")
        if self.depth_source not in ("stereo", "frame"):
            raise ConfigError(f"depth_source: expected 'stereo' or 'frame', got {self.depth_source!r}")
        if self.max_features < 4 or self.min_inliers < 4 or self.ransac_iterations < 1 or self.lk_levels < 0:
            raise ConfigError("max_features >= 4, min_inliers >= 4, ransac_iterations >= 1 and lk_levels >= 0 are "
                              f"required, got {self.max_features}, {self.min_inliers}, {self.ransac_iterations}, "
                              f"{self.lk_levels}")
        if self.lk_window_px < 3 or self.lk_window_px % 2 == 0:
            raise ConfigError(f"lk_window_px: expected an odd number >= 3, got {self.lk_window_px}")
        if not 0 < self.gftt_quality < 1 or not 0 < self.orb_ratio <= 1 or not 0 < self.ransac_confidence < 1:
            raise ConfigError("gftt_quality, orb_ratio and ransac_confidence: expected fractions in (0, 1), got "
                              f"{self.gftt_quality}, {self.orb_ratio}, {self.ransac_confidence}")
        positive = {"min_distance_px": self.min_distance_px, "lk_fb_px": self.lk_fb_px,
                    "depth_edge_px": self.depth_edge_px, "max_depth_m": self.max_depth_m,
                    "ransac_px": self.ransac_px, "max_step_m": self.max_step_m,
                    "max_step_yaw_deg": self.max_step_yaw_deg}
        for name, v in positive.items():
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: expected a positive number, got {v}")


@dataclass
class _Keyframe:
    """What a step keeps of the previous frame: its grey image, features with 3-D points in its left camera."""

    gray: np.ndarray
    pts: np.ndarray                     # (n, 2) float32 pixels of the features with valid depth
    xyz: np.ndarray                     # (n, 3) float64 camera-frame points
    desc: np.ndarray | None = None      # ORB descriptors of ``pts``


class StereoVO:
    """Frame-to-frame stereo visual odometry for one camera (see the module docstring).

    ``step(left, right)`` takes the next stereo pair (RGB uint8, the camera's size) and returns the motion
    ``(dx, dy, dyaw)`` from the previous pair to it in the previous vehicle frame, NaN for the first pair and
    for a step that fails. :attr:`last` describes the last step (features, matches, inliers, why it failed)."""

    def __init__(self, camera: StereoCamera, config: VOConfig = VOConfig()):
        if not isinstance(config, VOConfig):
            raise ConfigError(f"visual odometry config: expected a VOConfig, got {type(config).__name__}")
        self.camera, self.config = camera, config
        self._stereo = StereoDepth(camera, config.stereo) if config.depth_source == "stereo" else None
        self._K = camera.K
        v = camera.vehicle_from_camera("left")
        self._v, self._v_inv = v, np.linalg.inv(v)
        if config.detector == "orb":
            self._orb = cv2.ORB_create(nfeatures=config.max_features)
            self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._prev: _Keyframe | None = None
        self.last: dict = {}

    def reset(self) -> None:
        """Forget the previous frame: the next step returns NaN."""
        self._prev = None
        self.last = {}

    def step(self, left: np.ndarray, right: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        """The motion (dx, dy, dyaw) from the previous stereo pair to this one (NaN: unknown). ``depth``: the
        left image's metric depth, used (and required) only with ``depth_source="frame"``."""
        cam = self.camera
        for name, img in (("left", left), ("right", right)):
            img = np.asarray(img)
            if img.shape[:2] != (cam.height, cam.width) or img.dtype != np.uint8:
                raise ConfigError(f"visual odometry: the {name} image is {img.dtype} {img.shape}, expected uint8 "
                                  f"{cam.width}x{cam.height} (the camera's size)")
        if self.config.depth_source == "frame":
            if depth is None:
                raise ConfigError("visual odometry: depth_source 'frame' but no depth was given")
            depth = np.asarray(depth, np.float32)
        else:
            depth = self._stereo(left, right)
        gray = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY) if left.ndim == 3 else left
        out = np.full(3, np.nan)
        self.last = {"features": 0, "matches": 0, "inliers": 0, "failure": "first frame"}
        if self._prev is not None:
            out = self._motion(self._prev, gray)
        self._prev = self._keyframe(gray, depth)
        return out

    # --- one frame's features ----------------------------------------------------------------------
    def _keyframe(self, gray: np.ndarray, depth: np.ndarray) -> _Keyframe:
        cfg = self.config
        d = np.where(np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_depth_m), depth, 0).astype(np.float32)
        kernel = np.ones((3, 3), np.uint8)
        lo, hi = cv2.erode(d, kernel), cv2.dilate(d, kernel)
        fb = self.camera.fx * self.camera.baseline
        with np.errstate(divide="ignore", invalid="ignore"):
            usable = (lo > 0) & (fb / lo - fb / hi <= cfg.depth_edge_px)
        mask = usable.astype(np.uint8) * 255
        desc = None
        if cfg.detector == "gftt":
            c = cv2.goodFeaturesToTrack(gray, cfg.max_features, cfg.gftt_quality, cfg.min_distance_px, mask=mask)
            pts = np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2).astype(np.float32)
        else:
            kps, desc = self._orb.detectAndCompute(gray, mask)
            pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
            desc = desc if desc is not None else np.zeros((0, 32), np.uint8)
        ij = np.clip(np.round(pts).astype(np.int64), 0, [gray.shape[1] - 1, gray.shape[0] - 1])
        keep = usable[ij[:, 1], ij[:, 0]]
        pts = pts[keep]
        xyz = self.camera.backproject(pts.astype(np.float64), d[ij[keep, 1], ij[keep, 0]])
        return _Keyframe(gray, pts, xyz, desc[keep] if desc is not None else None)

    def _matches(self, prev: _Keyframe, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(indices into ``prev``'s features, their pixels in ``gray``)."""
        cfg = self.config
        if cfg.detector == "gftt":
            lk = dict(winSize=(cfg.lk_window_px, cfg.lk_window_px), maxLevel=cfg.lk_levels,
                      criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
            p0 = prev.pts.reshape(-1, 1, 2)
            p1, st, _ = cv2.calcOpticalFlowPyrLK(prev.gray, gray, p0, None, **lk)
            back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray, prev.gray, p1, None, **lk)
            fb = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
            p1 = p1.reshape(-1, 2)
            h, w = gray.shape
            ok = (st.ravel() == 1) & (st_b.ravel() == 1) & (fb < cfg.lk_fb_px) \
                & (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
            idx = np.flatnonzero(ok)
            return idx, p1[idx]
        kps, desc = self._orb.detectAndCompute(gray, None)
        if desc is None or len(kps) < 2 or len(prev.desc) < 2:
            return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
        fwd = self._matcher.knnMatch(prev.desc, desc, k=2)
        back = {m[0].queryIdx: m[0].trainIdx for m in self._matcher.knnMatch(desc, prev.desc, k=1) if m}
        idx, cur = [], []
        for m in fwd:
            if len(m) == 2 and m[0].distance < cfg.orb_ratio * m[1].distance \
                    and back.get(m[0].trainIdx) == m[0].queryIdx:
                idx.append(m[0].queryIdx)
                cur.append(kps[m[0].trainIdx].pt)
        return np.asarray(idx, np.int64), np.asarray(cur, np.float32).reshape(-1, 2)

    # --- the motion --------------------------------------------------------------------------------
    def _fail(self, why: str) -> np.ndarray:
        self.last["failure"] = why
        return np.full(3, np.nan)

    def _motion(self, prev: _Keyframe, gray: np.ndarray) -> np.ndarray:
        cfg = self.config
        self.last.update(features=len(prev.pts), failure=None)
        if len(prev.pts) < cfg.min_inliers:
            return self._fail(f"{len(prev.pts)} features with depth in the previous frame")
        idx, cur = self._matches(prev, gray)
        self.last["matches"] = len(idx)
        if len(idx) < cfg.min_inliers:
            return self._fail(f"{len(idx)} features matched")
        obj, img = prev.xyz[idx], cur.astype(np.float64)
        try:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                obj, img, self._K, None, iterationsCount=cfg.ransac_iterations, reprojectionError=cfg.ransac_px,
                confidence=cfg.ransac_confidence, flags=cv2.SOLVEPNP_AP3P)
        except cv2.error as e:
            return self._fail(f"PnP: {str(e).strip().splitlines()[-1]}")
        if not ok or inl is None or len(inl) < cfg.min_inliers:
            return self._fail(f"PnP RANSAC: {0 if inl is None else len(inl)} inliers")
        inl = inl.ravel()
        # RANSAC's own final fit on its inliers (EPnP after AP3P samples) can be far off when the points are
        # nearly coplanar (road markings); SQPnP on the inliers is not, and LM refines it
        ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], self._K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return self._fail("SQPnP on the RANSAC inliers found no pose")
        for _ in range(2):   # refine on the inliers, then on the inliers of the refined pose
            rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], self._K, None, rvec, tvec)
            proj, _ = cv2.projectPoints(obj, rvec, tvec, self._K, None)
            err = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
            new = np.flatnonzero(err < cfg.ransac_px)
            if len(new) < cfg.min_inliers:
                return self._fail(f"{len(new)} inliers after refinement")
            if np.array_equal(new, inl):
                break
            inl = new
        self.last["inliers"] = len(inl)
        t = np.eye(4)                                   # previous camera -> current camera
        t[:3, :3] = cv2.Rodrigues(rvec)[0]
        t[:3, 3] = tvec.ravel()
        m = self._v @ np.linalg.inv(t) @ self._v_inv    # the current vehicle frame in the previous one
        motion = np.array([m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])])
        if not np.all(np.isfinite(motion)) or math.hypot(motion[0], motion[1]) > cfg.max_step_m \
                or abs(math.degrees(motion[2])) > cfg.max_step_yaw_deg:
            return self._fail(f"implausible motion {np.round(motion, 3).tolist()}")
        return motion


def visual_odometry(sequence: Sequence, config: VOConfig = VOConfig(), progress: bool = False) -> np.ndarray:
    """(N, 3) odometry of ``sequence`` from its stereo pairs: row ``i`` is the motion (dx, dy, dyaw) from frame
    ``i - 1`` to frame ``i`` in frame ``i - 1``'s vehicle frame (the convention of
    :func:`satloc.tracking.track.relative_motion`); row 0 and failed steps are NaN. Poses are not used."""
    from tqdm import tqdm

    vo = StereoVO(sequence.camera, config)
    out = np.full((len(sequence), 3), np.nan)
    for i in tqdm(range(len(sequence)), desc="visual odometry", unit="frame", disable=not progress, leave=False):
        f = sequence[i]
        out[i] = vo.step(f.left, f.right, f.depth)
    return out


# --- dead reckoning and drift ----------------------------------------------------------------------------

def integrate_odometry(odometry: np.ndarray, start=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(N, 3) poses dead-reckoned from ``start`` (pose 0) by ``odometry`` (N, 3; row ``i`` moves pose ``i - 1``
    to pose ``i``, row 0 is ignored). A non-finite row counts as no motion."""
    odo = np.asarray(odometry, np.float64)
    p = Pose2(*np.asarray(start, np.float64))
    out = np.empty((len(odo), 3))
    for i in range(len(odo)):
        if i and np.all(np.isfinite(odo[i])):
            p = p @ Pose2(*odo[i])
        out[i] = p.as_array()
    return out


def odometry_drift(odometry: np.ndarray, poses: np.ndarray, segments_m=(50.0, 100.0)) -> dict:
    """How far odometry (N, 3) drifts from the true ``poses`` (N, 3) it should follow.

    * ``end_*``: dead reckoning (:func:`integrate_odometry`, from the first true pose) at the last frame:
      position error in metres and as a percentage of the distance driven (``end_error_pct``), heading error
      in degrees and degrees per 100 m driven;
    * ``segments``: for each length L of ``segments_m`` that the drive covers, KITTI's odometry metric: from
      every frame, the relative motion to the first frame at least L metres further along, its position error
      as a percentage of the distance between them (``trans_pct``) and its heading error in degrees per 100 m
      (``rot_deg_per_100m``), averaged (``n``: how many segments);
    * ``step_*``: per-step errors (RMSE of the (dx, dy) difference, of dyaw in degrees), over the steps with
      finite odometry; ``failed_steps``: steps after the first with non-finite odometry (counted as no motion).
    """
    odo, poses = np.asarray(odometry, np.float64), np.asarray(poses, np.float64)
    if odo.shape != poses.shape or odo.ndim != 2 or odo.shape[1] != 3 or len(odo) < 2:
        raise ConfigError(f"odometry drift: expected odometry and poses of the same shape (N >= 2, 3), got "
                          f"{odo.shape} and {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ConfigError("odometry drift: every true pose must be finite")
    est = integrate_odometry(odo, poses[0])
    s = arc_length(poses)
    dist = float(s[-1])
    end_m = float(np.hypot(*(est[-1, :2] - poses[-1, :2])))
    end_deg = abs(math.degrees(wrap_angle(est[-1, 2] - poses[-1, 2])))
    truth = np.array([Pose2(*poses[i - 1]).between(Pose2(*poses[i])).as_array() for i in range(1, len(poses))])
    ok = np.all(np.isfinite(odo[1:]), axis=1)
    dt = np.linalg.norm(odo[1:][ok, :2] - truth[ok, :2], axis=1)
    dyaw = np.degrees(wrap_angle(odo[1:][ok, 2] - truth[ok, 2])) if ok.any() else np.zeros(0)
    out = {"frames": len(poses), "distance_m": round(dist, 2), "failed_steps": int((~ok).sum()),
           "end_error_m": round(end_m, 3), "end_error_pct": round(100 * end_m / dist, 3) if dist > 0 else None,
           "end_heading_deg": round(end_deg, 3),
           "end_heading_deg_per_100m": round(100 * end_deg / dist, 3) if dist > 0 else None,
           "step_trans_rmse_m": round(float(np.sqrt(np.mean(dt ** 2))), 4) if ok.any() else None,
           "step_yaw_rmse_deg": round(float(np.sqrt(np.mean(dyaw ** 2))), 4) if ok.any() else None,
           "segments": {}}
    for length in segments_m:
        t_err, r_err = [], []
        for i in range(len(poses)):
            j = int(np.searchsorted(s, s[i] + length))
            if j >= len(poses):
                break
            e = Pose2(*poses[i]).between(Pose2(*poses[j])).between(Pose2(*est[i]).between(Pose2(*est[j])))
            seg = s[j] - s[i]
            t_err.append(100 * math.hypot(e.x, e.y) / seg)
            r_err.append(100 * abs(math.degrees(e.yaw)) / seg)
        if t_err:
            out["segments"][f"{length:g}"] = {"n": len(t_err), "trans_pct": round(float(np.mean(t_err)), 3),
                                              "rot_deg_per_100m": round(float(np.mean(r_err)), 3)}
    return out
