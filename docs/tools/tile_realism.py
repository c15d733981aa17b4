"""The generated satellite tiles beside real orthophotos, measured the same way (issue 46).

    python docs/tools/tile_realism.py [--parts traffic,...] [--real zurich.tif] [--out tile_realism.json]

For each tile, at 0.5 m a pixel (real tiles resampled to it, the generated captures resampled from their 0.2 m):

- whole tile: ORB keypoints per hectare (OpenCV ORB, nfeatures 100000, fastThreshold 20, on the grey image),
  the share of dark pixels (grey below 0.5 of the tile's median: shadows and dark surfaces), the share of
  vegetation (excess green ``(2g - r - b) / (r + g + b)`` above 0.08), the slope of the radially averaged power
  spectrum of the grey image between wavelengths of 1 and 20 m;
- on the road (a real tile: bands drawn by eye along carriageways, :data:`ZURICH_BANDS`; a generated one: its
  ground's ``road`` and ``lane_marking`` pixels): the share of vegetation over it (canopy), of shadow (grey below
  0.6 of the band's 75th percentile, not vegetation) and the rest. The same pixel rules on both: they are
  estimates (a dark car counts as shadow, a green one as canopy), compared like for like.

The real tile: the canton of Zurich's 2014 summer orthophoto (Amt fuer Raumentwicklung Kanton Zuerich, open
government data: free reuse, the source named), as the detectree project ships it downsampled to 0.5 m for its
tests: ``git clone https://github.com/martibosch/detectree`` and pass
``--real detectree/tests/data/big_img/1091-322_00.tif`` (EPSG:2056, 437.5 m x 300 m, Zurich-Altstetten).
"""
import argparse
import json
import sys

import cv2
import numpy as np

#: carriageway bands drawn by eye on the Zurich tile (pixels of its 0.5 m grid, band width in metres): the tram
#: road, a residential street and a side road (their kerbs, pavements and trees left out)
ZURICH_BANDS = [
    {"name": "main", "w_m": 6, "pts": [[290, 531], [440, 492], [570, 428], [640, 363], [715, 309], [790, 264],
                                        [865, 219]]},
    {"name": "side", "w_m": 4, "pts": [[600, 545], [690, 460], [740, 410], [830, 345]]},
    {"name": "south", "w_m": 4, "pts": [[440, 530], [640, 580]]},
]
MPP = 0.5


def grey(img):
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)


def vegetation(img):
    f = img.astype(np.float32)
    s = f.sum(axis=2) + 1e-6
    return (2 * f[..., 1] - f[..., 0] - f[..., 2]) / s > 0.08


def spectral_slope(g, mpp, lo_m=1.0, hi_m=20.0):
    g = g - g.mean()
    h, w = g.shape
    win = np.outer(np.hanning(h), np.hanning(w))
    p = np.abs(np.fft.fftshift(np.fft.fft2(g * win))) ** 2
    fy, fx = np.meshgrid(np.fft.fftshift(np.fft.fftfreq(h, mpp)), np.fft.fftshift(np.fft.fftfreq(w, mpp)),
                         indexing="ij")
    f = np.hypot(fx, fy)
    bins = np.geomspace(1 / hi_m, 1 / lo_m, 20)
    idx = np.digitize(f.ravel(), bins)
    pw = np.array([p.ravel()[idx == i].mean() for i in range(1, len(bins))])
    fc = np.sqrt(bins[1:] * bins[:-1])
    return float(np.polyfit(np.log(fc), np.log(pw), 1)[0])


def whole(img):
    g = grey(img)
    orb = cv2.ORB_create(nfeatures=100000, fastThreshold=20)
    kp = orb.detect(g.astype(np.uint8), None)
    area_ha = g.size * MPP * MPP / 1e4
    return {"orb_per_ha": len(kp) / area_ha, "dark": float((g < 0.5 * np.median(g)).mean()),
            "vegetation": float(vegetation(img).mean()), "spectral_slope": spectral_slope(g, MPP)}


def on_road(img, road):
    g = grey(img)
    veg = vegetation(img) & road
    ref = np.percentile(g[road & ~veg], 75)
    shadow = (g < 0.6 * ref) & road & ~veg
    n = max(int(road.sum()), 1)
    return {"road_px": int(road.sum()), "canopy": float(veg.sum() / n), "shadow": float(shadow.sum() / n),
            "rest": float(1 - (veg.sum() + shadow.sum()) / n)}


def real(path):
    import rasterio

    with rasterio.open(path) as f:
        img = np.ascontiguousarray(f.read([1, 2, 3]).transpose(1, 2, 0))
        res = abs(f.res[0])
    if abs(res - MPP) > 1e-6:
        raise SystemExit(f"{path}: expected {MPP} m a pixel, got {res}")
    road = np.zeros(img.shape[:2], np.uint8)
    for b in ZURICH_BANDS:
        cv2.polylines(road, [np.asarray(b["pts"], np.int32).reshape(-1, 1, 2)], False, 1,
                      max(1, int(round(b["w_m"] / MPP))))
    return {"whole": whole(img), "road": on_road(img, road > 0)}


def generated(name, parts):
    from satloc_env.world.capture import PARTS, capture_tile, road_cover
    from satloc_env.world.scene import load_scene

    sc = load_scene(name)
    lay, spec = sc.layout, sc.spec
    img, _ = capture_tile(lay, spec.meters_per_pixel, spec.seed, spec.knobs.satellite_gap, PARTS + tuple(parts))
    k = MPP / spec.meters_per_pixel
    h, w = int(img.shape[0] / k), int(img.shape[1] / k)
    small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    g_k = int(round(MPP / lay.ground_mpp))
    ground = lay.ground_labels[g_k // 2::g_k, g_k // 2::g_k][:h, :w]
    from satloc.labels import CLASS_ID as C
    road = np.isin(ground, (C["road"], C["lane_marking"]))
    return {"whole": whole(small), "road": on_road(small, road),
            "road_cover": road_cover(lay, spec.meters_per_pixel, spec.seed, spec.knobs.satellite_gap,
                                     PARTS + tuple(parts))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", action="append", default=[])
    ap.add_argument("--scenes", default="city,residential")
    ap.add_argument("--parts", default="", help="optional capture parts, comma-separated")
    ap.add_argument("--out")
    a = ap.parse_args(argv)
    parts = [p for p in a.parts.split(",") if p]
    out = {}
    for p in a.real:
        out[p] = real(p)
        print(p, json.dumps(out[p]), flush=True)
    for s in a.scenes.split(","):
        if s:
            out[s] = generated(s, parts)
            print(s, json.dumps(out[s]), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"parts": parts, "tiles": out}, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
