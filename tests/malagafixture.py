"""Writes small Malaga Urban extracts in the dataset's layout, for tests (see satloc/datasets/malaga.py).

The files follow the documented formats exactly: the GPS log as MRPT's ``rawlog-edit --export-gps-txt``
prints it (a ``%`` header line, 25 columns, Lat/Lon in radians, Time with ``%14.4f``), the camera file as an
MRPT ``TStereoCamera`` config block (with cx/cy/fx/fy on the lines where line-based readers look for them),
and ``img_CAMERA1_<time>_left.jpg`` / ``_right.jpg`` pairs. Only the image size is smaller than the real
800x600, to keep tests fast; images are synthetic.

    from malagafixture import write_malaga_extract, TurnTrack
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

MALAGA_LON0, MALAGA_LAT0 = -4.4777, 36.7153  # central Malaga, for synthetic tracks
T0 = 1261228749.9186  # a UNIX time in December 2009, when the dataset was recorded
_WGS84_A, _WGS84_F = 6378137.0, 1 / 298.257223563


@dataclass
class MalagaExtract:
    """What :func:`write_malaga_extract` wrote, in the exact values a reader should get back."""

    root: Path
    image_dir: Path
    camera_file: Path
    gps_file: Path
    image_times: np.ndarray  # (N,) of the pairs written, as the file names give them
    gps_times: np.ndarray  # (M,) as written (%14.4f)
    gps_lonlat: np.ndarray  # (M, 2) degrees (written in radians)
    gps_fix: np.ndarray  # (M,)
    camera: dict  # width, height, fx, fy, cx, cy, baseline as written
    left_names: list[str] = field(default_factory=list)
    right_names: list[str] = field(default_factory=list)


def _geocentric(lon, lat, alt):
    e2 = _WGS84_F * (2 - _WGS84_F)
    lo, la = np.radians(lon), np.radians(lat)
    n = _WGS84_A / np.sqrt(1 - e2 * np.sin(la) ** 2)
    return np.stack([(n + alt) * np.cos(la) * np.cos(lo), (n + alt) * np.cos(la) * np.sin(lo),
                     (n * (1 - e2) + alt) * np.sin(la)], axis=-1)


def _enu(xyz, lon0, lat0, xyz0):
    lo, la = math.radians(lon0), math.radians(lat0)
    r = np.array([[-math.sin(lo), math.cos(lo), 0.0],
                  [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
                  [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]])
    return (xyz - xyz0) @ r.T


GPS_HEADER = ("%% " + "%14s " + "%23s %23s %23s " + "%4s %4s %11s %11s " + "%23s %23s %23s " + "%6s "
              + "%21s %21s %21s " * 4 + "%14s ") % (
    "Time", "Lat", "Lon", "Alt", "fix", "#sats", "speed", "dir", "Local X", "Local Y", "Local Z", "rawlog ID",
    "Geocen X", "Geocen Y", "Geocen Z", "GPS X", "GPS Y", "GPS Z", "GPS VX", "GPS VY", "GPS VZ",
    "Local VX", "Local VY", "Local VZ", "SAT Time")


def gps_line(t, lat_rad, lon_rad, alt, fix, sats, speed, direction, local, idx, geocen) -> str:
    """One row as MRPT's exporter prints it (``rawlog-edit_gps.cpp``), 25 columns."""
    return (f"{t:14.4f} {lat_rad:23.16f} {lon_rad:23.16f} {alt:23.6f} {int(fix):4d} {int(sats):4d} "
            f"{speed:11.6f} {direction:11.6f} {local[0]:23.16f} {local[1]:23.16f} {local[2]:23.16f} "
            f"{int(idx):6d} {geocen[0]:21.16f} {geocen[1]:21.16f} {geocen[2]:21.16f} "
            + " ".join(f"{0.0:21.16f}" for _ in range(9)) + f" {t:14.4f} ")


def write_gps_log(path: Path, times, lonlat, fix=None, alt: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Write a ``*_all-sensors_GPS.txt``; returns the times and fixes as written."""
    times = np.asarray(times, np.float64)
    lonlat = np.asarray(lonlat, np.float64)
    fix = np.full(len(times), 1, np.int64) if fix is None else np.asarray(fix, np.int64)
    geo = _geocentric(lonlat[:, 0], lonlat[:, 1], np.full(len(times), alt))
    ok = np.flatnonzero(fix != 0)
    ref = ok[0] if len(ok) else 0
    local = _enu(geo, lonlat[ref, 0], lonlat[ref, 1], geo[ref])
    lines = [GPS_HEADER]
    for i, t in enumerate(times):
        if i + 1 < len(times):
            v = local[i + 1, :2] - local[i, :2]
            dtt = times[i + 1] - t
        else:
            v = local[i, :2] - local[max(i - 1, 0), :2]
            dtt = t - times[max(i - 1, 0)] or 1.0
        speed_knots = float(np.hypot(*v) / dtt * 3600 / 1852)
        direction = math.degrees(math.atan2(v[0], v[1])) % 360  # README: heading in degrees
        lines.append(gps_line(t, math.radians(lonlat[i, 1]), math.radians(lonlat[i, 0]), alt, fix[i], 9,
                              speed_knots, direction, local[i], 100 * i + 7, geo[i]))
    path.write_text("\n".join(lines) + "\n")
    return np.array([float(f"{t:.4f}") for t in times]), fix


def write_camera_file(path: Path, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                      baseline: float) -> dict:
    """An MRPT TStereoCamera config block; returns the values as written (5 decimals, as MRPT prints)."""
    vals = {k: float(f"{v:.5f}") for k, v in dict(fx=fx, fy=fy, cx=cx, cy=cy).items()}
    b = float(f"{baseline:.6f}")

    def cam(section):
        return [f"[{section}]", f"resolution=[{width} {height}]", f"cx={vals['cx']:.5f}", f"cy={vals['cy']:.5f}",
                f"fx={vals['fx']:.5f}", f"fy={vals['fy']:.5f}",
                "dist=[0.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00]",
                "focal_length=0.0038"]

    lines = ["# Rectified stereo camera parameters (a=0: only valid pixels), MRPT TStereoCamera block.",
             "# Written by satloc's test fixture in the layout of the Malaga Urban Dataset extracts.",
             "# Units: pixels; pose_quaternion = [x y z qr qx qy qz] of the right camera in the left (m).",
             ""]
    lines += cam("CAMERA_LEFT")
    lines += ["", "# ----------------------------------------------------------------------", ""]
    lines += cam("CAMERA_RIGHT")
    lines += ["", "# ----------------------------------------------------------------------", ""]
    lines += ["[CAMERA_LEFT2RIGHT_POSE]", f"pose_quaternion=[{b:.6f} 0.000000 0.000000 1.000000 0.000000 "
              f"0.000000 0.000000]"]
    path.write_text("\n".join(lines) + "\n")
    assert lines[6].startswith("cx=") and lines[17].startswith("cx=") and lines[27].startswith("pose_q")
    return dict(vals, width=width, height=height, baseline=b)


def synthetic_pair(i: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """A textured left image and a darker right one (RGB uint8), different per frame."""
    rng = np.random.default_rng(1000 + i)
    base = cv2.resize(rng.integers(0, 255, (height // 4 + 1, width // 4 + 1, 3), dtype=np.uint8),
                      (width, height), interpolation=cv2.INTER_LINEAR)
    left = np.clip(base.astype(np.int16) // 2 + 120, 0, 255).astype(np.uint8)
    right = np.clip(base.astype(np.int16) // 2 + 10, 0, 255).astype(np.uint8)
    return left, right


def write_malaga_extract(parent: Path, image_times: Sequence[float], gps_times: Sequence[float],
                         gps_lonlat, *, number: int = 7, size: tuple[int, int] = (80, 60),
                         fx: float = 62.118428, fy: float = 62.118428, cx: float = 40.40076,
                         cy: float = 30.905989, baseline: float = 0.119471, gps_fix=None,
                         images: Callable[[int], tuple[np.ndarray, np.ndarray]] | None = None,
                         drop_right: Sequence[int] = (), drop_left: Sequence[int] = (),
                         a0_in_folder_name: bool = False) -> MalagaExtract:
    """Write ``parent/malaga-urban-dataset-extract-NN/`` with one stereo pair per image time.

    Defaults are extract 07's 800x600 camera (fx 621.18428, cx 404.0076, cy 309.05989; Bumblebee baseline)
    scaled to 80x60. ``drop_right`` / ``drop_left``: frame indices written with one side only."""
    name = f"malaga-urban-dataset-extract-{number:02d}"
    root = Path(parent) / name
    w, h = size
    folder = f"{name}_rectified_{'a=0_' if a0_in_folder_name else ''}{w}x{h}_Images"
    image_dir = root / folder
    image_dir.mkdir(parents=True)
    camera = write_camera_file(root / f"camera_params_rectified_a=0_{w}x{h}.txt", w, h, fx, fy, cx, cy, baseline)
    images = images or (lambda i: synthetic_pair(i, w, h))
    stamps = [f"{t:.6f}" for t in image_times]
    lefts, rights, listing = [], [], []
    for i, s in enumerate(stamps):
        left, right = images(i)
        ln, rn = f"img_CAMERA1_{s}_left.jpg", f"img_CAMERA1_{s}_right.jpg"
        if i not in drop_left:
            assert cv2.imwrite(str(image_dir / ln), cv2.cvtColor(left, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, 95])
            listing.append(ln)
        if i not in drop_right:
            assert cv2.imwrite(str(image_dir / rn), cv2.cvtColor(right, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, 95])
            listing.append(rn)
        lefts.append(ln)
        rights.append(rn)
    (root / f"{name}_IMAGES.txt").write_text("\n".join(listing) + "\n")
    gps_file = root / f"{name}_all-sensors_GPS.txt"
    gt, gfix = write_gps_log(gps_file, gps_times, gps_lonlat, gps_fix)
    paired = [i for i in range(len(stamps)) if i not in drop_left and i not in drop_right]
    return MalagaExtract(root, image_dir, root / f"camera_params_rectified_a=0_{w}x{h}.txt", gps_file,
                         np.array([float(stamps[i]) for i in paired]), gt, np.asarray(gps_lonlat, np.float64),
                         gfix, camera, [lefts[i] for i in paired], [rights[i] for i in paired])


@dataclass(frozen=True)
class TurnTrack:
    """A drive in map metres: ``straight1`` m east, a left turn of ``radius`` through ``angle`` rad, then
    ``straight2`` m, at ``speed`` m/s, optionally standing still for ``stop_s`` seconds after ``stop_at_m``."""

    straight1: float = 30.0
    radius: float = 20.0
    angle: float = math.pi / 2
    straight2: float = 30.0
    speed: float = 6.0
    stop_at_m: float = 0.0
    stop_s: float = 0.0

    @property
    def length(self) -> float:
        return self.straight1 + self.radius * self.angle + self.straight2

    @property
    def duration(self) -> float:
        return self.length / self.speed + self.stop_s

    def distance(self, t):
        """Metres driven after ``t`` seconds."""
        t = np.asarray(t, np.float64)
        s = self.speed * t
        if self.stop_s > 0:
            t_stop = self.stop_at_m / self.speed
            s = np.where(t < t_stop, s, np.where(t < t_stop + self.stop_s, self.stop_at_m,
                                                 self.speed * (t - self.stop_s)))
        return np.clip(s, 0.0, self.length)

    def at(self, s):
        """(x, y, heading) at arc length ``s`` (..., 3)."""
        s = np.asarray(s, np.float64)
        arc = self.radius * self.angle
        x = np.where(s <= self.straight1, s, 0.0)
        y = np.zeros_like(s)
        head = np.zeros_like(s)
        on_arc = (s > self.straight1) & (s <= self.straight1 + arc)
        th = (s - self.straight1) / self.radius
        x = np.where(on_arc, self.straight1 + self.radius * np.sin(th), x)
        y = np.where(on_arc, self.radius * (1 - np.cos(th)), y)
        head = np.where(on_arc, th, head)
        after = s > self.straight1 + arc
        r = s - self.straight1 - arc
        ex, ey = self.straight1 + self.radius * math.sin(self.angle), self.radius * (1 - math.cos(self.angle))
        x = np.where(after, ex + r * math.cos(self.angle), x)
        y = np.where(after, ey + r * math.sin(self.angle), y)
        head = np.where(after, self.angle, head)
        return np.stack([x, y, head], axis=-1)


def track_lonlat(xy, lon0: float = MALAGA_LON0, lat0: float = MALAGA_LAT0) -> np.ndarray:
    """WGS84 degrees of map metres in the GeoFrame at (lon0, lat0)."""
    from satloc.geoframe import GeoFrame

    return GeoFrame(lon0, lat0).to_lonlat(np.asarray(xy, np.float64))
