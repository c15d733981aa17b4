"""KITTI raw ("synced + rectified") drives in their original layout, read as a lazy :class:`Sequence`.

Layout read (Geiger, Lenz, Stiller, Urtasun, "Vision meets Robotics: The KITTI Dataset", IJRR 2013, and the
raw data development kit)::

    <date>/calib_cam_to_cam.txt      S_rect_0x, R_rect_00, P_rect_0x (rectified cameras 0-3)
    <date>/calib_imu_to_velo.txt     R, T: IMU (OXTS) frame -> Velodyne frame
    <date>/calib_velo_to_cam.txt     R, T: Velodyne frame -> unrectified camera 0
    <date>/<date>_drive_<nnnn>_sync/
        image_02/data/0000000000.png, image_03/...   rectified colour pair (image_00/01: grey pair)
        image_0x/timestamps.txt                       one ``YYYY-MM-DD HH:MM:SS.nnnnnnnnn`` line per frame
        oxts/data/0000000000.txt                      one line of 30 numbers per frame (oxts/dataformat.txt)
        oxts/timestamps.txt

Frame ``i`` of every stream is line ``i`` (0-based) of its ``timestamps.txt`` and file ``{i:010d}`` of its
``data`` folder. An excerpt of a drive (timestamps for the whole drive, data files for some frames) is a
valid input: ``missing="skip"`` keeps the frames whose left image, right image and OXTS line all exist and
records their KITTI indices in ``meta["kitti_indices"]``; ``missing="error"`` names the first absent file.

**Camera.** fx, fy, cx, cy from the left rectified projection matrix ``P_rect_02`` (``P_rect_00`` for grey),
the image size from ``S_rect_02``. ``P_rect_0x = K [I | t_x]`` in the rectified camera-0 frame, so the
centre of rectified camera x lies at ``-t_x = -K⁻¹ P_rect_0x[:, 3]`` and the baseline is
``t_left.x - t_right.x`` (0.533 m on 2011_09_26, not the nominal 0.54 m).

**Mounting.** The chain IMU -> Velodyne (``calib_imu_to_velo``) -> camera 0 (``calib_velo_to_cam``) ->
rectified camera 0 (``R_rect_00``) -> rectified left camera (translation ``t_left``) places the left
camera in the IMU frame (x forward, y left, z up). The IMU's height above the ground is not in the
calibration files; it comes from KITTI's published sensor setup (cvlibs.net/datasets/kitti/setup.php and
Fig. 3 of the IJRR paper: GPS/IMU 0.93 m above the ground, cameras 1.65 m, Velodyne 1.73 m), overridable
with ``imu_height``. The camera's rotation in the IMU frame is split as yaw (about up) · pitch (about left,
positive down) · roll (about the optical axis):

* ``mount_height`` = IMU height + the camera's z in the IMU frame (1.659 m on 2011_09_26);
* ``pitch`` = the optical axis' angle below the IMU's horizontal plane (-0.48 deg on 2011_09_26, i.e. up);
* the **yaw** of the optical axis from the IMU's x axis (+0.059 deg on 2011_09_26) is not lost: the
  vehicle frame is aligned with the camera's heading, so it is added to every pose's yaw;
* the **roll** about the optical axis (-0.244 deg on 2011_09_26) is dropped: :class:`StereoCamera` has
  none. Also dropped are the per-frame OXTS roll and pitch of the vehicle (the camera is taken level with
  the ground plane below it, as in the simulator) and the OXTS altitude.

**Poses.** The OXTS lat/lon are projected through a :class:`GeoFrame` (default: ``GeoFrame(lon, lat)`` of
the first frame kept, the devkit's Mercator at the first frame's latitude); the OXTS heading ``yaw``
(0 = east, counter-clockwise: the map convention) plus the camera's yaw offset is the pose's yaw; the
position is that of the vehicle frame, on the ground below the left camera: the IMU position plus the
IMU -> left-camera offset rotated by the IMU heading in the horizontal plane. A synced frame's OXTS
timestamp differs from its images' by a few ms (6.6 ms for frame 0 of drive 0023, i.e. 6 cm at 9.4 m/s);
positions are not interpolated to the image time. On drive 0023 the steps between
frames alternate between 0.89 and 0.98 m (mean 0.94 m) while the image stamps are 0.104 s apart.

**Timestamps** are the left image stream's, in seconds (float64) from the first frame kept; the absolute
time of that frame is ``meta["time_origin"]``.

**Odometry** from the OXTS motion sensors (forward speed and yaw rate integrated between frames, not the
positions): :func:`oxts_odometry`, in the convention of :func:`satloc.tracking.track.relative_motion`.
"""
from __future__ import annotations

import math
import os
import re
import struct
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FormatError
from ..geoframe import GeoFrame
from ..geometry import Pose2, StereoCamera, wrap_angle
from ..satmap import read_image
from ..sequence import Frame, Sequence, check_camera_ranges

IMU_HEIGHT_M = 0.93  # GPS/IMU above the ground, KITTI sensor setup (setup.php; IJRR 2013 Fig. 3)

OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az", "af", "al",
    "au", "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy", "navstat", "numsats",
    "posmode", "velmode", "orimode",
)

CAMERAS = {"color": ("02", "03"), "gray": ("00", "01")}  # (left, right) camera numbers
MISSING = ("skip", "error")

_STAMP = re.compile(r"^(\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2})(?:\.(\d{1,9}))?$")
_INDEXED = re.compile(r"^(\d{10})\.(png|txt)$")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# camera axes (x right, y down, z forward) in a level vehicle-like frame (x forward, y left, z up)
_CAM_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class KittiRig:
    """The rectified stereo pair of one KITTI date, placed on the vehicle (see the module docstring).

    ``camera_in_imu``: the left rectified camera's centre in the IMU frame (x forward, y left, z up), m;
    ``yaw``: its optical axis' heading from the IMU's x axis (rad, counter-clockwise; added to poses);
    ``roll``: its rotation about the optical axis (rad; dropped from the :class:`StereoCamera`);
    ``imu_from_camera``: the full 4x4 transform taking left-camera points to the IMU frame."""

    camera: StereoCamera
    camera_in_imu: tuple[float, float, float]
    yaw: float
    roll: float
    imu_height: float
    imu_from_camera: tuple[tuple[float, ...], ...]

    def to_dict(self) -> dict:
        return {"camera_in_imu_m": list(self.camera_in_imu), "camera_yaw_rad": self.yaw,
                "camera_roll_rad_dropped": self.roll, "imu_height_m": self.imu_height,
                "mount_height_m": self.camera.mount_height, "pitch_rad": self.camera.pitch,
                "baseline_m": self.camera.baseline}


# --- calibration -----------------------------------------------------------------------------------------

def _read_text(path: Path, what: str) -> str:
    """The text of a ``what`` file; FormatError naming it when it is missing or unreadable."""
    try:
        return path.read_text()
    except FileNotFoundError as e:
        raise FormatError(f"{path}: {what} file not found") from e
    except (OSError, UnicodeDecodeError) as e:
        raise FormatError(f"{path}: not a readable text file ({e})") from e


def read_calib_file(path: str | os.PathLike) -> dict[str, tuple[int, str]]:
    """``key: values`` lines of a KITTI calibration file as {key: (line number, raw value text)}."""
    path = Path(path)
    text = _read_text(path, "calibration")
    out: dict[str, tuple[int, str]] = {}
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        if not sep or not key.strip():
            raise FormatError(f"{path} line {n}: expected 'key: values', got {line[:60]!r}")
        out[key.strip()] = (n, value)
    return out


def calib_values(calib: dict, path, key: str, count: int) -> np.ndarray:
    """The ``count`` numbers of ``key`` in a file read by :func:`read_calib_file`."""
    if key not in calib:
        raise FormatError(f"{path}: no '{key}:' line (expected {count} numbers)")
    n, value = calib[key]
    try:
        vals = np.array([float(v) for v in value.split()], dtype=np.float64)
    except ValueError as e:
        raise FormatError(f"{path} line {n} ({key}): expected {count} numbers, got {value.strip()[:60]!r}") from e
    if vals.shape != (count,):
        raise FormatError(f"{path} line {n} ({key}): expected {count} numbers, got {vals.size}")
    if not np.all(np.isfinite(vals)):
        raise FormatError(f"{path} line {n} ({key}): expected finite numbers, got {value.strip()[:60]!r}")
    return vals


def _rotation(calib, path, key: str) -> np.ndarray:
    r = calib_values(calib, path, key, 9).reshape(3, 3)
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0:
        raise FormatError(f"{path} line {calib[key][0]} ({key}): expected a rotation matrix "
                          f"(orthonormal, det +1), got {r.ravel().tolist()}")
    return r


def _rigid(calib, path) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = _rotation(calib, path, "R")
    t[:3, 3] = calib_values(calib, path, "T", 3)
    return t


def _projection(calib, path, cam: str) -> tuple[np.ndarray, np.ndarray]:
    """(K, t) of ``P_rect_<cam> = K [I | t]``."""
    key = f"P_rect_{cam}"
    p = calib_values(calib, path, key, 12).reshape(3, 4)
    k = p[:, :3]
    if not (k[0, 0] > 0 and k[1, 1] > 0 and k[1, 0] == 0 and k[2, 0] == 0 and k[2, 1] == 0 and k[2, 2] == 1):
        raise FormatError(f"{path} line {calib[key][0]} ({key}): expected a rectified projection matrix "
                          f"[fx 0 cx tx; 0 fy cy ty; 0 0 1 tz] with fx, fy > 0, got {p.ravel().tolist()}")
    return k, np.linalg.solve(k, p[:, 3])


def _camera_from_velo(cc: dict, cam_path: Path, t_left: np.ndarray, vc_path: Path) -> np.ndarray:
    """4x4: Velodyne frame -> camera 0 (``calib_velo_to_cam``) -> rectified camera 0 (``R_rect_00``) -> the
    rectified left camera (its translation ``t_left`` from ``P_rect``)."""
    rect = np.eye(4)
    rect[:3, :3] = _rotation(cc, cam_path, "R_rect_00")
    shift = np.eye(4)
    shift[:3, 3] = t_left
    return shift @ rect @ _rigid(read_calib_file(vc_path), vc_path)


def velo_to_camera(date_dir: str | os.PathLike, camera: str = "color") -> np.ndarray:
    """The 4x4 transform taking Velodyne points (``velodyne_points/data/*.bin``, metres) into the left rectified
    camera of ``camera`` (x right, y down, z forward; ``"color"``: camera 2), from a date folder's
    ``calib_velo_to_cam.txt`` and ``calib_cam_to_cam.txt`` (``R_rect_00``, ``P_rect_0x``): the devkit's chain
    ``P_rect_0x @ R_rect_00 @ Tr_velo_to_cam`` without the intrinsics."""
    if camera not in CAMERAS:
        raise ConfigError(f"kitti camera: expected one of {sorted(CAMERAS)}, got {camera!r}")
    date_dir = Path(date_dir)
    cam_path = date_dir / "calib_cam_to_cam.txt"
    cc = read_calib_file(cam_path)
    _, t_left = _projection(cc, cam_path, CAMERAS[camera][0])
    return _camera_from_velo(cc, cam_path, t_left, date_dir / "calib_velo_to_cam.txt")


def read_rig(date_dir: str | os.PathLike, camera: str = "color", imu_height: float = IMU_HEIGHT_M) -> KittiRig:
    """The rectified stereo rig (``camera`` ``"color"``: cameras 2/3, ``"gray"``: 0/1) from a date folder's
    three calibration files, mounted ``imu_height`` metres above the IMU's ground point."""
    if camera not in CAMERAS:
        raise ConfigError(f"kitti camera: expected one of {sorted(CAMERAS)}, got {camera!r}")
    if isinstance(imu_height, bool) or not isinstance(imu_height, (int, float)) or not (
            math.isfinite(imu_height) and 0 < imu_height < 10):
        raise ConfigError(f"kitti imu_height: expected metres in (0, 10), got {imu_height!r}")
    date_dir = Path(date_dir)
    left, right = CAMERAS[camera]
    cam_path = date_dir / "calib_cam_to_cam.txt"
    iv_path = date_dir / "calib_imu_to_velo.txt"
    vc_path = date_dir / "calib_velo_to_cam.txt"
    cc = read_calib_file(cam_path)
    k_l, t_l = _projection(cc, cam_path, left)
    k_r, t_r = _projection(cc, cam_path, right)
    if not np.allclose(k_l, k_r, rtol=1e-6, atol=1e-9):
        raise FormatError(f"{cam_path}: P_rect_{left} and P_rect_{right} have different intrinsics "
                          f"({k_l.ravel().tolist()} and {k_r.ravel().tolist()}); expected a rectified pair")
    baseline = float(t_l[0] - t_r[0])
    if not baseline > 0:
        raise FormatError(f"{cam_path} line {cc[f'P_rect_{right}'][0]} (P_rect_{right}): the right camera is not "
                          f"to the right of the left one (baseline {baseline:.4f} m)")
    size = calib_values(cc, cam_path, f"S_rect_{left}", 2)
    if not np.all((size >= 1) & (size == np.round(size))):
        raise FormatError(f"{cam_path} line {cc[f'S_rect_{left}'][0]} (S_rect_{left}): expected a positive "
                          f"integer width and height, got {size.tolist()}")
    cam_from_imu = _camera_from_velo(cc, cam_path, t_l, vc_path) @ _rigid(read_calib_file(iv_path), iv_path)
    try:
        with np.errstate(all="ignore"):
            imu_from_cam = np.linalg.inv(cam_from_imu)
    except np.linalg.LinAlgError:
        imu_from_cam = np.full((4, 4), np.nan)  # refused below, naming the files
    centre = imu_from_cam[:3, 3]
    # rotation of the camera in the IMU frame = Rz(yaw) Ry(pitch) Rx(roll) _CAM_AXES
    m = imu_from_cam[:3, :3] @ _CAM_AXES.T
    yaw = math.atan2(m[1, 0], m[0, 0])
    pitch = math.asin(float(np.clip(-m[2, 0], -1.0, 1.0)))
    roll = math.atan2(m[2, 1], m[2, 2])
    height = float(centre[2] + imu_height)
    if not (np.isfinite(imu_from_cam).all() and 0 < height < 10 and abs(pitch) < math.pi / 2):
        raise FormatError(f"{cam_path}, {vc_path}, {iv_path}: the calibration chain puts the left camera "
                          f"{height:.4g} m above the ground (with the IMU {imu_height} m high) and pitches it "
                          f"{math.degrees(pitch):.3g} degrees; expected a height in (0, 10) m and a pitch within "
                          f"+-90 degrees")
    cam = check_camera_ranges(StereoCamera(int(size[0]), int(size[1]), float(k_l[0, 0]), float(k_l[1, 1]),
                                           float(k_l[0, 2]), float(k_l[1, 2]), baseline, height, pitch),
                              f"{cam_path}: the camera")
    return KittiRig(cam, tuple(float(v) for v in centre), yaw, roll, float(imu_height),
                    tuple(tuple(float(v) for v in row) for row in imu_from_cam))


# --- per-frame files -------------------------------------------------------------------------------------

def read_oxts_file(path: str | os.PathLike) -> np.ndarray:
    """The 30 numbers (:data:`OXTS_FIELDS`) of one OXTS data file."""
    path = Path(path)
    text = _read_text(path, "OXTS")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise FormatError(f"{path} line 1: expected {len(OXTS_FIELDS)} numbers ({' '.join(OXTS_FIELDS[:3])} ...), "
                          f"the file is empty")
    if len(lines) > 1:
        raise FormatError(f"{path} line 2: expected one line of {len(OXTS_FIELDS)} numbers, found {len(lines)} lines")
    words = lines[0].split()
    if len(words) != len(OXTS_FIELDS):
        raise FormatError(f"{path} line 1: expected {len(OXTS_FIELDS)} numbers ({' '.join(OXTS_FIELDS[:3])} ... "
                          f"{OXTS_FIELDS[-1]}), got {len(words)}")
    vals = np.empty(len(words), np.float64)
    for j, w in enumerate(words):
        try:
            vals[j] = float(w)
        except ValueError:
            raise FormatError(f"{path} line 1, field {j + 1} ({OXTS_FIELDS[j]}): expected a number, got {w!r}") from None
    for j in (0, 1, 5):  # lat, lon, yaw: what a pose needs
        if not math.isfinite(vals[j]):
            raise FormatError(f"{path} line 1, field {j + 1} ({OXTS_FIELDS[j]}): expected a finite number, "
                              f"got {words[j]!r}")
    if not (-90 <= vals[0] <= 90 and -180 <= vals[1] <= 180):
        raise FormatError(f"{path} line 1: expected lat in [-90, 90] and lon in [-180, 180] degrees, "
                          f"got {vals[0]}, {vals[1]}")
    return vals


def read_timestamps(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A KITTI ``timestamps.txt``: (whole seconds since 1970 (int64), nanoseconds (int64), the lines)."""
    path = Path(path)
    text = _read_text(path, "timestamps")
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    secs = np.empty(len(lines), np.int64)
    nanos = np.empty(len(lines), np.int64)
    for n, line in enumerate(lines):
        m = _STAMP.match(line.strip())
        when = None
        if m:
            try:
                when = datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc)
            except ValueError:
                pass
        if when is None:
            raise FormatError(f"{path} line {n + 1}: expected a timestamp 'YYYY-MM-DD HH:MM:SS.nnnnnnnnn', "
                              f"got {line[:60]!r}")
        secs[n] = int(when.timestamp())
        nanos[n] = int((m.group(2) or "0").ljust(9, "0"))
    return secs, nanos, [ln.strip() for ln in lines]


def png_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) from a PNG file's header."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError as e:
        raise FormatError(f"{path}: image file not readable ({e})") from e
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise FormatError(f"{path}: not a PNG image")
    return struct.unpack(">II", head[16:24])


def _indexed_files(folder: Path, ext: str) -> set[int]:
    if not folder.is_dir():
        return set()
    out = set()
    for name in os.listdir(folder):
        m = _INDEXED.match(name)
        if m and m.group(2) == ext:
            out.add(int(m.group(1)))
    return out


class _FrameReader:
    """Reads kept frame ``j`` of a drive (a plain object, so a sequence can be pickled to a worker)."""

    def __init__(self, width: int, height: int, left: list[Path], right: list[Path], poses: np.ndarray,
                 stamps: np.ndarray):
        self.size, self.left, self.right, self.poses, self.stamps = (width, height), left, right, poses, stamps

    def __call__(self, j: int) -> Frame:
        imgs = []
        for path in (self.left[j], self.right[j]):
            img = read_image(path)
            if img.shape[1::-1] != self.size:
                raise FormatError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected "
                                  f"{self.size[0]}x{self.size[1]}")
            imgs.append(img)
        return Frame(imgs[0], imgs[1], Pose2.from_array(self.poses[j]), float(self.stamps[j]))


# --- the drive -------------------------------------------------------------------------------------------

_DRIVE_LAYOUT = ("a KITTI raw drive folder <date>_drive_<nnnn>_sync holding oxts/ and image_{left}/ "
                 "(camera {camera!r}), with the calibration files ({calib}) one level up, in the date folder")


def check_drive_folder(drive: Path, camera: str = "color") -> None:
    """:class:`FormatError` saying what a drive folder must hold when ``drive`` has none of its streams (a date
    folder, a drive's parent, an empty folder: the drive folders inside are listed) or when its date folder
    lacks the calibration files. A drive with some streams missing is left to :func:`load_kitti`'s own checks,
    which name the missing file."""
    left = CAMERAS[camera][0]
    calib = ("calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt")
    layout = _DRIVE_LAYOUT.format(left=left, camera=camera, calib=", ".join(calib))
    if not any((drive / d).is_dir() for d in ("oxts", "image_00", "image_01", "image_02", "image_03")):
        found = sorted(str(d) for d in drive.glob("*_drive_*_sync") if d.is_dir())
        found += sorted(str(d) for d in drive.glob("*/*_drive_*_sync") if d.is_dir())
        hint = ("; drive folders here: " + ", ".join(found[:10]) + (" ..." if len(found) > 10 else "")) if found \
            else ""
        have = sorted(p.name + ("/" if p.is_dir() else "") for p in drive.iterdir())[:8]
        raise FormatError(f"{drive}: not a KITTI drive folder (it holds {', '.join(have) or 'nothing'}); expected "
                          f"{layout}{hint}")
    absent = [c for c in calib if not (drive.parent / c).is_file()]
    if absent:
        raise FormatError(f"{drive.parent / absent[0]}: calibration file not found; expected {layout} (a drive copied "
                          f"without its date folder's calibration files: copy {', '.join(absent)} beside it)")


def load_kitti(drive_dir: str | os.PathLike, frame: GeoFrame | None = None, *, camera: str = "color",
               missing: str = "skip", imu_height: float = IMU_HEIGHT_M, name: str | None = None) -> Sequence:
    """A KITTI raw synced drive ``<date>/<date>_drive_<nnnn>_sync`` as a lazy :class:`Sequence`.

    ``frame``: the map frame of the poses (default: ``GeoFrame`` at the first kept frame's OXTS lon/lat);
    ``camera``: ``"color"`` (image_02/03) or ``"gray"`` (image_00/01, read as 3-channel RGB);
    ``missing``: ``"skip"`` frames without a left image, right image or OXTS file, or ``"error"``;
    ``imu_height``: the IMU's height above the ground (m). See the module docstring for the conventions.
    Images are read when a frame is accessed; everything else is read and checked here."""
    if missing not in MISSING:
        raise ConfigError(f"kitti missing: expected one of {list(MISSING)}, got {missing!r}")
    if camera not in CAMERAS:
        raise ConfigError(f"kitti camera: expected one of {sorted(CAMERAS)}, got {camera!r}")
    if frame is not None and not isinstance(frame, GeoFrame):
        raise ConfigError(f"kitti frame: expected a satloc.geoframe.GeoFrame or None, got {type(frame).__name__}")
    drive = Path(drive_dir)
    if not drive.is_dir():
        raise FormatError(f"{drive}: KITTI drive directory not found")
    drive = drive.resolve()
    check_drive_folder(drive, camera)
    rig = read_rig(drive.parent, camera, imu_height)
    cam = rig.camera
    left_id, right_id = CAMERAS[camera]
    left_dir, right_dir = drive / f"image_{left_id}", drive / f"image_{right_id}"
    oxts_dir = drive / "oxts"

    stamp_path = left_dir / "timestamps.txt"
    secs, nanos, stamp_lines = read_timestamps(stamp_path)
    n = len(secs)
    if n == 0:
        raise FormatError(f"{stamp_path}: no timestamps (an empty drive)")
    for other in (right_dir / "timestamps.txt", oxts_dir / "timestamps.txt"):
        if other.is_file():
            m = len(read_timestamps(other)[0])
            if m != n:
                raise FormatError(f"{other}: {m} timestamps, {stamp_path} has {n}; a synced drive has one "
                                  f"line per frame in every stream")

    streams = [(left_dir / "data", "png"), (right_dir / "data", "png"), (oxts_dir / "data", "txt")]
    present = [_indexed_files(folder, ext) for folder, ext in streams]
    for (folder, ext), idx in zip(streams, present):
        extra = sorted(i for i in idx if i >= n)
        if extra:
            raise FormatError(f"{folder / f'{extra[0]:010d}.{ext}'}: frame {extra[0]} has no line in {stamp_path} "
                              f"({n} lines)")
    kept = []
    for i in range(n):
        absent = [folder / f"{i:010d}.{ext}" for (folder, ext), idx in zip(streams, present) if i not in idx]
        if not absent:
            kept.append(i)
        elif missing == "error":
            raise FormatError(f"{absent[0]}: missing (frame {i}, listed on line {i + 1} of {stamp_path})")
    if not kept:
        raise FormatError(f"{drive}: no frame has a left image ({streams[0][0]}), a right image ({streams[1][0]}) "
                          f"and an OXTS file ({streams[2][0]}); {n} frames listed in {stamp_path}")

    want = (cam.width, cam.height)
    left_files = [streams[0][0] / f"{i:010d}.png" for i in kept]
    right_files = [streams[1][0] / f"{i:010d}.png" for i in kept]
    for lf, rf in zip(left_files, right_files):
        ls, rs = png_size(lf), png_size(rf)
        if ls != rs:
            raise FormatError(f"{rf}: right image is {rs[0]}x{rs[1]}, the left image {lf.name} is {ls[0]}x{ls[1]}")
        if ls != want:
            raise FormatError(f"{lf}: image is {ls[0]}x{ls[1]}, expected {want[0]}x{want[1]} "
                              f"(S_rect_{left_id} in {drive.parent / 'calib_cam_to_cam.txt'})")

    oxts = np.stack([read_oxts_file(streams[2][0] / f"{i:010d}.txt") for i in kept])
    lat, lon, imu_yaw = oxts[:, 0], oxts[:, 1], oxts[:, 5]
    if frame is None:
        try:
            frame = GeoFrame(lon[0], lat[0])
        except ConfigError as e:
            first = streams[2][0] / f"{kept[0]:010d}.txt"
            raise FormatError(f"{first} line 1: the first frame's lat/lon cannot be the map frame's origin "
                              f"({e})") from e
    imu_xy = frame.to_map(np.stack([lon, lat], axis=1))
    ox, oy = rig.camera_in_imu[0], rig.camera_in_imu[1]
    c, s = np.cos(imu_yaw), np.sin(imu_yaw)
    poses = np.stack([imu_xy[:, 0] + c * ox - s * oy, imu_xy[:, 1] + s * ox + c * oy,
                      wrap_angle(imu_yaw + rig.yaw)], axis=1)

    k = np.asarray(kept)
    stamps = (secs[k] - secs[k[0]]).astype(np.float64) + (nanos[k] - nanos[k[0]]).astype(np.float64) * 1e-9

    meta = {
        "source": "kitti_raw",
        "drive": drive.name,
        "date": drive.parent.name,
        "drive_dir": str(drive),
        "camera": camera,
        "geo_frame": frame.to_dict(),
        "kitti_indices": [int(i) for i in kept],
        "num_listed": n,
        "time_origin": stamp_lines[kept[0]],
        "calibration": rig.to_dict(),
    }
    read = _FrameReader(cam.width, cam.height, left_files, right_files, poses, stamps)
    return Sequence.lazy(cam, poses, stamps, read, name=name or drive.name, meta=meta)


# --- odometry from the OXTS motion sensors ---------------------------------------------------------------

CLOCKS = ("image", "oxts")


def oxts_odometry(sequence: Sequence, clock: str = "image", max_gap_s: float = 0.5,
                  substeps: int = 20) -> np.ndarray:
    """(N, 3) odometry of a KITTI drive read by :func:`load_kitti` (or a view of it) from its OXTS motion
    sensors: row ``i`` is the motion (dx, dy, dyaw) from frame ``i - 1`` to frame ``i`` in frame ``i - 1``'s
    vehicle frame (the convention of :func:`satloc.tracking.track.relative_motion`), row 0 NaN. Positions are not used:
    this is the wheel-odometry-like signal a vehicle has, to compare with visual odometry and the OXTS poses.

    The IMU's forward speed ``vf`` (m/s, parallel to the ground) and yaw rate ``wu`` (rad/s, about its up axis)
    are read from every OXTS file of the drive from the first to the last frame (frames an excerpt skipped
    included, where their OXTS file exists; samples with a non-finite ``vf`` or ``wu`` left out), taken as
    linear in time between the samples' OXTS timestamps (held beyond the first and last), and integrated as a
    planar unicycle (``substeps`` midpoint steps per frame interval) between the frames' times:
    ``clock="image"``, the left images' timestamps (the motion between the captures), or ``"oxts"``, the
    frames' OXTS timestamps (the times the OXTS poses were sampled at; on drive 0023 those intervals alternate
    between about 0.10 and 0.11 s while the images' are 0.104 s). The IMU's motion is carried to the vehicle
    frame below the left camera through the rig (``meta["calibration"]``: the camera's offset and yaw in the
    IMU frame). An interval whose speeds would be interpolated between samples more than ``max_gap_s`` apart,
    or held more than ``max_gap_s`` beyond the first or last sample, is NaN.

    The leftward speed ``vl`` is not used: on drive 0023 it reads 0.07-0.10 m/s (a 0.5 degree side slip, 8 mm
    sideways a frame) while the OXTS positions move less than 3 mm sideways a frame.
    Measured there (6 steps, 5.6 m): the integrated speed covers 2.3 % less distance than the OXTS positions
    (both clocks within 0.4 % of each other over the excerpt) and the heading agrees within 0.03 degrees."""
    if clock not in CLOCKS:
        raise ConfigError(f"kitti odometry clock: expected one of {list(CLOCKS)}, got {clock!r}")
    if isinstance(max_gap_s, bool) or not isinstance(max_gap_s, (int, float)) or not max_gap_s > 0 \
            or isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ConfigError(f"kitti odometry: max_gap_s > 0 and an integer substeps >= 1 are required, got "
                          f"{max_gap_s!r}, {substeps!r}")
    meta = sequence.meta
    if meta.get("source") != "kitti_raw" or not all(k in meta for k in ("kitti_indices", "drive_dir", "calibration")):
        raise ConfigError(f"kitti odometry: sequence {sequence.name!r} was not read by load_kitti (its meta has no "
                          f"KITTI drive, frame indices and calibration)")
    kept = np.asarray(meta["kitti_indices"], np.int64)
    if "source_frames" in meta:   # a view (Sequence.view) of the drive
        kept = kept[np.asarray(meta["source_frames"], np.int64)]
    out = np.full((len(sequence), 3), np.nan)
    if len(kept) != len(sequence):
        raise ConfigError(f"kitti odometry: sequence {sequence.name!r} has {len(sequence)} frames, its meta names "
                          f"{len(kept)} KITTI frames")
    if len(kept) < 2:
        return out
    drive = Path(meta["drive_dir"])
    img_s, img_ns, _ = read_timestamps(drive / f"image_{CAMERAS[meta.get('camera', 'color')][0]}" / "timestamps.txt")
    ox_s, ox_ns, _ = read_timestamps(drive / "oxts" / "timestamps.txt")
    if kept.min() < 0 or kept.max() >= min(len(img_s), len(ox_s)):
        raise ConfigError(f"kitti odometry: sequence {sequence.name!r} names KITTI frames up to {kept.max()}, "
                          f"{drive} lists {min(len(img_s), len(ox_s))}")
    t_img = (img_s - img_s[kept[0]]).astype(np.float64) + (img_ns - img_ns[kept[0]]).astype(np.float64) * 1e-9
    t_ox = (ox_s - img_s[kept[0]]).astype(np.float64) + (ox_ns - img_ns[kept[0]]).astype(np.float64) * 1e-9
    if not np.allclose(t_img[kept] - t_img[kept[0]], sequence.timestamps - sequence.timestamps[0], atol=1e-6):
        raise ConfigError(f"kitti odometry: the timestamps of sequence {sequence.name!r} are not those of the "
                          f"{drive} frames its meta names")
    idx = np.array([i for i in range(int(kept.min()), int(kept.max()) + 1)
                    if (drive / "oxts" / "data" / f"{i:010d}.txt").is_file()], np.int64)
    rec = np.stack([read_oxts_file(drive / "oxts" / "data" / f"{i:010d}.txt") for i in idx])
    v, w = rec[:, OXTS_FIELDS.index("vf")], rec[:, OXTS_FIELDS.index("wu")]
    good = np.isfinite(v) & np.isfinite(w)
    ts, v, w = t_ox[idx[good]], v[good], w[good]
    times = t_img[kept] if clock == "image" else t_ox[kept]
    cal = meta["calibration"]
    rig = Pose2(cal["camera_in_imu_m"][0], cal["camera_in_imu_m"][1], cal["camera_yaw_rad"])  # vehicle in IMU frame
    rig_inv = rig.inverse()
    for i in range(1, len(kept)):
        a, b = times[i - 1], times[i]
        h = (b - a) / substeps
        tm = a + (np.arange(substeps) + 0.5) * h     # midpoints of the sub-steps
        if not b > a or not len(ts) or not _covered(np.concatenate([[a], tm, [b]]), ts, max_gap_s):
            continue
        vm, wm = np.interp(tm, ts, v), np.interp(tm, ts, w)
        yaw = np.concatenate([[0.0], np.cumsum(wm * h)])
        mid = 0.5 * (yaw[:-1] + yaw[1:])
        imu = Pose2(float(np.sum(vm * h * np.cos(mid))), float(np.sum(vm * h * np.sin(mid))), float(yaw[-1]))
        out[i] = (rig_inv @ imu @ rig).as_array()
    return out


def _covered(t: np.ndarray, samples: np.ndarray, max_gap_s: float) -> bool:
    """Whether every time ``t`` is a sample's time, lies between two ``samples`` (sorted) at most ``max_gap_s``
    apart, or lies within ``max_gap_s`` of the first or last sample beyond them."""
    j = np.searchsorted(samples, t)                      # samples[j - 1] < t <= samples[j]
    before = samples[np.clip(j - 1, 0, len(samples) - 1)]
    after = samples[np.clip(j, 0, len(samples) - 1)]
    gap = np.where(j == 0, after - t, np.where(j == len(samples), t - before, after - before))
    return bool(np.all((gap <= max_gap_s) | (after == t)))
