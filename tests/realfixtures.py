"""The real KITTI excerpt in ../shared/realdata (non-commercial: read from there, never copied into the project;
tests using it skip when it is absent) and what the tests make from it."""
import math
from pathlib import Path

import cv2
import numpy as np

from satloc.geoframe import GeoFrame
from satloc.georef import write_geotiff

REAL = (Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kitti_raw_2011_09_26_drive_0023_7frames"
        / "2011_09_26" / "2011_09_26_drive_0023_sync")


def lidar_mosaic(drive: Path, path: Path, mpp: float = 0.2, margin_m: float = 80.0, max_depth_m: float = 25.0):
    """A satellite stand-in for a KITTI drive, georeferenced in the drive's GeoFrame as a GeoTIFF: each frame's
    left-image pixels projected onto the ground plane (its height from the frame's LiDAR points, 2-25 m ahead),
    leaving out pixels near LiDAR points more than 0.3 m above it (cars, walls, trees), averaged over frames."""
    from affine import Affine

    from satloc.datasets import load_kitti

    seq = load_kitti(drive)
    frame, cam = GeoFrame.from_dict(seq.meta["geo_frame"]), seq.camera
    xy = seq.poses[:, :2]
    x0, y0 = (math.floor((xy[:, k].min() - margin_m) / mpp) * mpp for k in (0, 1))
    x1, y1 = (math.ceil((xy[:, k].max() + margin_m) / mpp) * mpp for k in (0, 1))
    w, h = int(round((x1 - x0) / mpp)), int(round((y1 - y0) / mpp))
    acc, cnt = np.zeros((h, w, 3)), np.zeros((h, w))
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([uu, vv], -1).reshape(-1, 2).astype(np.float64)
    for i, k in enumerate(seq.meta["kitti_indices"]):
        f = seq[i]
        lidar = np.load(drive / "proj_depth" / "velodyne" / "image_02" / f"{k:010d}.npz")["velodyne_depth"].reshape(-1)
        ok = np.flatnonzero(lidar > 0)
        pts = cam.pixels_to_map(f.pose, uv[ok], lidar[ok])
        z0 = float(np.median(pts[pts[:, 2] < 0.5, 2]))
        above = np.zeros(len(uv), np.uint8)
        above[ok[pts[:, 2] - z0 > 0.3]] = 255
        above = cv2.dilate(above.reshape(cam.height, cam.width), np.ones((15, 15), np.uint8)).reshape(-1) > 0
        m = cam.map_from_camera(f.pose)
        rays = cam.backproject(uv, np.ones(len(uv))) @ m[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (z0 - m[2, 3]) / rays[:, 2]                  # z-depth where the ray meets the ground plane
        keep = (t > 2.0) & (t < max_depth_m) & ~above
        g = m[:3, 3] + rays[keep] * t[keep, None]
        px, py = np.floor((g[:, 0] - x0) / mpp).astype(int), np.floor((y1 - g[:, 1]) / mpp).astype(int)
        inb = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        np.add.at(acc, (py[inb], px[inb]), f.left.reshape(-1, 3)[keep][inb].astype(np.float64))
        np.add.at(cnt, (py[inb], px[inb]), 1)
    img = np.zeros((h, w, 3), np.uint8)
    has = cnt > 0
    img[has] = np.clip(acc[has] / cnt[has, None], 0, 255).astype(np.uint8)
    holes = ~has & cv2.morphologyEx(has.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8)).astype(bool)
    img = cv2.inpaint(img, holes.astype(np.uint8), 3, cv2.INPAINT_TELEA)
    write_geotiff(path, img, Affine(mpp, 0.0, x0, 0.0, -mpp, y1), frame.crs)
    return float(has.mean())
