"""Poses and the stereo camera model shared by the simulator, the dataset readers and the method.

Frames (right-handed):

* **map**: x east, y north, z up, metres. A :class:`SatelliteMap` georeferences this plane.
* **vehicle**: origin on the ground below the left camera, x forward, y left, z up. A :class:`Pose2`
  (x, y, yaw) places it on the map; yaw is counter-clockwise from east, radians in (-pi, pi].
* **camera** (OpenCV): x right, y down, z forward. The left camera sits ``mount_height`` metres above the
  vehicle origin, pitched down by ``pitch`` radians; the right camera is ``baseline`` metres to its right
  along the camera x axis (a rectified pair: same K, same orientation).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError


def wrap_angle(a):
    """Wrap angle(s) to (-pi, pi]."""
    w = np.mod(np.asarray(a, dtype=np.float64) + np.pi, 2 * np.pi) - np.pi
    w = np.where(w == -np.pi, np.pi, w)
    return float(w) if np.ndim(w) == 0 else w


def arc_length(points: np.ndarray) -> np.ndarray:
    """Distance along the polyline ``points`` (N, >=2; the first two columns) to each of its points, from 0."""
    p = np.asarray(points, dtype=np.float64)[:, :2]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


@dataclass(frozen=True)
class Pose2:
    """SE(2) pose on the map plane: position (x, y) in metres, heading ``yaw`` in radians."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "x", float(self.x))
        object.__setattr__(self, "y", float(self.y))
        object.__setattr__(self, "yaw", wrap_angle(self.yaw))

    # --- group operations -------------------------------------------------------------------------
    def __matmul__(self, other: "Pose2") -> "Pose2":
        """Composition ``self ∘ other``: ``other`` is expressed in the frame of ``self``."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2(self.x + c * other.x - s * other.y, self.y + s * other.x + c * other.y, self.yaw + other.yaw)

    def inverse(self) -> "Pose2":
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2(-c * self.x - s * self.y, s * self.x - c * self.y, -self.yaw)

    def between(self, other: "Pose2") -> "Pose2":
        """Relative pose ``self⁻¹ ∘ other`` (``other`` seen from ``self``), e.g. odometry."""
        return self.inverse() @ other

    # --- conversions ------------------------------------------------------------------------------
    def matrix(self) -> np.ndarray:
        """3x3 homogeneous matrix mapping vehicle-frame (x, y, 1) to map-frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, self.x], [s, c, self.y], [0.0, 0.0, 1.0]])

    @staticmethod
    def from_matrix(m: np.ndarray) -> "Pose2":
        m = np.asarray(m, dtype=np.float64)
        return Pose2(m[0, 2], m[1, 2], math.atan2(m[1, 0], m[0, 0]))

    def matrix3d(self) -> np.ndarray:
        """4x4 map-from-vehicle transform (vehicle origin on the ground, z = 0)."""
        t = np.eye(4)
        t[:2, :2] = self.matrix()[:2, :2]
        t[:2, 3] = (self.x, self.y)
        return t

    def transform(self, pts: np.ndarray) -> np.ndarray:
        """Map-frame coordinates of vehicle-frame points ``pts`` (..., 2)."""
        pts = np.asarray(pts, dtype=np.float64)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        x, y = pts[..., 0], pts[..., 1]
        return np.stack([self.x + c * x - s * y, self.y + s * x + c * y], axis=-1)

    def transform_inv(self, pts: np.ndarray) -> np.ndarray:
        """Vehicle-frame coordinates of map-frame points ``pts`` (..., 2)."""
        pts = np.asarray(pts, dtype=np.float64)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = pts[..., 0] - self.x, pts[..., 1] - self.y
        return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw])

    @staticmethod
    def from_array(a) -> "Pose2":
        a = np.asarray(a, dtype=np.float64).reshape(-1)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"a pose needs 3 finite values (x, y, yaw), got {a!r}")
        return Pose2(a[0], a[1], a[2])

    def distance(self, other: "Pose2") -> float:
        return math.hypot(self.x - other.x, self.y - other.y)


@dataclass(frozen=True)
class StereoCamera:
    """Rectified pinhole stereo rig on a vehicle (see the module docstring for frames).

    Pixel convention is OpenCV's: pixel (u, v) has its centre at integer coordinates.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    mount_height: float = 1.65
    pitch: float = 0.0

    def __post_init__(self):
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"camera: image size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ConfigError(f"camera: focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.baseline <= 0:
            raise ConfigError(f"camera: baseline must be positive, got {self.baseline}")

    # --- presets ----------------------------------------------------------------------------------
    @staticmethod
    def kitti() -> "StereoCamera":
        """KITTI raw colour pair (P_rect_02, 2011_09_26) at 1242x375, 0.54 m baseline, 1.65 m high."""
        return StereoCamera(1242, 375, 721.5377, 721.5377, 609.5593, 172.854, 0.54, 1.65, 0.0)

    @staticmethod
    def kitti_half() -> "StereoCamera":
        """The KITTI rig at half resolution (620x188)."""
        return StereoCamera.kitti().resized(620, 188, scale=0.5)

    @staticmethod
    def preset(name: str) -> "StereoCamera":
        presets = {"full": StereoCamera.kitti, "half": StereoCamera.kitti_half}
        if name not in presets:
            raise ConfigError(f"camera preset: expected one of {sorted(presets)}, got {name!r}")
        return presets[name]()

    def resized(self, width: int, height: int, scale: float | None = None) -> "StereoCamera":
        """Same rig with images of ``width`` x ``height``, intrinsics scaled by ``scale`` (default: the size
        ratio per axis), keeping OpenCV's pixel-centre convention."""
        sx, sy = (scale, scale) if scale else (width / self.width, height / self.height)
        return dataclasses.replace(
            self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
        )

    def rig_differences(self, other: "StereoCamera", baseline_rel: float = 0.03, height_m: float = 0.1,
                        pitch_rad: float = 0.02) -> list[str]:
        """How ``other``'s rig (baseline, mounting height, pitch) differs from this one beyond the given
        tolerances; empty when images of one can be resampled into the other's intrinsics and used as its."""
        bad = []
        if abs(other.baseline - self.baseline) > baseline_rel * self.baseline:
            bad.append(f"baseline {other.baseline:.4f} m against {self.baseline:.4f} m")
        if abs(other.mount_height - self.mount_height) > height_m:
            bad.append(f"mount_height {other.mount_height:.3f} m against {self.mount_height:.3f} m")
        if abs(other.pitch - self.pitch) > pitch_rad:
            bad.append(f"pitch {other.pitch:.4f} rad against {self.pitch:.4f} rad")
        return bad

    # --- matrices ---------------------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def vehicle_from_camera(self, side: str = "left") -> np.ndarray:
        """4x4 transform taking camera-frame points to the vehicle frame."""
        c, s = math.cos(self.pitch), math.sin(self.pitch)
        r = np.array([[0.0, -s, c], [-1.0, 0.0, 0.0], [0.0, -c, -s]])  # columns: camera x, y, z axes
        t = np.eye(4)
        t[:3, :3] = r
        t[:3, 3] = (0.0, 0.0, self.mount_height)
        if side == "right":
            t[:3, 3] += r[:, 0] * self.baseline
        elif side != "left":
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        return t

    def map_from_camera(self, pose: Pose2, side: str = "left") -> np.ndarray:
        """4x4 transform taking camera-frame points to the map frame for a vehicle at ``pose``."""
        return pose.matrix3d() @ self.vehicle_from_camera(side)

    # --- projection -------------------------------------------------------------------------------
    def project(self, pts_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (..., 2) and depths (...) of camera-frame points (..., 3)."""
        pts_cam = np.asarray(pts_cam, dtype=np.float64)
        z = pts_cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pts_cam[..., 0] / z + self.cx
            v = self.fy * pts_cam[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1), z

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) of pixels (..., 2) at metric depth (z) ``depth`` (...)."""
        uv = np.asarray(uv, dtype=np.float64)
        d = np.asarray(depth, dtype=np.float64)
        x = (uv[..., 0] - self.cx) / self.fx * d
        y = (uv[..., 1] - self.cy) / self.fy * d
        return np.stack([x, y, d], axis=-1)

    def pixels_to_map(self, pose: Pose2, uv: np.ndarray, depth: np.ndarray, side: str = "left") -> np.ndarray:
        """Map-frame 3-D points (..., 3) of left-camera pixels with known depth, vehicle at ``pose``."""
        p = self.backproject(uv, depth)
        t = self.map_from_camera(pose, side)
        return p @ t[:3, :3].T + t[:3, 3]

    def map_to_pixels(self, pose: Pose2, pts_map: np.ndarray, side: str = "left") -> tuple[np.ndarray, np.ndarray]:
        """Pixels and depths of map-frame 3-D points seen from the camera at ``pose``."""
        t = np.linalg.inv(self.map_from_camera(pose, side))
        p = np.asarray(pts_map, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]
        return self.project(p)

    def disparity_to_depth(self, disparity: np.ndarray) -> np.ndarray:
        """Metric depth of a disparity map (pixels); non-positive disparity gives 0 (invalid)."""
        d = np.asarray(disparity, dtype=np.float32)
        out = np.zeros_like(d)
        ok = d > 0
        out[ok] = self.fx * self.baseline / d[ok]
        return out

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
