"""A fuzz corpus for every file satloc reads (issue 15, item 3): seeded mutations (tests/fuzzing.py) of valid
artefacts that the project's own writers make here, in tmp_path.

Each format's cases must end in a :class:`satloc.FormatError` / :class:`satloc.ConfigError` naming the mutated
file, or in a loaded result that satisfies the format's invariants and, where the mutation cannot have made
another valid file (a checksum, an ignored field), equals the original; never another exception, never a
hang (``signal.setitimer`` bounds each case), never a result the loader should have refused (a NaN pose, a
wrong dtype). The counts of cases tried per format (loaded the same / loaded changed / rejected) go to the
JSON file ``$SATLOC_FUZZ_REPORT`` when it is set, and are printed (``pytest -s``).

``SATLOC_FUZZ_SCALE`` (default 1) multiplies the number of cases, e.g. 5 for a longer run.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
from fuzzing import Format, Target, Targeted, run_format

from satloc import Frame, Pose2, SatelliteMap, Sequence, StereoCamera
from satloc.geoframe import GeoFrame
from satloc.labels import NUM_CLASSES

SCALE = float(os.environ.get("SATLOC_FUZZ_SCALE", "1"))
COUNTS: dict[str, dict] = {}
FAILURES_SHOWN = 12


# --- shared invariants and digests ----------------------------------------------------------------------
def _finite(*vals) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in vals)


def check_camera(c: StereoCamera) -> None:
    from satloc.sequence import CAMERA_RANGES

    assert isinstance(c, StereoCamera), type(c)
    assert isinstance(c.width, int) and isinstance(c.height, int) and c.width > 0 and c.height > 0, c
    assert _finite(c.fx, c.fy, c.cx, c.cy, c.baseline, c.mount_height, c.pitch), c
    assert all(lo < getattr(c, k) <= hi for k, (lo, hi) in CAMERA_RANGES.items()), c


def check_satmap(sm: SatelliteMap) -> None:
    assert isinstance(sm, SatelliteMap)
    img = sm.image
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3 and min(img.shape[:2]) >= 1, img.shape
    assert _finite(sm.meters_per_pixel) and sm.meters_per_pixel > 0, sm.meters_per_pixel
    assert _finite(*sm.origin) and _finite(*sm.extent), (sm.origin, sm.extent)
    if sm.labels is not None:
        assert sm.labels.dtype == np.uint8 and sm.labels.shape == img.shape[:2], (sm.labels.dtype, sm.labels.shape)
        assert sm.labels.max() < NUM_CLASSES, sm.labels.max()
    assert sm.frame is None or isinstance(sm.frame, GeoFrame)


def digest_satmap(sm: SatelliteMap) -> dict:
    return {"image": sm.image, "labels": sm.labels, "mpp": sm.meters_per_pixel, "origin": list(sm.origin),
            "frame": sm.frame.to_dict() if sm.frame is not None else None}


def check_sequence(loaded) -> None:
    seq, frames = loaded
    check_camera(seq.camera)
    n = len(seq)
    assert len(frames) == n
    p, t = seq.poses, seq.timestamps
    assert p.shape == (n, 3) and p.dtype == np.float64 and t.shape == (n,) and t.dtype == np.float64
    fin = np.isfinite(p)
    assert np.all(fin.all(axis=1) | (~fin).all(axis=1)), "a pose row that is partly NaN"
    assert np.isfinite(t).all(), "non-finite timestamp"
    assert isinstance(seq.meta, dict) and isinstance(seq.name, str)
    assert seq.geo_frame is None or isinstance(seq.geo_frame, GeoFrame)
    for i, f in enumerate(frames):
        f.check(seq.camera)
        assert (f.pose is None) == (not fin[i].all())
        if f.pose is not None:
            assert np.allclose(f.pose.as_array()[:2], p[i, :2])
        if f.depth is not None:
            assert f.depth.dtype == np.float32 and np.isfinite(f.depth).all() and (f.depth >= 0).all()
        if f.labels is not None:
            assert f.labels.dtype == np.uint8 and f.labels.ndim == 2 and f.labels.max() < NUM_CLASSES


def digest_sequence(loaded, meta_drop: tuple = (), meta_keep: tuple | None = ("geo_frame",)) -> dict:
    """What a loaded sequence is; of ``meta`` only the keys ``meta_keep`` (None: all but ``meta_drop``)."""
    seq, frames = loaded
    meta = {k: v for k, v in seq.meta.items() if k not in meta_drop and (meta_keep is None or k in meta_keep)}
    return {"camera": seq.camera.to_dict(), "name": seq.name, "meta": meta, "poses": seq.poses,
            "timestamps": seq.timestamps,
            "frames": [[f.left, f.right, f.depth, f.labels, f.timestamp,
                        None if f.pose is None else f.pose.as_array()] for f in frames]}


def load_sequence(seq: Sequence):
    return seq, list(seq)


# --- scene YAML and saved scenes ------------------------------------------------------------------------
FUZZ_SCENE = """\
name: fuzz
seed: 3
description: a one-block scene for the fuzz corpus
generator: {type: grid, style: city, blocks: [1, 1], pitch_m: 60, road_width_m: 12, sidewalk_m: 3, margin_m: 12}
meters_per_pixel: 0.4
ground_mpp: 0.2
routes:
  main:
    waypoints: [[12, 12], [72, 12], [72, 72], [12, 72]]
    closed: true
  side: {waypoints: [[12, 12], [12, 60]], laps: 1}
database_route: main
query_route: side
objects:
  buildings: [{footprint: [[30, 30], [40, 30], [40, 40], [30, 40]], height: 9, facade: 1, roof_rgb: [90, 80, 70]}]
  trees: [{center: [20, 50], canopy_radius: 2.5}]
  cars: [{center: [50, 14], yaw_deg: 5, rgb: [10, 20, 200]}]
lighting: {sun_azimuth_deg: 120, sun_elevation_deg: 45}
knobs: {aliasing: 0.0, occlusion: 0.2, appearance: 0.1}
"""


def check_scene(sc) -> None:
    from satloc_env.world.scene import Scene

    assert isinstance(sc, Scene)
    check_satmap(sc.satmap)
    lay = sc.layout
    assert lay.ground_rgb.dtype == np.uint8 and lay.ground_rgb.ndim == 3 and lay.ground_rgb.shape[2] == 3
    assert lay.ground_labels.shape == lay.ground_rgb.shape[:2] and lay.ground_labels.dtype == np.uint8
    assert lay.ground_labels.max() < NUM_CLASSES
    assert _finite(lay.width_m, lay.height_m, lay.ground_mpp, lay.sun_azimuth, lay.sun_elevation)
    assert lay.ground_mpp > 0 and lay.width_m > 0 and lay.height_m > 0
    for b in lay.buildings:
        fp = np.asarray(b.footprint)
        assert fp.ndim == 2 and fp.shape[1] == 2 and len(fp) >= 3 and np.isfinite(fp).all(), fp.shape
        assert _finite(float(b.height)) and b.height > 0
    for t in lay.trees:
        assert _finite(*map(float, t.center), float(t.canopy_radius), float(t.canopy_bottom), float(t.canopy_top))
    for c in lay.cars:
        assert _finite(*map(float, c.center), float(c.yaw), float(c.length), float(c.width), float(c.height))
    for k in ("aliasing", "occlusion", "appearance"):
        assert 0 <= getattr(sc.spec.knobs, k) <= 1
    for k, r in sc.spec.routes.items():
        w = np.asarray(r.waypoints, np.float64)
        assert w.ndim == 2 and w.shape[1] == 2 and np.isfinite(w).all(), k


def digest_scene(sc) -> dict:
    from satloc.config import to_dict

    lay = sc.layout
    spec = {k: v for k, v in to_dict(sc.spec).items() if k != "description"}  # free text
    return {"spec": spec, "map": digest_satmap(sc.satmap), "ground_rgb": lay.ground_rgb,
            "ground_labels": lay.ground_labels, "size": [lay.width_m, lay.height_m, lay.ground_mpp],
            "sun": [lay.sun_azimuth, lay.sun_elevation],
            "buildings": [[np.asarray(b.footprint, np.float64), float(b.height), int(b.facade), list(b.roof_rgb)]
                          for b in lay.buildings],
            "trees": [[float(v) for v in (*t.center, t.canopy_radius, t.canopy_bottom, t.canopy_top, t.shade)]
                      for t in lay.trees],
            "cars": [[float(v) for v in (*c.center, c.yaw, c.length, c.width, c.height, *c.rgb)] for c in lay.cars],
            "alias_source": np.asarray(sc.alias_source)}


def make_scene_yaml(d: Path) -> None:
    d.mkdir(parents=True)
    (d / "fuzz.yaml").write_text(FUZZ_SCENE)


def load_scene_yaml(d: Path):
    from satloc_env.world.scene import build_scene, load_spec

    path = d / "fuzz.yaml"
    spec, base = load_spec(path)
    return build_scene(spec, base, where=str(path))


def make_saved_scene(d: Path) -> None:
    make_scene_yaml(d / "src")
    load_scene_yaml(d / "src").save(d / "scene")


def load_saved_scene(d: Path):
    from satloc_env.world.scene import Scene

    return Scene.load(d / "scene")


# --- satellite map and sequence ------------------------------------------------------------------------
def make_map(d: Path) -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    labels = rng.integers(0, NUM_CLASSES, (30, 40), dtype=np.uint8)
    SatelliteMap(img, 0.5, (100.0, 250.0), labels, GeoFrame(8.43, 49.01)).save(d / "map")


def load_map_dir(d: Path):
    return SatelliteMap.load(d / "map")


SEQ_CAMERA = StereoCamera(32, 12, 30.0, 30.5, 15.5, 5.75, 0.5, 1.6, 0.02)


def make_sequence(d: Path) -> None:
    rng = np.random.default_rng(2)
    cam, frames = SEQ_CAMERA, []
    for i in range(3):
        sh = (cam.height, cam.width)
        frames.append(Frame(rng.integers(0, 256, sh + (3,), dtype=np.uint8),
                            rng.integers(0, 256, sh + (3,), dtype=np.uint8), Pose2(3.0 + i, -2.0 + 0.5 * i, 0.1 * i),
                            0.1 * i, np.round(rng.uniform(0, 80, sh) * 256).astype(np.float32) / 256,
                            rng.integers(0, NUM_CLASSES, sh, dtype=np.uint8)))
    meta = {"source": "fuzz", "geo_frame": GeoFrame(8.43, 49.01).to_dict(), "note": {"list": [1, 2, 3]}}
    Sequence(cam, frames, "fuzzseq", meta).save(d / "seq")


def load_sequence_dir(d: Path):
    return load_sequence(Sequence.load(d / "seq"))


# --- build artefacts -----------------------------------------------------------------------------------
def _dictionary():
    from satloc.features.context import ContextConfig
    from satloc.features.dictionary import Dictionary, GridConfig

    rng = np.random.default_rng(3)
    n, f = 40, 5
    return Dictionary(rng.random((n, 9), dtype=np.float32), rng.random((n, 9), dtype=np.float32),
                      rng.uniform(0, 50, (n, 2)), rng.integers(0, f, n).astype(np.int32),
                      np.c_[np.arange(f) + 5.0, np.full(f, 20.0), np.zeros(f)], GridConfig(step_px=8), "rgb",
                      ContextConfig(scales_m=(1.0, 3.0)))


def check_dictionary(d) -> None:
    from satloc.features.dictionary import Dictionary

    assert isinstance(d, Dictionary)
    n = len(d.g)
    for name, a, width in (("g", d.g, None), ("s", d.s, None), ("loc", d.loc, 2)):
        assert a.ndim == 2 and a.dtype.kind == "f" and len(a) == n and np.isfinite(a).all(), (name, a.dtype, a.shape)
        assert width is None or a.shape[1] == width, (name, a.shape)
    assert d.frame.shape == (n,) and d.frame.dtype.kind in "iu", (d.frame.dtype, d.frame.shape)
    assert d.poses.ndim == 2 and d.poses.shape[1] == 3 and d.poses.dtype.kind == "f", d.poses.shape
    assert np.isfinite(d.poses).all()
    assert n == 0 or (d.frame.min() >= 0 and d.frame.max() < len(d.poses)), "frame index out of range"
    assert d.g.shape[1] >= 1 and d.s.shape[1] >= 1
    assert isinstance(d.feature_name, str)
    assert all(_finite(float(s)) and s > 0 for s in d.context.scales_m) and _finite(d.context.weight)
    assert _finite(d.grid.row_start_frac, d.grid.min_depth_m, d.grid.max_depth_m) and 0 <= d.grid.row_start_frac < 1


def digest_dictionary(d) -> dict:
    from satloc.config import to_dict

    return {"g": d.g, "s": d.s, "loc": d.loc, "frame": d.frame, "poses": d.poses, "grid": to_dict(d.grid),
            "context": to_dict(d.context), "feature_name": d.feature_name}


def make_dictionary(d: Path) -> None:
    _dictionary().save(d / "dictionary.npz")


def load_dictionary(d: Path):
    from satloc.features.dictionary import Dictionary

    return Dictionary.load(d / "dictionary.npz")


def make_satfeat(d: Path) -> None:
    from satloc.features.dictionary import SatelliteFeatures

    f = np.random.default_rng(4).random((30, 40, 9)).astype(np.float16)
    SatelliteFeatures(f, 0.5, (100.0, 250.0), "rgb").save(d / "satellite_features.npz")


def check_satfeat(sf) -> None:
    from satloc.features.dictionary import SatelliteFeatures

    assert isinstance(sf, SatelliteFeatures)
    f = sf.features
    assert f.ndim == 3 and f.dtype.kind == "f" and min(f.shape) >= 1 and np.isfinite(f).all(), (f.dtype, f.shape)
    assert _finite(sf.meters_per_pixel) and sf.meters_per_pixel > 0
    assert len(sf.origin) == 2 and _finite(*sf.origin) and isinstance(sf.name, str)


def digest_satfeat(sf) -> dict:
    return {"features": sf.features, "mpp": sf.meters_per_pixel, "origin": list(sf.origin), "name": sf.name}


def load_satfeat(d: Path):
    from satloc.features.dictionary import SatelliteFeatures

    return SatelliteFeatures.load(d / "satellite_features.npz")


def make_projections(d: Path) -> None:
    from satloc.features.projection import Projections

    rng = np.random.default_rng(5)
    Projections(np.eye(9, dtype=np.float32) + 0.01 * rng.random((9, 9), dtype=np.float32),
                np.eye(9, dtype=np.float32), [3.0, 2.5, 2.25], True, [0.5, 0.75, 0.8, 0.7], 2).save(
        d / "projections.pt")


def check_projections(p) -> None:
    from satloc.features.projection import Projections

    assert isinstance(p, Projections)
    for w in (p.W_g, p.W_s):
        assert w.ndim == 2 and w.shape[0] == w.shape[1] >= 1 and w.dtype == np.float32, (w.dtype, w.shape)
        assert np.isfinite(w).all()
    assert all(_finite(v) for v in p.loss_curve) and all(_finite(v) for v in p.val_curve)
    assert isinstance(p.converged, bool) and isinstance(p.best_epoch, int) and p.best_epoch >= -1


def digest_projections(p) -> dict:
    return {"W_g": p.W_g, "W_s": p.W_s, "loss": list(p.loss_curve), "val": list(p.val_curve),
            "converged": p.converged, "best": p.best_epoch}


def load_projections(d: Path):
    from satloc.features.projection import Projections

    return Projections.load(d / "projections.pt")


BUILD_CAMERA = StereoCamera.kitti().resized(96, 40)


def make_build(d: Path) -> None:
    """A tiny build through the pipeline (dictionary, satellite features, projections, satellite table)."""
    from satloc.features.context import ContextConfig
    from satloc.features.projection import ProjectionConfig
    from satloc.pipeline import BuildConfig, build, train_projection
    from satloc_env.envs.auto_localizer import load_cached_localizer

    rng = np.random.default_rng(6)
    cam, frames = BUILD_CAMERA, []
    for i in range(10):
        sh = (cam.height, cam.width)
        frames.append(Frame(rng.integers(0, 256, sh + (3,), dtype=np.uint8),
                            rng.integers(0, 256, sh + (3,), dtype=np.uint8), Pose2(5.0 + i, 20.0, 0.03 * i), 0.1 * i,
                            rng.uniform(3, 30, sh).astype(np.float32)))
    db = Sequence(cam, frames, "db")
    sm = SatelliteMap(rng.integers(0, 256, (80, 80, 3), dtype=np.uint8), 0.5, (0.0, 40.0))
    build(db, sm, d / "build", BuildConfig(features="rgb", depth_source="frame",
                                           context=ContextConfig(scales_m=(1.0, 3.0))), progress=False)
    train_projection(d / "build", ProjectionConfig(max_epochs=1, val_frac=0.0, max_anchors=500), progress=False)
    load_cached_localizer(d / "build", "full")  # writes satellite_table_full.npz


def load_build(d: Path):
    from satloc_env.envs.auto_localizer import load_cached_localizer

    return load_cached_localizer(d / "build", "full")


def check_localizer(loc) -> None:
    from satloc.localizers.database import Localizer

    assert isinstance(loc, Localizer)
    check_dictionary(loc.dictionary)
    check_satfeat(loc.satfeat)
    check_camera(loc.camera)
    dg, ds = loc.dictionary.g.shape[1], loc.dictionary.s.shape[1]
    assert loc.proj.W_g.shape == (dg, dg) and loc.proj.W_s.shape == (ds, ds)
    assert np.isfinite(loc.proj.W_g).all() and np.isfinite(loc.proj.W_s).all()
    h, w = loc.satfeat.features.shape[:2]
    assert loc.pixel_row.shape == (h * w,) and loc.pixel_row.min() >= -1
    rows = len(loc.sat_ids)
    assert np.array_equal(loc.pixel_row[loc.pixel_row >= 0], np.arange(rows)), "pixel_row is not a row index"
    assert loc.sat_ids.shape == (rows, loc.config.neighbors) and loc.sat_w.shape == loc.sat_ids.shape
    assert loc.sat_ids.min() >= 0 and loc.sat_ids.max() < len(loc.dictionary), "table ids out of range"
    assert np.isfinite(loc.sat_w).all() and (loc.sat_w > 0).all()
    assert _finite(loc.eps_s, loc.eps_g) and loc.eps_s > 0
    assert np.isfinite(loc.candidates).all()


def digest_localizer(loc) -> dict:
    return {"dictionary": digest_dictionary(loc.dictionary), "satfeat": digest_satfeat(loc.satfeat),
            "camera": loc.camera.to_dict(), "W_g": loc.proj.W_g, "W_s": loc.proj.W_s,
            "pixel_row": loc.pixel_row, "ids": loc.sat_ids, "weights": loc.sat_w, "eps_s": loc.eps_s,
            "eps_g": loc.eps_g, "candidates": loc.candidates, "extractor": loc.extractor.name}


def make_autoloc(d: Path) -> None:
    from satloc.config import to_dict
    from satloc.features.projection import ProjectionConfig
    from satloc.persist import FORMAT_VERSION, header, write_json
    from satloc.pipeline import BuildConfig
    from satloc_env.envs.record import RecordConfig

    key = {"scene": "fuzz", "source": "/somewhere/fuzz.yaml", "scene_sha256": "0" * 64, "aliasing": 0.0,
           "resolution": "half", "format_version": FORMAT_VERSION, "satloc_version": "0.1.0", "key_version": 1,
           "speed_mps": 8.0, "database_pass": to_dict(RecordConfig().database), "build": to_dict(BuildConfig()),
           "projection": to_dict(ProjectionConfig())}
    write_json(d / "entry" / "autoloc.json", dict(header("autoloc_cache"), key=key, seconds=12.5))


def load_autoloc(d: Path):
    from satloc_env.envs.auto_localizer import describe_entry

    return describe_entry(d / "entry")


def check_autoloc(key) -> None:
    assert isinstance(key, dict) and all(isinstance(k, str) for k in key)
    assert isinstance(key["scene"], str) and key["resolution"] in ("half", "full")
    assert _finite(key["aliasing"]) and 0 <= key["aliasing"] <= 1
    for k in ("database_pass", "build", "projection"):
        assert isinstance(key[k], dict)


# --- FCN weights ---------------------------------------------------------------------------------------
def make_fcn(d: Path) -> None:
    import torch

    from satloc.features.fcn import SegEdgeNet, ViewNet, save_fcn

    torch.manual_seed(0)
    views = {"ground": ViewNet(SegEdgeNet(NUM_CLASSES, (2, 3)).eval(), 0.5),
             "satellite": ViewNet(SegEdgeNet(NUM_CLASSES, (3, 2, 2)).eval(), 1.0)}
    d.mkdir(parents=True)
    save_fcn(d / "fcn.pt", views, {"epochs": 1, "note": "fuzz", "curve": [1.0, 0.5]})


def load_fcn_file(d: Path):
    from satloc.features.fcn import load_fcn

    return load_fcn(d / "fcn.pt")


def check_fcn(loaded) -> None:
    import torch

    from satloc.features.fcn import VIEWS, SegEdgeNet

    views, training = loaded
    assert views and set(views) <= set(VIEWS) and isinstance(training, dict)
    for v in views.values():
        assert isinstance(v.net, SegEdgeNet) and 0 < v.input_scale <= 4
        for t in v.net.state_dict().values():
            assert not t.is_floating_point() or bool(torch.isfinite(t).all()), "non-finite weights"


def digest_fcn(loaded) -> dict:
    views, training = loaded
    return {k: {"widths": list(v.net.widths), "scale": v.input_scale,
                "state": {n: t.detach().numpy().copy() for n, t in v.net.state_dict().items()}}
            for k, v in sorted(views.items())}


# --- KITTI raw, Malaga, georeferenced maps ----------------------------------------------------------------
DRIVE = "2011_09_26/2011_09_26_drive_0001_sync"


def make_kitti(d: Path) -> None:
    from kittifixture import write_kitti_drive

    write_kitti_drive(d, 4)


def load_kitti_drive(d: Path):
    from satloc.datasets.kitti import load_kitti

    return load_sequence(load_kitti(d / DRIVE))


def check_kitti(loaded) -> None:
    check_sequence(loaded)
    assert np.isfinite(loaded[0].poses).all(), "a KITTI frame without a finite pose"


def digest_real(loaded) -> dict:
    return digest_sequence(loaded, ("drive_dir", "extract_dir"), None)


def make_malaga(d: Path) -> None:
    from malagafixture import T0, TurnTrack, track_lonlat, write_malaga_extract

    track = TurnTrack(straight1=10.0, radius=8.0, straight2=10.0, speed=5.0)
    gps_t = T0 + np.arange(0.0, 8.0, 1.0)
    xy = track.at(track.distance(gps_t - T0))[:, :2]
    img_t = T0 + 0.5 + 1.2 * np.arange(6)
    write_malaga_extract(d, img_t, gps_t, track_lonlat(xy), size=(40, 30), fx=31.0, fy=31.0, cx=20.2, cy=15.45)


MALAGA = "malaga-urban-dataset-extract-07"


def load_malaga_extract(d: Path):
    from satloc.datasets.malaga import load_malaga

    return load_sequence(load_malaga(d / MALAGA))


def _malaga_images(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in (d / MALAGA).glob("*_Images/*.jpg"))


def make_geotiff(d: Path) -> None:
    from geofixtures import UTM
    from geofixtures import make_geotiff as mk

    d.mkdir(parents=True)
    mk(d / "map.tif", UTM, gsd_m=4.0)


def make_world_png(d: Path) -> None:
    from geofixtures import UTM, make_world_image

    d.mkdir(parents=True)
    make_world_image(d / "map.png", UTM, gsd_m=4.0)


def make_world_jpeg(d: Path) -> None:
    from geofixtures import make_world_image

    d.mkdir(parents=True)
    make_world_image(d / "map.jpg", "EPSG:3857", gsd_m=4.0)


def make_tiles(d: Path) -> None:
    from geofixtures import make_tiles as mk

    mk(d / "tiles", zoom=16)


def load_georef(name: str):
    def load(d: Path):
        from satloc.geodata.georef import load_map

        return load_map(d / name)

    return load


# --- targeted cases: known pitfalls, run before the seeded ones -------------------------------------------
def edit_json(fn):
    def apply(path: Path) -> None:
        d = json.loads(path.read_text())
        fn(d)
        path.write_text(json.dumps(d))
    return apply


def edit_yaml(fn):
    def apply(path: Path) -> None:
        import yaml

        d = yaml.safe_load(path.read_text())
        fn(d)
        path.write_text(yaml.safe_dump(d, sort_keys=False))
    return apply


def edit_npz(fn):
    def apply(path: Path) -> None:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        fn(a)
        with open(path, "wb") as f:
            np.savez_compressed(f, **a)
    return apply


def edit_torch(fn):
    def apply(path: Path) -> None:
        import torch

        obj = torch.load(path, weights_only=True)
        fn(obj)
        torch.save(obj, path)
    return apply


def edit_tokens(line: int, column: int, value: str):
    """Replace the whitespace-separated token ``column`` of (0-based) non-comment line ``line``."""
    def apply(path: Path) -> None:
        lines = path.read_text().splitlines()
        body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("%")]
        words = lines[body[line]].split()
        words[column] = value
        lines[body[line]] = " ".join(words)
        path.write_text("\n".join(lines) + "\n")
    return apply


def set_item(path: tuple, value):
    def fn(d):
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return fn


def truncate_by(n: int):
    def apply(path: Path) -> None:
        path.write_bytes(path.read_bytes()[:-n])
    return apply


def as_png_8bit(path: Path) -> None:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert cv2.imwrite(str(path.with_suffix(".tmp.png")), (img // 257).astype(np.uint8) if img.dtype == np.uint16
                       else (img.astype(np.uint16) * 257))
    path.with_suffix(".tmp.png").replace(path)


def jpeg_under_png_name(path: Path) -> None:
    import cv2

    img = cv2.imread(str(path))
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 100])
    path.write_bytes(buf.tobytes())


def geotiff_far_away(path: Path) -> None:
    """The GeoTIFF moved to x = 1e20 m (GDAL's transformer loops for ages on such coordinates)."""
    import rasterio
    from affine import Affine

    with rasterio.open(path) as ds:
        arr, prof = ds.read(), dict(ds.profile)
    t = prof["transform"]
    prof["transform"] = Affine(t.a, t.b, 1e20, t.d, t.e, t.f)
    with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path, "w", **prof) as dst:
        dst.write(arr)


def targeted() -> dict[str, list[Targeted]]:
    scale = lambda k: (lambda a: a.__setitem__(k, a[k] * np.float32(1e30)))  # noqa: E731
    return {
        "scene_yaml": [
            Targeted("fuzz.yaml", "generator.blocks [100000, 100000] (a 6000 km ground)",
                     edit_yaml(set_item(("generator", "blocks"), [100000, 100000]))),
            Targeted("fuzz.yaml", "ground_mpp 1e-9 (a ground of 1e23 pixels)",
                     edit_yaml(set_item(("ground_mpp",), 1e-9))),
            Targeted("fuzz.yaml", "routes.main.laps 1e9", edit_yaml(set_item(("routes", "main", "laps"), 10**9))),
            Targeted("fuzz.yaml", "lighting.sun_elevation_deg 0",
                     edit_yaml(set_item(("lighting", "sun_elevation_deg"), 0))),
            Targeted("fuzz.yaml", "a tree 1e18 m away",
                     edit_yaml(set_item(("objects", "trees", 0, "center"), [1e18, 5]))),
            Targeted("fuzz.yaml", "building facade -1", edit_yaml(set_item(("objects", "buildings", 0, "facade"), -1))),
        ],
        "saved_scene": [
            Targeted("scene/layout.npz", "a tree's shade NaN",
                     edit_npz(lambda a: a["trees"].__setitem__((0, 5), np.nan))),
            Targeted("scene/tile/map.json", "tile at 0.8 m per pixel (not the layout's extent)",
                     edit_json(set_item(("meters_per_pixel",), 0.8))),
        ],
        "map": [
            Targeted("map/map.json", "origin [NaN, 250]", edit_json(set_item(("origin",), [float("nan"), 250.0]))),
            Targeted("map/map.json", "meters_per_pixel true", edit_json(set_item(("meters_per_pixel",), True))),
            Targeted("map/labels.png", "labels as a 16-bit PNG", as_png_8bit),
        ],
        "sequence": [
            Targeted("seq/frames.npz", "a NaN pose of a posed frame",
                     edit_npz(lambda a: a["poses"].__setitem__((1, 0), np.nan))),
            Targeted("seq/frames.npz", "an infinite timestamp",
                     edit_npz(lambda a: a["timestamps"].__setitem__(2, np.inf))),
            Targeted("seq/depth/000001.png", "depth as an 8-bit PNG", as_png_8bit),
            Targeted("seq/sequence.json", "camera.mount_height -1.6",
                     edit_json(set_item(("camera", "mount_height"), -1.6))),
            Targeted("seq/sequence.json", "num_frames 2 (frames.npz has 3)", edit_json(set_item(("num_frames",), 2))),
            Targeted("seq/sequence.json", "meta.geo_frame.lat0 NaN",
                     edit_json(set_item(("meta", "geo_frame", "lat0"), float("nan")))),
        ],
        "dictionary_npz": [
            Targeted("dictionary.npz", "a frame index past the poses",
                     edit_npz(lambda a: a["frame"].__setitem__(0, len(a["poses"])))),
        ],
        "projections_pt": [
            Targeted("projections.pt", "W_g scaled by 1e30 (finite, but distances overflow)", edit_torch(scale("W_g"))),
        ],
        "build_dir": [
            Targeted("build/satellite_table_full.npz", "table ids past the dictionary",
                     edit_npz(lambda a: a["ids"].__setitem__((0, 0), 10**6)), "same"),
            Targeted("build/build.json", "camera.fx 0", edit_json(set_item(("camera", "fx"), 0))),
            Targeted("build/build.json", "config.features 'nonsense'",
                     edit_json(set_item(("config", "features"), "nonsense"))),
        ],
        "autoloc_entry": [
            Targeted("entry/autoloc.json", "key.aliasing 2", edit_json(set_item(("key", "aliasing"), 2.0))),
        ],
        "fcn_weights": [
            Targeted("fcn.pt", "widths [1000000, 1000000] (a network of terabytes)",
                     edit_torch(set_item(("views", "ground", "widths"), [10**6, 10**6]))),
            Targeted("fcn.pt", "input_scale NaN",
                     edit_torch(set_item(("views", "ground", "input_scale"), float("nan")))),
        ],
        "kitti_calib": [
            Targeted("2011_09_26/calib_imu_to_velo.txt", "T.z 1e300 (camera far below the ground)",
                     edit_tokens(2, 3, "1e300")),
        ],
        "kitti_oxts": [
            Targeted(f"{DRIVE}/oxts/data/0000000000.txt", "first frame lat 89.9 (no Mercator origin)",
                     edit_tokens(0, 0, "89.9")),
        ],
        "kitti_images": [
            Targeted(f"{DRIVE}/image_02/data/0000000001.png", "a JPEG under the PNG's name", jpeg_under_png_name),
        ],
        "malaga_gps": [
            Targeted(f"{MALAGA}/{MALAGA}_all-sensors_GPS.txt", "first fix lat -1.56 rad (no Mercator origin)",
                     edit_tokens(0, 1, "-1.56")),
        ],
        "world_file_png": [
            Targeted("map.pgw", "C = 1e20 (GDAL's transformer loops on it)", edit_tokens(4, 0, "1e20")),
        ],
        "world_file_jpeg": [Targeted("map.jpg", "JPEG truncated by 200 bytes", truncate_by(200))],
        "geotiff": [Targeted("map.tif", "origin at x = 1e20", geotiff_far_away)],
    }


# --- the formats ---------------------------------------------------------------------------------------
def _formats(tiles: list[str], kitti_oxts: list[str], kitti_png: list[str], malaga_jpg: list[str]) -> list[Format]:
    n = lambda k: max(1, int(round(k * SCALE)))  # noqa: E731
    seq_free = dict(free=(("meta",),), bound=(("meta", "geo_frame"),))
    return [
        Format("scene_yaml", make_scene_yaml, [Target("fuzz.yaml", "yaml", free=(("description",),))],
               load_scene_yaml, digest_scene, check_scene, n(80)),
        Format("saved_scene", make_saved_scene, [
            Target("scene/scene.json", "json", free=(("spec", "description"),), weight=2),
            Target("scene/layout.npz", "npz", weight=3,
                   required=("ground_rgb", "ground_labels", "alias_source", "bld_nverts", "bld_verts", "bld_params",
                             "trees", "cars")),
            Target("scene/tile/map.json", "json"), Target("scene/tile/map.png", "png"),
            Target("scene/tile/labels.png", "png", image={"depth": "reject"})],
            load_saved_scene, digest_scene, check_scene, n(80)),
        Format("map", make_map, [Target("map/map.json", "json", weight=3), Target("map/map.png", "png", weight=2),
                                 Target("map/labels.png", "png", image={"depth": "reject"})],
               load_map_dir, digest_satmap, check_satmap, n(80)),
        Format("sequence", make_sequence, [
            Target("seq/sequence.json", "json", weight=3, **seq_free),
            Target("seq/frames.npz", "npz", weight=3, required=("poses", "timestamps", "has_pose")),
            Target("seq/left/000000.png", "png"), Target("seq/right/000002.png", "png"),
            Target("seq/depth/000001.png", "png", image={"depth": "reject"}),
            Target("seq/labels/000001.png", "png", image={"depth": "reject"})],
            load_sequence_dir, digest_sequence, check_sequence, n(120)),
        Format("dictionary_npz", make_dictionary,
               [Target("dictionary.npz", "npz", required=("g", "s", "loc", "frame", "poses"))],
               load_dictionary, digest_dictionary, check_dictionary, n(70)),
        Format("satellite_features_npz", make_satfeat,
               [Target("satellite_features.npz", "npz", required=("features",))],
               load_satfeat, digest_satfeat, check_satfeat, n(60)),
        Format("projections_pt", make_projections, [Target("projections.pt", "torch")],
               load_projections, digest_projections, check_projections, n(60)),
        Format("build_dir", make_build, [
            Target("build/build.json", "json", weight=2,
                   free=tuple((k,) for k in ("database", "database_name", "map", "entries", "database_frames",
                                             "database_m", "satellite_features_s", "dictionary_s"))),
            Target("build/dictionary.npz", "npz", required=("g", "s", "loc", "frame", "poses")),
            Target("build/satellite_features.npz", "npz", required=("features",)),
            Target("build/projections.pt", "torch"),
            Target("build/satellite_table_full.npz", "npz", expect="same", delete="same", weight=3),
            Target("build/projection.json", "unused", delete="same", weight=0.5),
            Target("build/projection_loss.png", "unused", delete="same", weight=0.5)],
            load_build, digest_localizer, check_localizer, n(60)),
        Format("autoloc_entry", make_autoloc, [Target("entry/autoloc.json", "json", free=(("seconds",),))],
               load_autoloc, lambda k: k, check_autoloc, n(60)),
        Format("fcn_weights", make_fcn, [Target("fcn.pt", "torch", free=(("training",),))],
               load_fcn_file, digest_fcn, check_fcn, n(70)),
        Format("kitti_calib", make_kitti, [Target(f"2011_09_26/calib_{k}.txt", "text")
                                           for k in ("cam_to_cam", "imu_to_velo", "velo_to_cam")],
               load_kitti_drive, digest_real, check_kitti, n(80)),
        Format("kitti_oxts", make_kitti, [Target(p, "text", delete="valid") for p in kitti_oxts]
               + [Target(f"{DRIVE}/oxts/dataformat.txt", "unused", delete="same", weight=0.5)],
               load_kitti_drive, digest_real, check_kitti, n(70)),
        Format("kitti_timestamps", make_kitti, [
            Target(f"{DRIVE}/image_02/timestamps.txt", "text", weight=2),
            Target(f"{DRIVE}/image_03/timestamps.txt", "text", delete="same"),
            Target(f"{DRIVE}/oxts/timestamps.txt", "text", delete="same")],
            load_kitti_drive, digest_real, check_kitti, n(60)),
        Format("kitti_images", make_kitti, [Target(p, "png", delete="valid") for p in kitti_png],
               load_kitti_drive, digest_real, check_kitti, n(60)),
        Format("malaga_camera", make_malaga,
               [Target(f"{MALAGA}/camera_params_rectified_a=0_40x30.txt", "text")],
               load_malaga_extract, digest_real, check_sequence, n(70)),
        Format("malaga_gps", make_malaga, [Target(f"{MALAGA}/{MALAGA}_all-sensors_GPS.txt", "text")],
               load_malaga_extract, digest_real, check_sequence, n(70)),
        Format("malaga_images", make_malaga, [Target(p, "jpeg", delete="valid") for p in malaga_jpg],
               load_malaga_extract, digest_real, check_sequence, n(60)),
        Format("malaga_image_list", make_malaga, [Target(f"{MALAGA}/{MALAGA}_IMAGES.txt", "unused", delete="same")],
               load_malaga_extract, digest_real, check_sequence, n(20)),
        Format("geotiff", make_geotiff, [Target("map.tif", "tiff")], load_georef("map.tif"), digest_satmap,
               check_satmap, n(60)),
        Format("world_file_png", make_world_png, [Target("map.png", "png"), Target("map.pgw", "text", weight=2),
                                                  Target("map.prj", "text")],
               load_georef("map.png"), digest_satmap, check_satmap, n(60)),
        Format("world_file_jpeg", make_world_jpeg, [Target("map.jpg", "jpeg", weight=2), Target("map.jgw", "text")],
               load_georef("map.jpg"), digest_satmap, check_satmap, n(40)),
        Format("xyz_tiles", make_tiles, [Target(p, "png") for p in tiles], load_georef("tiles"), digest_satmap,
               check_satmap, n(40)),
    ]


def _listing(tmp: Path) -> dict[str, list[str]]:
    """Relative paths of the per-frame files the formats mutate (from one copy of each artefact)."""
    make_kitti(tmp / "k")
    make_malaga(tmp / "m")
    make_tiles(tmp / "t")
    drive = tmp / "k" / DRIVE
    return {
        "tiles": sorted(str(p.relative_to(tmp / "t")) for p in (tmp / "t" / "tiles").rglob("*.png")),
        "kitti_oxts": sorted(str(p.relative_to(tmp / "k")) for p in (drive / "oxts" / "data").glob("*.txt")),
        "kitti_png": sorted(str(p.relative_to(tmp / "k")) for p in drive.glob("image_0[23]/data/*.png")),
        "malaga_jpg": _malaga_images(tmp / "m"),
    }


@pytest.fixture(scope="module")
def formats(tmp_path_factory) -> dict[str, Format]:
    listing = _listing(tmp_path_factory.mktemp("listing"))
    out = {f.name: f for f in _formats(**listing)}
    for name, cases in targeted().items():
        out[name].targeted = cases
    return out


FORMAT_NAMES = ["scene_yaml", "saved_scene", "map", "sequence", "dictionary_npz", "satellite_features_npz",
                "projections_pt", "build_dir", "autoloc_entry", "fcn_weights", "kitti_calib", "kitti_oxts",
                "kitti_timestamps", "kitti_images", "malaga_camera", "malaga_gps", "malaga_images",
                "malaga_image_list", "geotiff", "world_file_png", "world_file_jpeg", "xyz_tiles"]


@pytest.mark.parametrize("name", FORMAT_NAMES)
def test_fuzz(name, formats, tmp_path):
    fmt = formats[name]
    counts, results = run_format(fmt, tmp_path, seed=int(os.environ.get("SATLOC_FUZZ_SEED", "0")))
    COUNTS[name] = dict(counts, minimum=fmt.cases)
    failed = [r for r in results if r.outcome == "FAIL"]
    lines = [f"case {r.index} [{r.mutation.target if r.mutation else '?'}: "
             f"{r.mutation.op if r.mutation else '?'} (expect {r.mutation.expect if r.mutation else '?'})]: "
             f"{r.detail}" for r in failed[:FAILURES_SHOWN]]
    assert not failed, f"{name}: {len(failed)} of {len(results)} cases failed:\n" + "\n".join(lines)
    assert counts["tried"] >= fmt.cases


def test_fuzz_counts():
    """Every format that ran tried at least its minimum number of cases; the counts are reported."""
    if not COUNTS:
        pytest.skip("no fuzz format ran in this session")
    total = {k: sum(c[k] for c in COUNTS.values()) for k in ("tried", "loaded_same", "loaded_changed", "rejected",
                                                              "failed")}
    report = {"formats": COUNTS, "total": total}
    out = os.environ.get("SATLOC_FUZZ_REPORT")
    if out:
        from satloc.persist import write_json

        write_json(out, report)
    print("\nfuzz cases per format (tried: loaded same / loaded changed / rejected / failed)")
    for name, c in COUNTS.items():
        print(f"  {name:24s} {c['tried']:4d}: {c['loaded_same']:4d} / {c['loaded_changed']:4d} / "
              f"{c['rejected']:4d} / {c['failed']}")
    print(f"  {'total':24s} {total['tried']:4d}: {total['loaded_same']:4d} / {total['loaded_changed']:4d} / "
          f"{total['rejected']:4d} / {total['failed']}")
    short = {k: c for k, c in COUNTS.items() if c["tried"] < c["minimum"]}
    assert not short, f"formats below their minimum number of cases: {short}"
    assert set(COUNTS) <= set(FORMAT_NAMES)
