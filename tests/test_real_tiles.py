"""The scenes over real orthophotos (scenes/real): their files parse and their roads lie on their images; built
and driven where the image has been fetched (scenes/real/README.md), skipped otherwise."""
import json
from pathlib import Path

import numpy as np
import pytest

from satloc.labels import CLASS_ID
from satloc_env.world.scene import load_spec

REAL = Path(__file__).resolve().parents[1] / "scenes" / "real"
SCENES = {"zurich_altstetten": (47.3767, 8.4884, 0.79), "vienna_schoenbrunn": (48.1850, 16.3120, 0.68),
          "banepa": (27.6311, 85.5210, 0.73)}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_the_scene_file_and_its_roads(name):
    spec, _ = load_spec(REAL / f"{name}.yaml")
    assert spec.generator["type"] == "image" and spec.generator["image"] == f"{name}.tif"
    roads = json.loads((REAL / spec.generator["roads"]).read_text())
    pts = np.array([p for f in roads["features"] for p in f["geometry"]["coordinates"]])
    lat, lon, _ = SCENES[name]
    assert np.all(np.abs(pts[:, 1] - lat) < 0.003) and np.all(np.abs(pts[:, 0] - lon) < 0.004)
    assert all(f["properties"]["width"] > 0 for f in roads["features"])
    # the camera's world parks cars of its own, which the map does not show, and shades the ground under them
    assert spec.generator["parked_per_km"] == 54 and spec.ground_shadows is True


@pytest.mark.parametrize("name", sorted(SCENES))
def test_the_scene_over_the_fetched_image(name):
    if not (REAL / f"{name}.tif").is_file():
        pytest.skip(f"scenes/real/{name}.tif not fetched (scenes/real/README.md)")
    from satloc_env.world.scene import load_scene

    sc = load_scene(REAL / f"{name}.yaml")
    network_km = SCENES[name][2]
    assert sc.road_graph.length_m / 1000 == pytest.approx(network_km, abs=0.05)
    # the drawn roads lie on the image's roads: their pixels are grey asphalt more than the image at large
    img, lab = sc.satmap.image.astype(float), sc.layout.ground_labels
    road = lab == CLASS_ID["road"]
    sat = img.max(axis=2) - img.min(axis=2)
    assert sat[road].mean() < sat[~road].mean()
    assert sc.layout.cars and all(sc.is_drivable(*c.center) for c in sc.layout.cars)
