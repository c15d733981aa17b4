"""The picture docs/images/beyond_edge.jpg: the left camera near the tile's edge, looking out, with neutral
ground beyond the edge (top) and the tile mirrored (bottom), on ``suburb_utm`` and ``osm_town``.

    python docs/tools/beyond_edge.py docs/images/beyond_edge.jpg
"""
import sys

import cv2
import numpy as np

from satloc.geometry import StereoCamera
from satloc_env.render.stereo import StereoRenderer
from satloc_env.world.meshes import build_world
from satloc_env.world.scene import load_scene


def facing_the_edge(scene):
    """The first pose of the scene's routes (every 2 m) that looks at the tile's edge from 15 to 30 m."""
    w, h = scene.layout.width_m, scene.layout.height_m
    best = None
    for route in scene.routes.values():
        for s in np.arange(0.0, route.length, 2.0):
            p = route.pose_at(s, -1.75)
            dx, dy = np.cos(p.yaw), np.sin(p.yaw)
            ts = [t for t in ((w - p.x) / dx if dx > 1e-6 else None, -p.x / dx if dx < -1e-6 else None,
                              (h - p.y) / dy if dy > 1e-6 else None, -p.y / dy if dy < -1e-6 else None)
                  if t is not None]
            t = min(ts)
            if 15 < t < 30 and (best is None or t < best[0]):
                best = (t, p)
    return best[1]


def main(out: str) -> None:
    cam = StereoCamera.kitti_half()
    columns = []
    for name in ("suburb_utm", "osm_town"):
        scene = load_scene(name)
        pose = facing_the_edge(scene)
        views = []
        for beyond in ("neutral", "mirror"):
            with StereoRenderer(build_world(scene.layout, pad_m=250.0, beyond=beyond), cam) as r:
                views.append(r.render(pose, depth=False)["left"])
        columns.append(np.concatenate(views, axis=0))
    gap = np.full((columns[0].shape[0], 8, 3), 255, np.uint8)
    img = np.concatenate([columns[0], gap, columns[1]], axis=1)
    cv2.imwrite(out, cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])


if __name__ == "__main__":
    main(sys.argv[1])
