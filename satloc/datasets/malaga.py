"""Reader of the Malaga Urban Dataset extracts (Blanco-Claraco, Moreno-Dueñas, González-Jiménez, IJRR 2014).

:func:`load_malaga` turns one extract directory into a lazy :class:`satloc.sequence.Sequence`: the rectified
stereo pairs, the rectified camera, and poses from the GPS log, projected into a
:class:`satloc.geoframe.GeoFrame`.

Layout of an extract (``malaga-urban-dataset-extract-NN/``), as this module reads it::

    malaga-urban-dataset-extract-NN_rectified_800x600_Images/    (and/or ..._1024x768_Images/)
        img_CAMERA1_<unix time>_left.jpg, img_CAMERA1_<unix time>_right.jpg
    camera_params_rectified_a=0_800x600.txt                       (and/or ..._1024x768.txt)
    malaga-urban-dataset-extract-NN_all-sensors_GPS.txt

Format facts and where they come from (no Malaga data could be downloaded while this was written; the
reader is written against these sources, and the test fixture ``tests/malagafixture.py`` against them too):

* **GPS log** (``*_GPS.txt``). The extracts' own README (``README.txt`` shipped in each extract, "Part of the
  Malaga Urban Dataset"; text seen in the code corpus) lists the columns: Time (UNIX time_t with decimals),
  Lat and Lon (WGS84, **radians**), Alt (m), fix (0 signal lost, 1 standalone, 4 RTK fix, 5 float RTK,
  6 dead reckoning), #sats, speed, dir, Local X/Y/Z (m, ENU about a point near the start), rawlog ID,
  Geocen X/Y/Z, GPS X/Y/Z, GPS VX/VY/VZ, Local VX/VY/VZ, Satellite time: 25 columns. MRPT's exporter that
  writes this file (``apps/rawlog-edit/rawlog-edit_gps.cpp``, ``op_export_gps_txt``) confirms the order,
  the count, the header line starting with ``%`` and the radians (``DEG2RAD(latitude_degrees)``); it prints
  Time with ``%14.4f``. A C++ pose importer seen in the code corpus (RTAB-Map style, its "Malaga Urban
  format") also expects 25 values and skips the header line.
  *Where the sources disagree*: the README gives speed in knots and dir (heading) in degrees, while MRPT's
  exporter writes ``DEG2RAD(speed_knots)`` and ``DEG2RAD(direction_degrees)``. This reader uses neither.
* **Images**: ``img_CAMERA1_<unix time>_left.jpg`` / ``_right.jpg``, time with 6 decimals (e.g.
  ``img_CAMERA1_1261228749.918590_left.jpg``, quoted by VSLAM-LAB's Malaga loader). *Where the sources
  disagree*: the extract README names the folders ``{*}_rectified_a=0_800x600_Images``, while every loader
  seen (MATLAB/Python VO projects on extract 07, VSLAM-LAB, srrg2's converter) uses
  ``{*}_rectified_800x600_Images``; both are accepted. VSLAM-LAB notes that a handful of frames ship with
  only one side.
* **Camera file**: MRPT's ``TStereoCamera`` config block (``libs/img/src/TStereoCamera.cpp``,
  ``TCamera.cpp``): sections ``[CAMERA_LEFT]``, ``[CAMERA_RIGHT]`` with ``resolution=[ncols nrows]``,
  ``cx``, ``cy``, ``fx``, ``fy`` (pixels; MRPT's loader scales values below 2 by the image size), ``dist``,
  ``focal_length``; and ``[CAMERA_LEFT2RIGHT_POSE]`` ``pose_quaternion=[x y z qr qx qy qz]``, the right
  camera's pose in the left one, whose x is the baseline in metres (VSLAM-LAB and srrg2 read it so;
  srrg2 also reads cx, cy, fx, fy from lines 7-10 and 18-21 and the pose from line 28). For extract 07 at
  800x600, VO course code uses K = [621.18428 0 404.0076; 0 621.18428 309.05989].
* **Camera placement**: the dataset paper's Table 2 gives the sensors' poses in the vehicle's reference
  frame; MRPT's ``malaga-urban-dataset-playback-3d`` (``project-lidar-into-image``) corrects the camera's z
  there from 0.273 (a typo) to 0.057 m. The height of that reference frame above the road, and the
  camera's pitch, were not found in any source reachable here: ``mount_height`` defaults to
  :data:`MALAGA_MOUNT_HEIGHT_M` = 1.6 m, an *estimate* for a camera on a car's roof rack, not a documented
  figure, and ``pitch`` to 0. Both are configuration fields; set them when the paper's values are at hand.

Choices made here:

* **Poses**: GPS fixes with fix = 0 (signal lost) are dropped; the rest are projected into the frame and
  interpolated linearly in time to each image time (positions equal the linearly interpolated lat/lon).
  The pose is that of the GPS antenna; its lever arm to the left camera is not documented and is ignored.
* **Yaw** is the direction of travel: a cubic Hermite curve by arc length through the fixes (each run of
  fixes within ``min_step_m`` of its first replaced by its mean, so GPS jitter while standing still adds
  no wiggles), read as the chord over ``heading_window_m`` (3 m) centred on the image's place along the
  track. Standing still, the image keeps the heading of the track through the place where the vehicle
  stands. The window trades GPS noise against turns entered without a transition curve, where the chord
  errs by up to about window / (8 R) radians (0.7 degrees for 3 m at R = 30 m). With fixes far apart on a
  tight turn the curve cannot know where the turn starts: on a 15 m radius turn entered from a straight,
  fixes 7 m apart (1 Hz at 25 km/h) gave up to 5.3 degrees near the turn's ends (1.3 degrees at 5 Hz).
* **Frames without a pose**: frames before the first fix, after the last, in a gap between fixes longer
  than ``max_gap_s``, or on a track too short to give a heading are kept with a NaN pose row
  (``Frame.pose`` None), so frame i is always the i-th stereo pair of the folder.
* **Unpaired images**: a left image without its right (or the reverse) is skipped; their names are in
  ``meta["unpaired_skipped"]``.
* **Timestamps** are seconds from the first pair, from the image file names' UNIX times; the first pair's
  time as its file name spells it is ``meta["time_origin"]`` (as :mod:`satloc.datasets.kitti` does).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from ..config import from_dict
from ..errors import ConfigError, FormatError
from ..geoframe import GeoFrame
from ..geometry import Pose2, StereoCamera, arc_length
from ..satmap import read_image
from ..sequence import Frame, Sequence, check_camera_ranges

MALAGA_MOUNT_HEIGHT_M = 1.6  # an estimate, see the module docstring: no source gave the height above the road

GPS_COLUMNS = (
    "Time", "Lat", "Lon", "Alt", "fix", "#sats", "speed", "dir", "Local X", "Local Y", "Local Z", "rawlog ID",
    "Geocen X", "Geocen Y", "Geocen Z", "GPS X", "GPS Y", "GPS Z", "GPS VX", "GPS VY", "GPS VZ",
    "Local VX", "Local VY", "Local VZ", "SAT Time",
)
"""The 25 columns of an extract's ``*_GPS.txt`` (extract README; MRPT ``rawlog-edit --export-gps-txt``)."""

IMAGE_RE = re.compile(r"^img_CAMERA1_(\d+(?:\.\d+)?)_(left|right)\.jpg$")
IMAGE_DIR_RE = re.compile(r"_rectified_(?:a=[^_]*_)?(\d+)x(\d+)_Images$")
CAMERA_FILE_RE = re.compile(r"^camera_params_rectified(?:_a=[^_]*)?_(\d+)x(\d+)\.txt$")

_GPS_T, _GPS_LAT, _GPS_LON, _GPS_FIX = 0, 1, 2, 4


@dataclass(frozen=True)
class MalagaConfig:
    """How :func:`load_malaga` reads an extract."""

    resolution: str | None = None  # "800x600" or "1024x768"; None: the largest rectified folder present
    mount_height: float = MALAGA_MOUNT_HEIGHT_M  # left camera above the road, metres (estimate)
    pitch: float = 0.0  # camera pitch down, radians (undocumented)
    heading_window_m: float = 3.0  # yaw: direction of the track over this length
    min_step_m: float = 1.0  # yaw: a run of fixes within this of its first is one place (jitter)
    max_gap_s: float | None = 5.0  # no pose between fixes further apart in time than this

    def __post_init__(self):
        if self.resolution is not None and not re.fullmatch(r"\d+x\d+", self.resolution):
            raise ConfigError(f"resolution: expected 'WIDTHxHEIGHT' such as '800x600', got {self.resolution!r}")
        for name in ("mount_height", "heading_window_m", "min_step_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: expected a positive number of metres, got {v!r}")
        if not math.isfinite(self.pitch):
            raise ConfigError(f"pitch: expected a finite angle in radians, got {self.pitch!r}")
        if self.max_gap_s is not None and not (math.isfinite(self.max_gap_s) and self.max_gap_s > 0):
            raise ConfigError(f"max_gap_s: expected a positive number of seconds or null, got {self.max_gap_s!r}")


@dataclass(frozen=True)
class GpsLog:
    """The usable rows of a GPS log: times (s), WGS84 latitude and longitude (degrees), fix quality."""

    path: Path
    times: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    fix: np.ndarray
    lines: np.ndarray  # 1-based line number of each row in the file


@dataclass(frozen=True)
class StereoPairs:
    """The stereo pairs of an image folder, sorted by time, and the images left without their other side."""

    times: np.ndarray  # UNIX seconds
    stamps: list[str]  # the times as the file names spell them
    left: list[Path]
    right: list[Path]
    unpaired: list[str]


# --- GPS ------------------------------------------------------------------------------------------------

def read_gps_log(path: str | Path) -> GpsLog:
    """Read an extract's ``*_GPS.txt``: rows with fix 0 (signal lost) and repeated times are dropped.

    Raises FormatError naming the file and line for a row without 25 columns, a field that is not a number,
    a latitude/longitude that is not in radians, time going backwards, or a log with no usable fix."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: GPS log not found")
    try:
        text = path.read_text(encoding="ascii", errors="strict")
    except (UnicodeDecodeError, OSError) as e:
        raise FormatError(f"{path}: not a readable text GPS log ({e})") from e
    rows, lines = [], []
    for n, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("%"):
            continue
        parts = s.split()
        if len(parts) != len(GPS_COLUMNS):
            raise FormatError(f"{path} line {n}: expected {len(GPS_COLUMNS)} whitespace-separated columns "
                              f"({', '.join(GPS_COLUMNS)}), got {len(parts)}")
        vals = []
        for k, p in enumerate(parts):
            try:
                v = float(p)
            except ValueError:
                raise FormatError(f"{path} line {n}: column {k + 1} ({GPS_COLUMNS[k]}) is not a number: "
                                  f"{p!r}") from None
            if not math.isfinite(v) and k in (_GPS_T, _GPS_LAT, _GPS_LON, _GPS_FIX):
                raise FormatError(f"{path} line {n}: column {k + 1} ({GPS_COLUMNS[k]}) is not finite: {p!r}")
            vals.append(v)
        if abs(vals[_GPS_LAT]) > math.pi / 2 or abs(vals[_GPS_LON]) > math.pi:
            raise FormatError(f"{path} line {n}: Lat {parts[_GPS_LAT]}, Lon {parts[_GPS_LON]} are not WGS84 "
                              f"radians (the extracts' README and MRPT's exporter give radians)")
        rows.append(vals)
        lines.append(n)
    if not rows:
        raise FormatError(f"{path}: empty GPS log, expected rows of {len(GPS_COLUMNS)} columns "
                          f"({', '.join(GPS_COLUMNS)})")
    a = np.array(rows, dtype=np.float64)
    ln = np.array(lines)
    keep = a[:, _GPS_FIX] != 0
    a, ln = a[keep], ln[keep]
    if not len(a):
        raise FormatError(f"{path}: no GPS fix (every row has fix = 0, signal lost)")
    dt = np.diff(a[:, _GPS_T])
    if np.any(dt < 0):
        i = int(np.argmax(dt < 0)) + 1
        raise FormatError(f"{path} line {ln[i]}: Time {a[i, _GPS_T]!r} is earlier than the previous fix's "
                          f"{a[i - 1, _GPS_T]!r}; expected times in increasing order")
    first = np.concatenate([[True], dt > 0])  # a repeated time keeps its first row
    a, ln = a[first], ln[first]
    return GpsLog(path, a[:, _GPS_T].copy(), np.degrees(a[:, _GPS_LAT]), np.degrees(a[:, _GPS_LON]),
                  a[:, _GPS_FIX].astype(np.int64), ln)


# --- camera ---------------------------------------------------------------------------------------------

def _parse_ini(path: Path) -> dict[str, dict[str, tuple[str, int]]]:
    sections: dict[str, dict[str, tuple[str, int]]] = {}
    current = None
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (UnicodeDecodeError, OSError) as e:
        raise FormatError(f"{path}: not a readable text camera file ({e})") from e
    for n, raw in enumerate(text.splitlines(), start=1):
        s = raw.split("//", 1)[0].strip()
        if not s or s[0] in "#;":
            continue
        if s.startswith("[") and s.endswith("]"):
            current = s[1:-1].strip()
            if current in sections:
                raise FormatError(f"{path} line {n}: section [{current}] appears twice")
            sections[current] = {}
            continue
        if "=" not in s:
            raise FormatError(f"{path} line {n}: expected 'key=value', '[SECTION]' or a comment, got {raw!r}")
        if current is None:
            raise FormatError(f"{path} line {n}: 'key=value' before any [SECTION]")
        key, value = (p.strip() for p in s.split("=", 1))
        if key in sections[current]:
            raise FormatError(f"{path} line {n}: [{current}] {key} appears twice")
        sections[current][key] = (value, n)
    return sections


def _numbers(path: Path, sections, section: str, key: str, count: int | None = None) -> list[float]:
    if section not in sections:
        raise FormatError(f"{path}: missing section [{section}]; expected [CAMERA_LEFT], [CAMERA_RIGHT] and "
                          f"[CAMERA_LEFT2RIGHT_POSE] (MRPT TStereoCamera config block)")
    if key not in sections[section]:
        raise FormatError(f"{path}: [{section}] has no '{key}' field")
    value, n = sections[section][key]
    body = value[1:-1] if value.startswith("[") and value.endswith("]") else value
    try:
        out = [float(v) for v in body.replace(",", " ").split()]
    except ValueError:
        raise FormatError(f"{path} line {n}: [{section}] {key} = {value!r} is not a number"
                          + ("" if count == 1 else "s")) from None
    if (count is not None and len(out) != count) or not out or not all(math.isfinite(v) for v in out):
        want = "a number" if count == 1 else f"{count} numbers"
        raise FormatError(f"{path} line {n}: [{section}] {key}: expected {want}, got {value!r}")
    return out


def read_camera_params(path: str | Path, mount_height: float = MALAGA_MOUNT_HEIGHT_M,
                       pitch: float = 0.0) -> StereoCamera:
    """The rectified stereo camera of a ``camera_params_rectified_*.txt`` file (MRPT TStereoCamera format).

    The left and right sections must describe one rectified camera (same fx, fy, cx, cy, resolution);
    the baseline is the x of ``[CAMERA_LEFT2RIGHT_POSE] pose_quaternion``."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: camera parameter file not found")
    ini = _parse_ini(path)
    cams = {}
    for side in ("CAMERA_LEFT", "CAMERA_RIGHT"):
        w, h = _numbers(path, ini, side, "resolution", 2)
        if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
            raise FormatError(f"{path} line {ini[side]['resolution'][1]}: [{side}] resolution: expected "
                              f"[ncols nrows] positive integers, got {ini[side]['resolution'][0]!r}")
        k = {name: _numbers(path, ini, side, name, 1)[0] for name in ("fx", "fy", "cx", "cy")}
        for name, size in (("fx", w), ("fy", h), ("cx", w), ("cy", h)):
            if k[name] < 2.0:  # MRPT's TCamera::loadFromConfigFile: values below 2 are fractions of the size
                k[name] *= size
        if k["fx"] <= 0 or k["fy"] <= 0:
            raise FormatError(f"{path}: [{side}] focal lengths must be positive, got fx={k['fx']}, fy={k['fy']}")
        cams[side] = dict(k, width=int(w), height=int(h))
    left, right = cams["CAMERA_LEFT"], cams["CAMERA_RIGHT"]
    for name in ("width", "height", "fx", "fy", "cx", "cy"):
        if abs(left[name] - right[name]) > 1e-3:
            raise FormatError(f"{path}: [CAMERA_RIGHT] {name} = {right[name]} differs from [CAMERA_LEFT] "
                              f"{name} = {left[name]}; a rectified pair needs one camera for both sides")
    pose = _numbers(path, ini, "CAMERA_LEFT2RIGHT_POSE", "pose_quaternion", 7)
    if not pose[0] > 0:
        raise FormatError(f"{path} line {ini['CAMERA_LEFT2RIGHT_POSE']['pose_quaternion'][1]}: "
                          f"[CAMERA_LEFT2RIGHT_POSE] pose_quaternion: expected the right camera at x > 0 "
                          f"(the baseline, metres), got x = {pose[0]}")
    return check_camera_ranges(StereoCamera(left["width"], left["height"], left["fx"], left["fy"], left["cx"],
                                            left["cy"], pose[0], float(mount_height), float(pitch)),
                               f"{path}: the camera")


# --- images ---------------------------------------------------------------------------------------------

def list_stereo_pairs(image_dir: str | Path) -> StereoPairs:
    """The ``img_CAMERA1_<time>_left.jpg`` / ``_right.jpg`` pairs of a folder, by time; other files are ignored."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise FormatError(f"{image_dir}: image folder not found")
    sides: dict[str, dict[str, Path]] = {"left": {}, "right": {}}
    for p in image_dir.iterdir():
        m = IMAGE_RE.match(p.name)
        if m:
            sides[m.group(2)][m.group(1)] = p
    both = set(sides["left"]) & set(sides["right"])
    unpaired = sorted(p.name for s in ("left", "right") for t, p in sides[s].items() if t not in both)
    stamps = sorted(both, key=lambda t: (float(t), t))
    if not stamps:
        raise FormatError(f"{image_dir}: no stereo pairs (img_CAMERA1_<unix time>_left.jpg with its "
                          f"_right.jpg)" + (f"; unpaired: {unpaired[:5]}" if unpaired else ""))
    times = np.array([float(t) for t in stamps], dtype=np.float64)
    if np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0))
        raise FormatError(f"{image_dir}: images {stamps[i]!r} and {stamps[i + 1]!r} have the same time")
    return StereoPairs(times, stamps, [sides["left"][t] for t in stamps], [sides["right"][t] for t in stamps],
                       unpaired)


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from a JPEG file's frame header (SOF segment), without decoding the image."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            if f.read(2) != b"\xff\xd8":
                raise FormatError(f"{path}: not a JPEG image")
            while True:
                b = f.read(1)
                if b != b"\xff":  # every segment starts with a marker
                    break
                while b == b"\xff":  # fill bytes before the marker's code
                    b = f.read(1)
                if not b:
                    break
                marker = b[0]
                if marker == 0x01 or 0xD0 <= marker <= 0xD7:
                    continue
                seg = f.read(2)
                if len(seg) < 2:
                    break
                length = int.from_bytes(seg, "big")
                if marker in _JPEG_SOF:
                    body = f.read(5)
                    if len(body) < 5:
                        break
                    h, w = int.from_bytes(body[1:3], "big"), int.from_bytes(body[3:5], "big")
                    return w, h
                if marker in (0xD9, 0xDA) or length < 2:  # end of image or scan data before any frame header
                    break
                f.seek(length - 2, 1)
    except OSError as e:
        raise FormatError(f"{path}: image file not readable ({e})") from e
    raise FormatError(f"{path}: not a JPEG image (no frame header)")


def _read_pair(left: Path, right: Path) -> tuple[np.ndarray, np.ndarray]:
    a, b = read_image(left), read_image(right)
    if a.shape != b.shape:
        raise FormatError(f"{left} is {a.shape[1]}x{a.shape[0]} but {right} is {b.shape[1]}x{b.shape[0]}; "
                          f"expected a stereo pair of one size")
    return a, b


class _PairReader:
    """Reads pair ``i`` of an extract (a plain object, so a sequence can be pickled to a worker process)."""

    def __init__(self, left: list[Path], right: list[Path], poses: np.ndarray, stamps: np.ndarray):
        self.left, self.right, self.poses, self.stamps = left, right, poses, stamps

    def __call__(self, i: int) -> Frame:
        a, b = _read_pair(self.left[i], self.right[i])
        p = self.poses[i]
        return Frame(a, b, Pose2.from_array(p) if np.all(np.isfinite(p)) else None, float(self.stamps[i]))


# --- poses ----------------------------------------------------------------------------------------------

def _hermite_track(v: np.ndarray):
    """Arc lengths of the vertices ``v`` (K, 2) and a C1 curve through them by arc length (Catmull-Rom
    tangents from the neighbours), returned as ``(u, curve(q) -> (..., 2))``."""
    u = arc_length(v)
    m = np.empty_like(v)
    m[0] = (v[1] - v[0]) / (u[1] - u[0])
    m[-1] = (v[-1] - v[-2]) / (u[-1] - u[-2])
    if len(v) > 2:
        m[1:-1] = (v[2:] - v[:-2]) / (u[2:] - u[:-2])[:, None]

    def curve(q):
        q = np.clip(np.asarray(q, np.float64), 0.0, u[-1])
        k = np.clip(np.searchsorted(u, q, side="right") - 1, 0, len(u) - 2)
        h = (u[k + 1] - u[k])[:, None]
        s = ((q - u[k]) / (u[k + 1] - u[k]))[:, None]
        s2, s3 = s * s, s * s * s
        return ((2 * s3 - 3 * s2 + 1) * v[k] + (s3 - 2 * s2 + s) * h * m[k]
                + (-2 * s3 + 3 * s2) * v[k + 1] + (s3 - s2) * h * m[k + 1])

    return u, curve


def _track_vertices(ft: np.ndarray, fxy: np.ndarray, min_step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Times and positions of the track's vertices: each run of consecutive fixes within ``min_step_m`` of
    the run's first fix becomes one vertex, the run's mean time and position."""
    times, points = [], []
    i = 0
    while i < len(ft):
        j = i + 1
        while j < len(ft) and np.hypot(*(fxy[j] - fxy[i])) < min_step_m:
            j += 1
        p = fxy[i:j].mean(axis=0)
        if not points or np.hypot(*(p - points[-1])) >= 0.25 * min_step_m:
            times.append(ft[i:j].mean())
            points.append(p)
        i = j
    return np.array(times), np.array(points).reshape(-1, 2)


def track_poses(fix_times: np.ndarray, fix_xy: np.ndarray, times: np.ndarray,
                heading_window_m: float = 3.0, min_step_m: float = 1.0,
                max_gap_s: float | None = 5.0) -> np.ndarray:
    """Poses (N, 3) [x, y, yaw] at ``times`` from a track of fixes (``fix_times`` increasing, ``fix_xy`` in
    metres); NaN rows where there is none (outside the track, in a gap, no heading). See the module
    docstring for the method."""
    ft = np.asarray(fix_times, np.float64)
    fxy = np.asarray(fix_xy, np.float64)
    t = np.asarray(times, np.float64)
    out = np.full((len(t), 3), np.nan)
    inside = (t >= ft[0]) & (t <= ft[-1])
    if max_gap_s is not None and len(ft) > 1:
        j = np.clip(np.searchsorted(ft, t, side="right"), 1, len(ft) - 1)
        inside &= (ft[j] - ft[j - 1] <= max_gap_s) | (t == ft[j - 1]) | (t == ft[j])
    if not inside.any():
        return out
    out[:, 0] = np.interp(t, ft, fxy[:, 0])
    out[:, 1] = np.interp(t, ft, fxy[:, 1])
    # heading: a curve by arc length through the fixes, each run of fixes within min_step_m of its first
    # (standing still, GPS jitter) replaced by its mean
    vt, vxy = _track_vertices(ft, fxy, min_step_m)
    if len(vt) >= 2:
        u, curve = _hermite_track(vxy)
        q = np.interp(t, vt, u)
        total = u[-1]
        a = np.clip(q - heading_window_m / 2, 0.0, max(total - heading_window_m, 0.0))
        b = np.minimum(a + heading_window_m, total)
        d = curve(b) - curve(a)
        out[:, 2] = np.arctan2(d[:, 1], d[:, 0])
    out[~inside] = np.nan
    out[np.isnan(out).any(axis=1)] = np.nan
    return out


# --- the extract ----------------------------------------------------------------------------------------

def _choose_images(root: Path, resolution: str | None) -> tuple[Path, int, int]:
    found = {}
    for p in root.iterdir():
        m = IMAGE_DIR_RE.search(p.name)
        if p.is_dir() and m:
            found.setdefault((int(m.group(1)), int(m.group(2))), []).append(p)
    if not found:
        raise FormatError(f"{root}: no rectified image folder (<extract>_rectified_800x600_Images or "
                          f"_1024x768_Images)")
    if resolution is None:
        size = max(found, key=lambda s: s[0] * s[1])
    else:
        size = tuple(int(v) for v in resolution.split("x"))
        if size not in found:
            raise ConfigError(f"resolution: {resolution!r} not in {root}; it has "
                              f"{sorted(f'{w}x{h}' for w, h in found)}")
    dirs = sorted(found[size])
    if len(dirs) > 1:
        raise FormatError(f"{root}: several {size[0]}x{size[1]} image folders {[d.name for d in dirs]}")
    return dirs[0], size[0], size[1]


def _find_camera_file(root: Path, w: int, h: int) -> Path:
    cands = sorted(p for p in root.iterdir()
                   if (m := CAMERA_FILE_RE.match(p.name)) and (int(m.group(1)), int(m.group(2))) == (w, h))
    if not cands:
        raise FormatError(f"{root}: no camera file camera_params_rectified_a=0_{w}x{h}.txt for the "
                          f"{w}x{h} images")
    if len(cands) > 1:
        raise FormatError(f"{root}: several {w}x{h} camera files {[p.name for p in cands]}")
    return cands[0]


def _find_gps_file(root: Path) -> Path:
    cands = sorted(p for p in root.glob("*_GPS.txt") if p.is_file())
    best = [p for p in cands if p.name.endswith("_all-sensors_GPS.txt")] or cands
    if not best:
        raise FormatError(f"{root}: no GPS log ({root.name}_all-sensors_GPS.txt)")
    if len(best) > 1:
        named = [p for p in best if p.name.startswith(root.name)]
        if len(named) != 1:
            raise FormatError(f"{root}: several GPS logs {[p.name for p in best]}")
        best = named
    return best[0]


def load_malaga(extract_dir: str | Path, frame: GeoFrame | None = None,
                config: MalagaConfig | Mapping | None = None, *, name: str | None = None) -> Sequence:
    """A lazy :class:`Sequence` of a Malaga Urban extract directory (see the module docstring).

    ``frame``: the map frame; default a :class:`GeoFrame` at the first GPS fix used (the log's first row
    with fix != 0). ``config``: a :class:`MalagaConfig` or a dict of its fields. Every pair's image size is
    checked here (from the JPEG headers); images are decoded when a frame is accessed."""
    if frame is not None and not isinstance(frame, GeoFrame):
        raise ConfigError(f"malaga frame: expected a satloc.geoframe.GeoFrame or None, got {type(frame).__name__}")
    if config is None:
        cfg = MalagaConfig()
    elif isinstance(config, MalagaConfig):
        cfg = config
    else:
        cfg = from_dict(MalagaConfig, config, "malaga config")
    root = Path(extract_dir)
    if not root.is_dir():
        raise FormatError(f"{root}: Malaga extract directory not found")
    image_dir, w, h = _choose_images(root, cfg.resolution)
    camera_file = _find_camera_file(root, w, h)
    camera = read_camera_params(camera_file, cfg.mount_height, cfg.pitch)
    if (camera.width, camera.height) != (w, h):
        raise FormatError(f"{camera_file}: resolution {camera.width}x{camera.height} does not match the "
                          f"{w}x{h} of {image_dir.name}")
    pairs = list_stereo_pairs(image_dir)
    for lf, rf in zip(pairs.left, pairs.right):
        ls, rs = jpeg_size(lf), jpeg_size(rf)
        if ls != rs:
            raise FormatError(f"{lf} is {ls[0]}x{ls[1]} but {rf} is {rs[0]}x{rs[1]}; expected a stereo pair "
                              f"of one size")
        if ls != (w, h):
            raise FormatError(f"{lf}: image is {ls[0]}x{ls[1]}, expected {w}x{h} (the folder name and "
                              f"{camera_file.name})")
    gps_file = _find_gps_file(root)
    gps = read_gps_log(gps_file)
    if frame is None:
        try:
            frame = GeoFrame(float(gps.lon[0]), float(gps.lat[0]))
        except ConfigError as e:
            raise FormatError(f"{gps_file} line {gps.lines[0]}: the first fix cannot be the map frame's origin "
                              f"({e})") from e
    fix_xy = frame.to_map(np.stack([gps.lon, gps.lat], axis=-1))
    poses = track_poses(gps.times, fix_xy, pairs.times, cfg.heading_window_m, cfg.min_step_m, cfg.max_gap_s)

    stamps = pairs.times - pairs.times[0]
    read = _PairReader(pairs.left, pairs.right, poses, stamps)
    meta = {
        "source": "malaga_urban",
        "geo_frame": frame.to_dict(),
        "extract": root.name,
        "extract_dir": str(root.resolve()),
        "image_dir": image_dir.name,
        "camera_file": camera_file.name,
        "gps_file": gps_file.name,
        "resolution": [w, h],
        "time_origin": pairs.stamps[0],
        "unpaired_skipped": pairs.unpaired,
        "frames_without_pose": int(np.isnan(poses).any(axis=1).sum()),
        "gps_fixes_used": int(len(gps.times)),
        "pose": "GPS antenna, linear in time; yaw: direction of travel over heading_window_m",
        "heading_window_m": cfg.heading_window_m,
        "mount_height_note": "estimate (undocumented height of the roof frame above the road)",
    }
    return Sequence.lazy(camera, poses, stamps, read, name=name or root.name, meta=meta)
