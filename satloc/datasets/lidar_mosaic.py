"""A satellite stand-in made from a KITTI raw drive itself: a bird's-eye mosaic of the drive's own ground
pixels, placed with its LiDAR, written as a GeoTIFF in the drive's :class:`~satloc.geoframe.GeoFrame`.

For trying ``satloc evaluate`` on a drive when no satellite image of it is at hand. **Caveat:** the map is
made from the same images the method then localizes (queries included), seen from the ground, so an
evaluation against it is a *self-consistency check* of the calibration, the georeferencing chain and the
pipeline, not a measure of localization against satellite imagery (no change of viewpoint, season, sensor,
or occluders seen from above; the mosaic only covers the road and what is near it).

How it is made (:func:`lidar_mosaic`), for each frame with LiDAR:

1. the LiDAR points in the left colour camera (image_02) are placed in the map with the frame's pose; the
   ground height ``z0`` is the median height of the points below 0.5 m;
2. pixels near (a 15 x 15 px neighbourhood of) a LiDAR point more than 0.3 m above ``z0`` (cars, walls,
   trees, poles) are left out;
3. every other pixel's ray is intersected with the plane ``z = z0``; those meeting it between 2 m and
   ``max_depth_m`` ahead (z-depth) add their colour to the map cell they fall in.

The colours are averaged per cell; small holes (within a 7 x 7 px closing of the covered cells) are
inpainted, the rest stays black. The map spans the bounding box of the drive's poses plus ``margin_m``, on a
grid of ``mpp`` metres aligned to multiples of ``mpp`` in the drive's frame (``load_kitti``'s default: the
first kept frame's OXTS position).

LiDAR read per frame (KITTI index ``k``, the first found):

* ``velodyne_points/data/<k:010d>.bin`` (a raw KITTI drive): float32 ``x y z reflectance`` per point in the
  Velodyne frame, moved into the left rectified colour camera with the date folder's calibration
  (:func:`satloc.datasets.kitti.velo_to_camera`: ``calib_velo_to_cam``, ``R_rect_00``, ``P_rect_02``'s
  translation) and projected with its intrinsics; points less than 1 m ahead or outside the image are dropped;
* ``proj_depth/velodyne/image_02/<k:010d>.npz`` (KITTI depth maps already projected into image_02, as in the
  KITTI depth benchmark and excerpts made from it): array ``velodyne_depth`` (H, W), z-depth in metres, 0
  where there is none.

Frames without either are left out; a drive where no frame has one is a :class:`ConfigError`.
"""
from __future__ import annotations

import hashlib
import math
import os
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FormatError
from ..geoframe import GeoFrame
from ..persist import header, read_json, write_json
from .kitti import load_kitti, velo_to_camera

#: the sources of LiDAR depth read, relative to the drive folder, in the order they are tried
VELODYNE_BIN = ("velodyne_points", "data")
PROJECTED_NPZ = ("proj_depth", "velodyne", "image_02")
RECORD_FORMAT = "lidar_mosaic"
#: bump when the way the mosaic is made changes, so a saved one is made again
ALGORITHM_VERSION = 1
MIN_DEPTH_M = 2.0        # ground rays nearer than this are left out (the bonnet, the LiDAR's blind zone)
ABOVE_GROUND_M = 0.3     # a LiDAR point this high above the ground marks an obstacle ...
OBSTACLE_PX = 15         # ... and the pixels within this neighbourhood of it are left out
MAX_PIXELS = 150e6       # the largest mosaic made (e.g. 2.4 x 2.4 km at 0.2 m/px)


def lidar_file(drive: str | os.PathLike, index: int) -> Path | None:
    """The LiDAR file of KITTI frame ``index`` of ``drive`` (see the module docstring), or None."""
    drive = Path(drive)
    for parts, ext in ((VELODYNE_BIN, "bin"), (PROJECTED_NPZ, "npz")):
        p = drive.joinpath(*parts, f"{index:010d}.{ext}")
        if p.is_file():
            return p
    return None


def _no_lidar(drive: Path, n: int) -> ConfigError:
    return ConfigError(
        f"{drive}: no LiDAR for any of its {n} frames; a LiDAR mosaic needs "
        f"{Path(*VELODYNE_BIN, '<index>.bin')} (a raw KITTI drive's Velodyne scans, with the date folder's "
        f"calib_velo_to_cam.txt) or {Path(*PROJECTED_NPZ, '<index>.npz')} (projected depth maps) in the drive "
        f"folder; give a georeferenced satellite image instead")


def read_velodyne(path: str | os.PathLike) -> np.ndarray:
    """(N, 4) float32 ``x y z reflectance`` of a KITTI ``velodyne_points/data/*.bin`` scan."""
    path = Path(path)
    try:
        raw = np.fromfile(path, dtype="<f4")
    except OSError as e:
        raise FormatError(f"{path}: not readable ({e})") from e
    if raw.size % 4:
        raise FormatError(f"{path}: {raw.size * 4} bytes, not a whole number of 16-byte points "
                          f"(float32 x y z reflectance)")
    return raw.reshape(-1, 4)


def _lidar_pixels(path: Path, cam, velo_to_cam: Callable[[], np.ndarray]) -> tuple[np.ndarray, np.ndarray,
                                                                                    np.ndarray]:
    """(pixel (N, 2) float, flat pixel index (N,), z-depth (N,)) of a frame's LiDAR points in the left image."""
    w, h = cam.width, cam.height
    if path.suffix == ".bin":
        pts = read_velodyne(path)[:, :3].astype(np.float64)
        t = velo_to_cam()
        pc = pts @ t[:3, :3].T + t[:3, 3]
        pc = pc[np.all(np.isfinite(pc), axis=1) & (pc[:, 2] > 1.0)]
        uv, z = cam.project(pc)
        col, row = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        return uv[ok], row[ok] * w + col[ok], z[ok]
    try:
        with np.load(path) as f:
            depth = np.asarray(f["velodyne_depth"], dtype=np.float64)
    except KeyError as e:
        raise FormatError(f"{path}: no 'velodyne_depth' array (a projected KITTI depth map)") from e
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise FormatError(f"{path}: not a readable .npz ({e})") from e
    if depth.shape != (h, w):
        raise FormatError(f"{path}: velodyne_depth is {depth.shape}, expected (H, W) = ({h}, {w}) of image_02")
    depth = depth.reshape(-1)
    idx = np.flatnonzero(np.isfinite(depth) & (depth > 0))
    uv = np.stack([idx % w, idx // w], axis=1).astype(np.float64)
    return uv, idx, depth[idx]


def _grid(poses: np.ndarray, mpp: float, margin_m: float) -> tuple[float, float, int, int]:
    """(x0, y1, width, height) of the map: the poses' bounding box plus ``margin_m``, on multiples of ``mpp``."""
    xy = poses[np.all(np.isfinite(poses), axis=1), :2]
    x0, y0 = (math.floor((xy[:, k].min() - margin_m) / mpp) * mpp for k in (0, 1))
    x1, y1 = (math.ceil((xy[:, k].max() + margin_m) / mpp) * mpp for k in (0, 1))
    return x0, y1, round((x1 - x0) / mpp), round((y1 - y0) / mpp)


def _check(mpp, margin_m, max_depth_m) -> None:
    for name, v, ok, what in (("mpp", mpp, lambda v: v > 0, "a positive number of metres per pixel"),
                              ("margin_m", margin_m, lambda v: v >= 0, "a non-negative number of metres"),
                              ("max_depth_m", max_depth_m, lambda v: v > MIN_DEPTH_M,
                               f"a number of metres above {MIN_DEPTH_M:g}")):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and ok(v)):
            raise ConfigError(f"lidar mosaic {name}: expected {what}, got {v!r}")


def _build(drive: Path, path: Path, mpp: float, margin_m: float, max_depth_m: float, log) -> dict:
    import cv2
    from affine import Affine

    from ..geodata.georef import write_geotiff

    _check(mpp, margin_m, max_depth_m)
    seq = load_kitti(drive)
    frame, cam = GeoFrame.from_dict(seq.meta["geo_frame"]), seq.camera
    indices = seq.meta["kitti_indices"]
    files = [lidar_file(drive, k) for k in indices]
    if not any(files):
        raise _no_lidar(drive, len(indices))
    x0, y1, w, h = _grid(seq.poses, mpp, margin_m)
    if w * h > MAX_PIXELS:   # about 25 bytes a pixel while it is made
        raise ConfigError(f"lidar mosaic of {drive}: {w} x {h} px at {mpp:g} m/px over the drive plus {margin_m:g} m "
                          f"is more than {MAX_PIXELS / 1e6:g} Mpx; use a larger mpp or a smaller margin_m")
    acc, cnt = np.zeros((h, w, 3), np.float32), np.zeros((h, w), np.int32)   # integer sums: exact in float32
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([uu, vv], -1).reshape(-1, 2).astype(np.float64)
    rays_cam = cam.backproject(uv, np.ones(len(uv)))
    calib: list[np.ndarray] = []

    def velo() -> np.ndarray:   # the calibration, read once and only for a drive with Velodyne scans
        if not calib:
            calib.append(velo_to_camera(drive.parent, "color"))
        return calib[0]

    used, no_ground = [], []
    for i, (k, lidar) in enumerate(zip(indices, files)):
        if lidar is None:
            continue
        f = seq[i]
        luv, lidx, depth = _lidar_pixels(lidar, cam, velo)
        pts = cam.pixels_to_map(f.pose, luv, depth)
        ground = pts[pts[:, 2] < 0.5, 2]
        if len(ground) < 20:
            no_ground.append(int(k))
            continue
        z0 = float(np.median(ground))
        above = np.zeros(len(uv), np.uint8)
        above[lidx[pts[:, 2] - z0 > ABOVE_GROUND_M]] = 255
        above = cv2.dilate(above.reshape(cam.height, cam.width),
                           np.ones((OBSTACLE_PX, OBSTACLE_PX), np.uint8)).reshape(-1) > 0
        m = cam.map_from_camera(f.pose)
        rays = rays_cam @ m[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z0 - m[2, 3]) / rays[:, 2]                  # z-depth where the ray meets the ground plane
        keep = (t > MIN_DEPTH_M) & (t < max_depth_m) & ~above
        g = m[:3, 3] + rays[keep] * t[keep, None]
        px, py = np.floor((g[:, 0] - x0) / mpp).astype(np.int64), np.floor((y1 - g[:, 1]) / mpp).astype(np.int64)
        inb = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        np.add.at(acc, (py[inb], px[inb]), f.left.reshape(-1, 3)[keep][inb].astype(np.float32))
        np.add.at(cnt, (py[inb], px[inb]), 1)
        used.append(int(k))
    if not used:
        raise ConfigError(f"{drive}: none of the {len(indices)} frames' LiDAR scans has 20 points near the ground "
                          f"(below 0.5 m in the vehicle frame); check the calibration in {drive.parent}")
    img = np.zeros((h, w, 3), np.uint8)
    has = cnt > 0
    img[has] = np.clip(acc[has] / cnt[has, None], 0, 255).astype(np.uint8)
    del acc, cnt
    holes = ~has & cv2.morphologyEx(has.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8)).astype(bool)
    img = cv2.inpaint(img, holes.astype(np.uint8), 3, cv2.INPAINT_TELEA)
    write_geotiff(path, img, Affine(mpp, 0.0, x0, 0.0, -mpp, y1), frame.crs)
    covered = float(has.mean())
    if log is not None:
        log(f"lidar mosaic {path}: {w} x {h} px at {mpp:g} m/px from {len(used)} of {len(indices)} frames of "
            f"{drive.name}; {100 * covered:.1f} % of it covered")
    return {"covered_fraction": covered, "size_px": [w, h], "frames_used": used,
            "frames_without_lidar": [int(k) for k, p in zip(indices, files) if p is None],
            "frames_without_ground": no_ground,
            "lidar": sorted({str(Path(*p.relative_to(drive).parts[:-1])) for p in files if p is not None})}


def lidar_mosaic(drive: str | os.PathLike, path: str | os.PathLike, mpp: float = 0.2, margin_m: float = 80.0,
                 max_depth_m: float = 25.0, log: Callable[[str], None] | None = None) -> float:
    """Write the LiDAR mosaic of the KITTI raw drive folder ``drive`` (``<date>/<date>_drive_<nnnn>_sync``,
    its colour images and OXTS read with :func:`satloc.datasets.load_kitti`) to ``path`` (a GeoTIFF in the
    drive's frame, written atomically) at ``mpp`` metres per pixel over the drive's poses plus ``margin_m``,
    with ground pixels up to ``max_depth_m`` ahead (see the module docstring). Returns the fraction of the
    map's cells that frames covered. :class:`ConfigError` naming the folder when no frame has LiDAR."""
    return _build(Path(drive).resolve(), Path(path), mpp, margin_m, max_depth_m, log)["covered_fraction"]


def _inputs(drive: Path, mpp: float, margin_m: float, max_depth_m: float) -> dict:
    """What a mosaic is made from: the drive, its frames, the size and time of every file read, the settings."""
    seq = load_kitti(drive)
    indices = seq.meta["kitti_indices"]
    read = [drive.parent / f"calib_{c}.txt" for c in ("cam_to_cam", "imu_to_velo", "velo_to_cam")]
    read += [drive / "image_02" / "timestamps.txt"]
    for k in indices:
        read += [drive / "image_02" / "data" / f"{k:010d}.png", drive / "oxts" / "data" / f"{k:010d}.txt"]
        lidar = lidar_file(drive, k)
        if lidar is not None:
            read.append(lidar)
    h = hashlib.sha1()
    for f in read:
        st = f.stat() if f.exists() else None
        h.update(f"{f.relative_to(drive.parent)}\0{st and st.st_size}\0{st and st.st_mtime_ns}\n".encode())
    return {"drive": str(drive), "frames": [int(k) for k in indices], "files": {"count": len(read),
            "sha1": h.hexdigest()}, "mpp": mpp, "margin_m": margin_m, "max_depth_m": max_depth_m,
            "algorithm": ALGORITHM_VERSION}


def _image_stamp(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def record_path(path: str | os.PathLike) -> Path:
    """The JSON record kept beside a mosaic ``path`` by :func:`ensure_lidar_mosaic`."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def ensure_lidar_mosaic(drive: str | os.PathLike, path: str | os.PathLike, mpp: float = 0.2,
                        margin_m: float = 80.0, max_depth_m: float = 25.0,
                        log: Callable[[str], None] | None = None) -> dict:
    """:func:`lidar_mosaic` into ``path`` unless ``path`` holds one made from the same drive (the same files,
    unchanged) with the same settings, as its record ``<path>.json`` says. Returns the record: ``inputs``,
    ``covered_fraction``, the frames used, ``reused`` (whether this call kept the existing mosaic)."""
    drive, path = Path(drive).resolve(), Path(path)
    _check(mpp, margin_m, max_depth_m)
    inputs = _inputs(drive, mpp, margin_m, max_depth_m)
    rec_path = record_path(path)
    if path.is_file() and rec_path.is_file():
        try:
            old = read_json(rec_path, RECORD_FORMAT)
        except FormatError:
            old = {}
        if old.get("inputs") == inputs and old.get("image") == _image_stamp(path):
            if log is not None:
                log(f"lidar mosaic {path}: reused (made from the same files of {drive.name})")
            return dict(old, reused=True)
    rec_path.unlink(missing_ok=True)   # a mosaic without its record is never taken for a finished one
    made = _build(drive, path, mpp, margin_m, max_depth_m, log)
    rec = {**header(RECORD_FORMAT), "inputs": inputs, **made, "image": _image_stamp(path)}
    write_json(rec_path, rec)
    return dict(rec, reused=False)
