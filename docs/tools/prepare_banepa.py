"""Make banepa.tif: OpenAerialMap drone imagery of Banepa (Nepal), as the hotosm/fAIr-models repository keeps it.

The repository keeps the imagery as 512 x 512 px GeoTIFF chips of web-map tiles at zoom 19 (EPSG:4326, JPEG
compressed, georeferenced by a ``.aux.xml`` beside each chip, about 0.13 m a pixel) under
``data/sample/train/oam/``: 6 x 8 adjacent chips, x 386690..386695, y 220241..220248, a 406 m x 541 m block of
Banepa's centre on both sides of the Araniko Highway. This script

1. reads those 48 chips (and checks that all are there and, by SHA-256, that they are the ones this scene was
   drawn on: commit 95f0727e8fb05816c1544766e8039f5237c3867d of hotosm/fAIr-models);
2. merges them into one mosaic (EPSG:4326, as stored);
3. warps the mosaic to WGS 84 / UTM zone 45N (EPSG:32645) at 0.3 m a pixel, averaging the source pixels
   (the chips are 0.13 m: about 2.3 x 2.3 of them to a 0.3 m pixel), north up;
4. crops it to the largest axis-aligned rectangle on a whole 0.3 m grid that lies wholly inside the chips'
   footprint (the warp turns the geographic rectangle by the grid convergence, -0.7 degrees, so its edges
   have slivers without imagery), and writes it as a 3-band uint8 GeoTIFF (DEFLATE).

Run it with the project's virtual environment (rasterio and numpy):

    git clone --depth 1 https://github.com/hotosm/fAIr-models /tmp/fAIr-models
    python docs/tools/prepare_banepa.py /tmp/fAIr-models scenes/real/banepa.tif

The imagery's licence: scenes/real/README.md (OpenAerialMap / Open Imagery Network, CC BY 4.0 as the
repository's STAC item states; the per-image metadata on api.openaerialmap.org was not checked).
"""

from __future__ import annotations

import hashlib
import math
import sys
from pathlib import Path

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.merge import merge
from rasterio.transform import Affine
from rasterio.warp import reproject
from rasterio.warp import transform as warp_transform

CHIP_DIR = "data/sample/train/oam"
XS = range(386690, 386696)        # 6 columns of zoom-19 tiles
YS = range(220241, 220249)        # 8 rows
ZOOM = 19
DST_CRS = CRS.from_epsg(32645)    # WGS 84 / UTM zone 45N
RES = 0.3                          # metres a pixel
#: SHA-256 over the 48 chips' bytes, in the order of chip_names() (commit 95f0727 of hotosm/fAIr-models)
EXPECTED_SHA256 = "22d3cc77eb750dd0ac2db7edb94a9c8bfc8238d94056de78b15acd31897bf510"


def chip_names() -> list[str]:
    return [f"OAM-{x}-{y}-{ZOOM}.tif" for x in XS for y in YS]


def digest(paths: list[Path]) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(p.read_bytes())
    return h.hexdigest()


def main(repo: str, out: str) -> None:
    chips = [Path(repo) / CHIP_DIR / n for n in chip_names()]
    missing = [str(p) for p in chips if not p.exists() or not Path(str(p) + ".aux.xml").exists()]
    if missing:
        sys.exit(f"missing chips or their .aux.xml georeference: {missing[:3]} ... ({len(missing)} in all)")
    d = digest(chips)
    if d != EXPECTED_SHA256:
        print(f"warning: the chips' SHA-256 is {d}, not {EXPECTED_SHA256}: the repository's sample data may have "
              f"changed since the scene's roads were drawn (check out commit 95f0727 of hotosm/fAIr-models)",
              file=sys.stderr)

    srcs = [rasterio.open(p) for p in chips]
    for s in srcs:
        if s.crs is None or s.count != 3 or s.dtypes[0] != "uint8":
            sys.exit(f"{s.name}: expected a georeferenced 3-band uint8 chip, got crs={s.crs} count={s.count} "
                     f"dtype={s.dtypes[0]}")
    mosaic, src_tf = merge(srcs)                       # (3, H, W) uint8, EPSG:4326
    src_crs = srcs[0].crs
    h, w = mosaic.shape[1:]
    for s in srcs:
        s.close()

    # the mosaic's corners in UTM; the largest axis-aligned rectangle inside that (nearly square) quadrilateral
    cols = [0, w, w, 0]
    rows = [0, 0, h, h]
    lon = [src_tf.c + c * src_tf.a for c in cols]
    lat = [src_tf.f + r * src_tf.e for r in rows]
    ex, ny = warp_transform(src_crs, DST_CRS, lon, lat)   # corners: NW, NE, SE, SW
    west = max(ex[0], ex[3])
    east = min(ex[1], ex[2])
    north = min(ny[0], ny[1])
    south = max(ny[2], ny[3])
    west = math.ceil(west / RES) * RES + RES            # one pixel in from the edge against resampling seams
    south = math.ceil(south / RES) * RES + RES
    east = math.floor(east / RES) * RES - RES
    north = math.floor(north / RES) * RES - RES
    width = int(round((east - west) / RES))
    height = int(round((north - south) / RES))
    dst_tf = Affine(RES, 0.0, west, 0.0, -RES, north)

    dst = np.zeros((3, height, width), np.uint8)
    reproject(mosaic, dst, src_transform=src_tf, src_crs=src_crs, dst_transform=dst_tf, dst_crs=DST_CRS,
              resampling=Resampling.average, src_nodata=None, dst_nodata=None)

    profile = dict(driver="GTiff", width=width, height=height, count=3, dtype="uint8", crs=DST_CRS,
                   transform=dst_tf, compress="deflate", predictor=2, tiled=True, blockxsize=256,
                   blockysize=256, photometric="RGB", interleave="pixel")
    with rasterio.open(out, "w", **profile) as f:
        f.write(dst)
        f.update_tags(SOURCE="OpenAerialMap image 62d85d11d8499800053796c1 (Banepa, Nepal) as zoom-19 chips in "
                             "github.com/hotosm/fAIr-models data/sample/train/oam (commit 95f0727)",
                      LICENSE="CC BY 4.0 (OpenAerialMap / Open Imagery Network; attribution: OIN contributors)")
    print(f"{out}: {width} x {height} px at {RES} m = {width * RES:.1f} m x {height * RES:.1f} m, {DST_CRS}, "
          f"west {west:.1f} south {south:.1f} east {east:.1f} north {north:.1f}; chips' SHA-256 {d}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python docs/tools/prepare_banepa.py FAIR_MODELS_CHECKOUT OUT.tif")
    main(sys.argv[1], sys.argv[2])
