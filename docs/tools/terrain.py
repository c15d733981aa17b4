"""``city`` at variety 1 over gentle hills (``terrain: {relief_m: 1.5, wavelength_m: 250}``) against the plane.

    python docs/tools/terrain.py picture docs/images/terrain_city.jpg
    python docs/tools/terrain.py bev

``picture``: the left camera at three places of the loop, on the plane (left) and over the hills (right), the
car standing on the ground under its wheels. ``bev``: how far a flat-ground bird's-eye projection (level
ground in the plane of the car's wheels) puts the ground the camera sees over the hills: per frame (60 along
the loop), the median over its ground pixels (road, marking, sidewalk, parking) at 10, 20 and 30 m (+-2.5 m)
of the horizontal distance between where each pixel's ray meets that plane and where the ground is.
"""
import dataclasses
import sys

import cv2
import numpy as np

from satloc.geometry import StereoCamera
from satloc.labels import CLASS_ID
from satloc_env.render.stereo import StereoRenderer
from satloc_env.world.scene import TerrainSpec, build_scene, load_spec


def scenes():
    spec, base = load_spec("city")
    spec = dataclasses.replace(spec, generator={**spec.generator, "variety": 1.0})
    hills = dataclasses.replace(spec, terrain=TerrainSpec(relief_m=1.5, wavelength_m=250.0))
    return build_scene(spec, base), build_scene(hills, base)


def picture(out: str) -> None:
    rows = []
    for s in scenes():
        route = s.routes[s.spec.database_route]
        with StereoRenderer(s.world, StereoCamera.kitti_half()) as r:
            views = [r.render(route.pose_at(d, -1.75), depth=False)["left"] for d in (30.0, 150.0, 420.0)]
        rows.append(np.vstack(views))
    cv2.imwrite(out, cv2.cvtColor(np.hstack(rows), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])


def bev() -> None:
    s = scenes()[1]
    cam = StereoCamera.kitti_half()
    route = s.routes[s.spec.database_route]
    t_vc = cam.vehicle_from_camera("left")
    ground = [CLASS_ID[k] for k in ("road", "lane_marking", "sidewalk", "parking")]
    errors: dict[int, list[float]] = {10: [], 20: [], 30: []}
    with StereoRenderer(s.world, cam) as r:
        for d in np.linspace(5, route.length - 5, 60):
            out = r.render(route.pose_at(float(d), -1.75), depth=True, labels=True)
            v, u = np.nonzero(np.isin(out["labels_left"], ground) & (out["depth_left"] > 0))
            pc = cam.backproject(np.stack([u, v], 1).astype(np.float64), out["depth_left"][v, u].astype(np.float64))
            pv = pc @ t_vc[:3, :3].T + t_vc[:3, 3]                       # the ground, in the car's frame
            eye = t_vc[:3, 3]
            ray = pv - eye
            down = np.where(ray[:, 2] < -1e-6, ray[:, 2], np.nan)
            flat = eye + (-eye[2] / down)[:, None] * ray                   # where the ray meets z = 0
            err = np.linalg.norm(flat[:, :2] - pv[:, :2], axis=1)
            rng = np.linalg.norm(pv[:, :2], axis=1)
            for metres, acc in errors.items():
                m = (np.abs(rng - metres) < 2.5) & np.isfinite(err)
                if m.any():
                    acc.append(float(np.median(err[m])))
    print("| range | median frame | 90th percentile | worst frame |\n|---|---|---|---|")
    for metres, acc in errors.items():
        a = np.asarray(acc)
        print(f"| {metres} m | {np.median(a):.2f} m | {np.percentile(a, 90):.2f} m | {a.max():.2f} m |")


if __name__ == "__main__":
    if sys.argv[1:2] == ["picture"]:
        picture(sys.argv[2])
    elif sys.argv[1:2] == ["bev"]:
        bev()
    else:
        sys.exit(__doc__)
