"""A small synthetic KITTI raw drive in KITTI's exact on-disk layout, for tests (no KITTI data in it).

``write_kitti_drive(root, n_frames)`` writes ``root/<date>/<date>_drive_<nnnn>_sync`` (returned) with the
date folder's three calibration files, ``image_02/03`` (and with ``gray=True`` ``image_00/01``) PNGs and
``timestamps.txt``, and ``oxts/data/*.txt`` (30 numbers a line), ``oxts/timestamps.txt`` and
``oxts/dataformat.txt``. The rig (:class:`SynthRig`, our own numbers) and the vehicle poses (``poses`` in
``frame``, default :func:`default_poses` in :data:`DEFAULT_FRAME`) are chosen by the caller, so a reader must
give back exactly ``rig.camera()`` and ``poses``. Images default to a textured fronto-parallel wall at
``rig.wall_depth`` metres (a constant disparity) and can be anything through ``images(i, pose)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from satloc.geoframe import GeoFrame
from satloc.geometry import StereoCamera

DEFAULT_FRAME = GeoFrame(8.41, 49.01)
OXTS_NAMES = ("lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu "
              "pos_accuracy vel_accuracy navstat numsats posmode velmode orimode").split()
_CAM_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rigid(r, t):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


@dataclass(frozen=True)
class SynthRig:
    """Our own rectified rig and mounting, written as KITTI calibration files.

    The colour (left) camera sits ``mount_height`` above the ground, at ``camera_xy`` in the IMU frame,
    turned by ``yaw``, ``pitch`` (down) and ``roll`` from the IMU axes; the IMU is ``imu_height`` high.
    The grey left camera (rectified camera 0) is ``gray_offset`` from the colour one along the rectified
    camera axes (KITTI: about 6 cm to its right), with the same intrinsics and orientation."""

    width: int = 160
    height: int = 48
    fx: float = 140.0
    fy: float = 139.0
    cx: float = 79.25
    cy: float = 23.75
    baseline: float = 0.5
    mount_height: float = 1.62
    pitch: float = 0.03
    yaw: float = 0.02
    roll: float = 0.01
    camera_xy: tuple[float, float] = (1.1, -0.3)
    imu_height: float = 0.93
    gray_offset: tuple[float, float, float] = (0.06, 0.001, -0.003)
    wall_depth: float = 7.0  # the default images: a wall at this depth (disparity fx * baseline / depth)

    def camera(self, kind: str = "color") -> StereoCamera:
        h = self.mount_height if kind == "color" else self.mount_height + float(self._rotation()[2] @ self.gray_offset)
        return StereoCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.baseline, h,
                            self.pitch)

    def camera_in_imu(self, kind: str = "color") -> np.ndarray:
        c = np.array([self.camera_xy[0], self.camera_xy[1], self.mount_height - self.imu_height])
        return c if kind == "color" else c + self._rotation() @ np.asarray(self.gray_offset)

    def _rotation(self) -> np.ndarray:
        """Left camera axes in the IMU frame."""
        return _rz(self.yaw) @ _ry(self.pitch) @ _rx(self.roll) @ _CAM_AXES


def default_poses(n: int, spacing: float = 1.0, start=(3.0, -2.0), yaw0: float = 0.6,
                  turn: float = 0.01) -> np.ndarray:
    """(n, 3) vehicle poses on a gentle arc, ``spacing`` m apart, in :data:`DEFAULT_FRAME`."""
    out = np.zeros((n, 3))
    x, y, yaw = float(start[0]), float(start[1]), yaw0
    for i in range(n):
        out[i] = (x, y, yaw)
        x += spacing * math.cos(yaw + turn / 2)
        y += spacing * math.sin(yaw + turn / 2)
        yaw += turn
    out[:, 2] = np.mod(out[:, 2] + np.pi, 2 * np.pi) - np.pi
    return out


def wall_images(rig: SynthRig, seed: int = 0) -> Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Images of a random-textured wall at ``rig.wall_depth``: the right image is the left one shifted by
    the wall's disparity (rounded to whole pixels)."""
    d = int(round(rig.fx * rig.baseline / rig.wall_depth))

    def images(i: int, pose) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng(seed * 100003 + i)
        tex = rng.integers(0, 256, (rig.height, rig.width + d, 3)).astype(np.uint8)
        tex = cv2.GaussianBlur(tex, (3, 3), 0.7)
        return np.ascontiguousarray(tex[:, :rig.width]), np.ascontiguousarray(tex[:, d:d + rig.width])

    return images


def _fmt(vals) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(vals))


def write_calibration(date_dir: Path, rig: SynthRig) -> None:
    """The three calibration files of ``rig`` in KITTI's format (extra keys as in KITTI's files)."""
    date_dir.mkdir(parents=True, exist_ok=True)
    k = np.array([[rig.fx, 0.0, rig.cx], [0.0, rig.fy, rig.cy], [0.0, 0.0, 1.0]])
    # the colour camera's translation from rectified camera 0 (x_cam2 = x_rect0 + t2), and the right ones
    t2 = np.asarray(rig.gray_offset, dtype=np.float64)  # camera 0's centre in camera 2's frame
    t = {"00": np.zeros(3), "01": np.array([-rig.baseline, 0.0, 0.0]), "02": t2,
         "03": t2 + np.array([-rig.baseline, 0.0, 0.0])}
    r_rect = _rz(0.004) @ _rx(-0.003) @ _ry(0.002)
    imu_from_cam2 = _rigid(rig._rotation(), rig.camera_in_imu())
    velo_from_imu = _rigid(_rz(0.001) @ _rx(0.015), [-0.81, 0.32, -0.8])
    shift2 = _rigid(np.eye(3), t2)
    rect = _rigid(r_rect, np.zeros(3))
    # cam2_from_imu = shift2 @ rect @ cam0_from_velo @ velo_from_imu, solved for cam0_from_velo
    cam0_from_velo = (np.linalg.inv(rect) @ np.linalg.inv(shift2) @ np.linalg.inv(imu_from_cam2)
                      @ np.linalg.inv(velo_from_imu))
    lines = ["calib_time: 01-Jan-2020 12:00:00", "corner_dist: 9.950000e-02"]
    for cam in ("00", "01", "02", "03"):
        p = np.hstack([k, (k @ t[cam])[:, None]])
        lines += [f"S_{cam}: 1.392000e+03 5.120000e+02", f"K_{cam}: {_fmt(k)}", f"D_{cam}: 0.0 0.0 0.0 0.0 0.0",
                  f"R_{cam}: {_fmt(np.eye(3))}", f"T_{cam}: {_fmt(t[cam])}",
                  f"S_rect_{cam}: {rig.width:.6e} {rig.height:.6e}",
                  f"R_rect_{cam}: {_fmt(r_rect if cam == '00' else np.eye(3))}", f"P_rect_{cam}: {_fmt(p)}"]
    (date_dir / "calib_cam_to_cam.txt").write_text("\n".join(lines) + "\n")
    (date_dir / "calib_imu_to_velo.txt").write_text(
        f"calib_time: 01-Jan-2020 12:00:00\nR: {_fmt(velo_from_imu[:3, :3])}\nT: {_fmt(velo_from_imu[:3, 3])}\n")
    (date_dir / "calib_velo_to_cam.txt").write_text(
        f"calib_time: 01-Jan-2020 12:00:00\nR: {_fmt(cam0_from_velo[:3, :3])}\nT: {_fmt(cam0_from_velo[:3, 3])}\n"
        "delta_f: 0.000000e+00 0.000000e+00\ndelta_c: 0.000000e+00 0.000000e+00\n")


def _stamp(t: datetime, extra_ns: int) -> str:
    return t.strftime("%Y-%m-%d %H:%M:%S") + f".{t.microsecond * 1000 + extra_ns:09d}"


def write_kitti_drive(root: str | Path, n_frames: int, *, rig: SynthRig = SynthRig(), poses=None,
                      frame: GeoFrame = DEFAULT_FRAME, date: str = "2011_09_26", drive: int = 1,
                      color: bool = True, gray: bool = False, keep: Iterable[int] | None = None,
                      images: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                      dt: float = 0.1, seed: int = 0) -> Path:
    """Write a synthetic drive of ``n_frames`` (timestamps for all; data files for the indices in ``keep``,
    default all) and return its ``<date>_drive_<nnnn>_sync`` folder. ``poses`` (n_frames, 3): the vehicle
    poses (below the colour left camera) in ``frame``; the OXTS lat/lon/yaw written give them back through
    ``rig``. ``images(i, pose)`` -> (left, right) RGB uint8 at the rig's size (default :func:`wall_images`).
    """
    root = Path(root)
    poses = default_poses(n_frames) if poses is None else np.asarray(poses, np.float64)
    if poses.shape != (n_frames, 3):
        raise ValueError(f"poses: expected ({n_frames}, 3), got {poses.shape}")
    keep = set(range(n_frames)) if keep is None else set(keep)
    images = images or wall_images(rig, seed)
    date_dir = root / date
    write_calibration(date_dir, rig)
    drv = date_dir / f"{date}_drive_{drive:04d}_sync"
    rng = np.random.default_rng(seed)
    t0 = datetime.strptime(date, "%Y_%m_%d") + timedelta(hours=13, minutes=17, seconds=59, microseconds=287203)
    times = [t0 + timedelta(seconds=i * dt) for i in range(n_frames)]
    jitter = rng.integers(0, 1000, n_frames)
    streams = []
    if color:
        streams += [("image_02", 0), ("image_03", 1)]
    if gray:
        streams += [("image_00", 0), ("image_01", 1)]
    for name, _ in streams:
        (drv / name / "data").mkdir(parents=True, exist_ok=True)
        (drv / name / "timestamps.txt").write_text("".join(_stamp(t, int(j)) + "\n" for t, j in zip(times, jitter)))
    (drv / "oxts" / "data").mkdir(parents=True, exist_ok=True)
    (drv / "oxts" / "timestamps.txt").write_text(
        "".join(_stamp(t + timedelta(microseconds=6557), int(j)) + "\n" for t, j in zip(times, jitter)))
    (drv / "oxts" / "dataformat.txt").write_text("".join(f"{f}: OXTS field {i + 1}\n" for i, f in enumerate(OXTS_NAMES)))

    cam_xy = rig.camera_in_imu()[:2]
    speed = 1.0 / dt
    for i in sorted(keep):
        x, y, yaw = poses[i]
        imu_yaw = yaw - rig.yaw
        c, s = math.cos(imu_yaw), math.sin(imu_yaw)
        imu_xy = np.array([x - (c * cam_xy[0] - s * cam_xy[1]), y - (s * cam_xy[0] + c * cam_xy[1])])
        lon, lat = frame.to_lonlat(imu_xy)
        rec = np.zeros(30)
        rec[:11] = (lat, lon, 115.0 + 0.01 * i, 0.004, 0.007, imu_yaw, speed * s, speed * c, speed, 0.0, 0.0)
        rec[13] = rec[16] = 9.81
        rec[23:30] = (0.2, 0.03, 4, 8, 5, 5, 0)
        words = [repr(float(v)) for v in rec[:25]] + [str(int(v)) for v in rec[25:]]
        (drv / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(words) + "\n")
        left, right = images(i, poses[i])
        for name, side in streams:
            img = (left, right)[side]
            if name in ("image_00", "image_01"):
                out = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            else:
                out = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(drv / name / "data" / f"{i:010d}.png"), out):
                raise OSError(f"could not write {drv / name / 'data' / f'{i:010d}.png'}")
    return drv
