"""The ``satloc`` command line. It composes the method (:mod:`satloc`) and the simulator (:mod:`satloc_env`)."""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np

from satloc.device import HELP as DEVICE_HELP
from satloc.errors import ConfigError, SatlocError, SatlocWarning
from satloc_env.world.meshes import LOD_M


def _save_rgb(path: Path, img: np.ndarray) -> None:
    from satloc.persist import atomic_path

    with atomic_path(path, suffix=path.suffix) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{path}: could not write image")


def scene_picture(scene, max_px: int = 1400) -> np.ndarray:
    """The whole satellite tile with the scene's map drawn on it: building footprints (magenta), trees
    (green rings), the road graph's edges (yellow) and nodes (red: dead ends, white: junctions), and the
    database route (light blue)."""
    sm = scene.satmap
    img = sm.image.copy()
    k = 16   # sub-pixel drawing (shift=4)

    def px(xy):
        return np.round(sm.world_to_pixel(np.asarray(xy, np.float64)) * k).astype(np.int32)

    for b in scene.layout.buildings:
        cv2.polylines(img, [px(b.footprint).reshape(-1, 1, 2)], True, (255, 0, 255), 2, cv2.LINE_AA, shift=4)
    for t in scene.layout.trees:
        cv2.circle(img, tuple(px(t.center)), int(round(t.canopy_radius / sm.meters_per_pixel * k)), (60, 230, 60), 1,
                   cv2.LINE_AA, shift=4)
    rg = scene.road_graph
    for u, v, key in rg.graph.edges(keys=True):
        xy, _ = rg.edge_xy(u, v, key)
        cv2.polylines(img, [px(xy).reshape(-1, 1, 2)], False, (255, 220, 0), 3, cv2.LINE_AA, shift=4)
    for n, d in rg.graph.nodes(data=True):
        deg = rg.graph.degree(n)
        cv2.circle(img, tuple(px(d["xy"])), 5 * k, (255, 40, 40) if deg == 1 else (255, 255, 255), -1,
                   cv2.LINE_AA, shift=4)
    route = scene.routes[scene.spec.database_route]
    cv2.polylines(img, [px(route.points).reshape(-1, 1, 2)], False, (80, 200, 255), 1, cv2.LINE_AA, shift=4)
    s = min(1.0, max_px / max(img.shape[:2]))
    return cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else img


def route_overview(scene, poses: np.ndarray, max_px: int = 1400) -> np.ndarray:
    """The whole satellite tile with the route and the given poses drawn on it."""
    sm = scene.satmap
    img = sm.image.copy()
    route = scene.routes[scene.spec.database_route]
    uv = sm.world_to_pixel(route.points)
    cv2.polylines(img, [np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)], False, (80, 200, 255), 3,
                  cv2.LINE_AA, shift=4)
    for x, y, yaw in poses:
        a = sm.world_to_pixel(np.array([x, y]))
        b = sm.world_to_pixel(np.array([x + 6 * np.cos(yaw), y + 6 * np.sin(yaw)]))
        cv2.arrowedLine(img, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), (255, 40, 40), 2,
                        cv2.LINE_AA, tipLength=0.4)
    s = min(1.0, max_px / max(img.shape[:2]))
    return cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else img


def cmd_demo(args) -> int:
    """The main job on the default scene: record database and query passes, build the dictionary, learn the
    projections, localize every query with GO, NP, full and full refined by bird's-eye alignment, single
    images and tracked, print mean (std) errors and write pictures."""
    from satloc.config import from_dict
    from satloc_env.experiments.scene_run import ExperimentConfig, run_scene

    overrides = {"scene": args.scene, "database_frames": args.db_frames or None, "features": args.features}
    if args.localizer:
        overrides["localizers"] = list(args.localizer)
    if args.query_frames:
        overrides["query_frames"] = args.query_frames
    cfg = from_dict(ExperimentConfig, overrides, "demo options")
    log = (lambda *a, **k: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    s = run_scene(cfg, args.out, progress=not args.quiet, log=log)
    out = Path(args.out)
    print(f"satloc demo: {s['scene']}, database {s['database_m']:.0f} m, {s['queries']} queries (revisit: "
          f"other lane, appearance and occluders)")
    _print_rows(s)
    pics = sorted(p.name for p in out.glob("*.png"))
    print(f"  pictures in {out}: {', '.join(pics)}")
    stages = _demo_artefacts(out)
    sizes = ", ".join(f"{p.name}/ {_mb(p):.0f} MB" for p in stages if p.is_dir())
    if args.keep_artefacts:
        print(f"  artefacts in {out} (a rerun reuses them; --no-keep-artefacts deletes them): {sizes}, "
              f"localization_<mode>.npz/.json, odometry and stage files")
    else:
        for p in stages:
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink()
        print(f"  deleted the artefacts ({sizes}, the localizations and stage files); kept the pictures and "
              f"summary.json")
    return 0


def _print_rows(s: dict) -> None:
    """The modes' rows of a summary (:func:`satloc_env.experiments.scene_run.localize_and_report`), then the
    reference floors' and the user's localizers'."""
    rows = list(s["modes"].items()) + [(r.get("name", k), r) for k, r in s.get("localizers", {}).items()]
    for name, r in rows:
        qps = f"  {r['queries_per_s']:.1f} queries/s" if r.get("queries_per_s") else ""
        print(f"  {name:16s}  mean {r['mean_m']:.2f} m (std {r['std_m']:.2f})  median {r['median_m']:.2f} m  "
              f"{100 * r['within_1m']:.0f} % within 1 m{qps}")


def _with_localizers(config: dict, specs: list[str] | None, nested: bool = False) -> dict:
    """``config`` with ``--localizer`` specs added to its ``localizers`` (``nested``: its ``experiment``'s, for
    the sweep and the gap curve)."""
    if not specs:
        return config
    config = dict(config)
    if nested:
        e = dict(config.get("experiment") or {})
        e["localizers"] = list(e.get("localizers") or []) + list(specs)
        config["experiment"] = e
    else:
        config["localizers"] = list(config.get("localizers") or []) + list(specs)
    return config


def _demo_artefacts(out: Path) -> list[Path]:
    """What ``satloc demo`` writes besides its pictures and ``summary.json``: the recording, the build, the
    per-mode localizations, the visual odometry and the stage stamps."""
    names = ["rec", "build", "record.json", "build_stage.json", "projection_stage.json", "odometry_visual.npz"]
    return [out / n for n in names if (out / n).exists()] + sorted(out.glob("localization_*"))


def _mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def cmd_experiment(args) -> int:
    import yaml

    from satloc_env.experiments.scene_run import aliasing, markdown_table
    from satloc_env.experiments.tables import table1

    config = {}
    if args.config:
        p = Path(args.config)
        if not p.is_file():
            raise SatlocError(f"{p}: config file not found")
        config = yaml.safe_load(p.read_text()) or {}
    log = (lambda *a, **k: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    if args.ray is not None and args.which not in ("table1", "table2", "sweep", "gap", "fidelity"):
        raise SatlocError(f"--ray: only table1, table2, sweep, gap and fidelity run on Ray, not {args.which}")
    from satloc_env.experiments.scale import Runner

    with Runner(ray=args.ray is not None, address=args.ray, exact=args.ray_threads == "serial") as runner:
        if args.which == "table2":
            from satloc_env.experiments.tables import table2

            table2(args.out, config, progress=not args.quiet, log=log, runner=runner)
            print((Path(args.out) / "table2.md").read_text(), end="")
            print(f"written: {Path(args.out) / 'table2.csv'}, {Path(args.out) / 'pr_curves.png'}")
            return 0
        if args.localizer and args.which not in ("table1", "sweep", "gap"):
            raise SatlocError(f"--localizer: table1, sweep and gap grade a user's localizer, not {args.which}")
        if args.which in ("sweep", "gap"):
            from satloc_env.experiments.tables import gap_curve, sweep

            config = _with_localizers(config, args.localizer, nested=True)

            (sweep if args.which == "sweep" else gap_curve)(args.out, config, progress=not args.quiet, log=log,
                                                            runner=runner)
            print((Path(args.out) / "sweep.md").read_text(), end="")
            extra = f", {Path(args.out) / 'gap.png'}" if args.which == "gap" else ""
            print(f"written: {Path(args.out) / 'sweep.csv'}, {Path(args.out) / 'sweep.png'}{extra}")
            return 0
        if args.which == "fidelity":
            from satloc_env.experiments.fidelity import fidelity

            fidelity(args.out, config, progress=not args.quiet, log=log, runner=runner)
            print((Path(args.out) / "fidelity.md").read_text(), end="")
            print(f"written: {Path(args.out) / 'fidelity.csv'}, {Path(args.out) / 'fidelity.json'}")
            return 0
        if args.which == "table1":
            config = _with_localizers(config, args.localizer)
            rows = table1(args.out, tuple(args.scenes), config, progress=not args.quiet, log=log, runner=runner)
            print(markdown_table(rows), end="")
            print(f"written: {Path(args.out) / 'table1.csv'}")
            return 0
    if args.which == "tune":
        from satloc_env.experiments.tune import tune

        res = tune(args.out, config, progress=not args.quiet, log=log)
        print((Path(args.out) / "tune.md").read_text(), end="")
        print("chosen: " + ", ".join(f"{k}={v}" for k, v in res["chosen"].items()))
        print(f"written: {Path(args.out) / 'tune.json'}")
        return 0
    if args.which == "aliasing":
        aliasing(args.out, tuple(args.scenes), config, progress=not args.quiet, log=log)
        print((Path(args.out) / "aliasing.md").read_text(), end="")
        print(f"written: {Path(args.out) / 'aliasing.csv'}")
    return 0


def cmd_view(args) -> int:
    """A Rerun recording (.rrd) of what a localizer did: an experiment folder's methods query by query, or an
    episode of an environment driven by its autopilot (satloc_env/envs/viewer.py)."""
    if (args.folder is None) == (args.scene is None):
        raise SatlocError("satloc view: give an experiment folder or --scene (an episode to drive), not both")
    if args.folder is not None:
        from satloc_env.experiments.view import view_folder

        out = args.out or str(Path(args.folder) / "view.rrd")
        s = view_folder(args.folder, out, images=not args.no_images, progress=not args.quiet)
        print(f"satloc view: {len(s['methods'])} methods over {s['queries']} queries"
              f"{' with their stereo pairs' if s['images'] else ''}: {', '.join(s['methods'])}")
    else:
        from satloc_env.envs.viewer import episode_to_rrd

        out = args.out or "episode.rrd"
        kw = {"scene": args.scene, "localizer": args.localizer or "cross", "localize_every": args.localize_every}
        if args.track:
            kw["localizer_track"] = True
        s = episode_to_rrd("satloc/SatLoc-v0", out, steps=args.steps, seed=args.seed, **kw)
        err = "" if s["mean_error_m"] is None else f", mean error {s['mean_error_m']:.2f} m"
        print(f"satloc view: {args.scene}, {s['steps']} localizations by {kw['localizer']}{err}")
    print(f"written: {out} (open it with: rerun {out})")
    return 0


def cmd_evaluate(args) -> int:
    """The method on replayed real data: a KITTI raw drive or a Malaga extract, its queries (another drive or
    a split of the same one) and a georeferenced satellite image (satloc_env/experiments/evaluate.py)."""
    from satloc_env.experiments.evaluate import EvaluateConfig, evaluate

    overrides = {"resolution": args.resolution, "mpp": args.mpp, "split": args.split,
                 "modes": list(args.modes) if args.modes else None}
    if args.queries is not None and args.split is not None:
        raise SatlocError("give either --queries (another drive) or --split (random:F or passes), not both")
    if args.localizer:
        overrides["localizers"] = list(args.localizer)
    cfg = _stage_config(EvaluateConfig, args.config, overrides)
    if args.localizer:   # added to those of the configuration file
        base = _stage_config(EvaluateConfig, args.config, {})
        cfg = dataclasses.replace(cfg, localizers=tuple(base.localizers) + tuple(args.localizer))
    log = (lambda *a, **k: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    reader = "malaga" if args.malaga else "kitti"
    s = evaluate(args.malaga or args.database, args.satellite, args.out, cfg, queries=args.queries, reader=reader,
                 progress=not args.quiet, log=log)
    print(f"satloc evaluate: {s['sequence']}, database {s['database_frames']} frames ({s['database_m']:.0f} m), "
          f"{s['queries']} queries; {s['split']}")
    if "lidar_mosaic" in s:
        print(f"  map: {s['map_kind']}: {s['satellite']}, made from this drive's own images and LiDAR "
              f"({100 * s['lidar_mosaic']['covered_fraction']:.1f} % of it covered); these errors do not measure "
              f"localization against satellite imagery")
    _print_rows(s)
    print(f"written: {Path(args.out) / 'results.csv'}, {Path(args.out) / 'results.md'}, pictures in {args.out}")
    return 0


def cmd_record(args) -> int:
    from satloc_env.envs.record import PassConfig, RecordConfig, record_passes

    wander = {k: v for k, v in (("wander_m", args.wander), ("speed_wander", args.speed_wander)) if v is not None}
    cfg = RecordConfig(
        scene=args.scene, resolution=args.resolution, aliasing=args.aliasing, satellite_gap=args.satellite_gap,
        database=PassConfig(lane_offset_m=args.db_lane, spacing_m=args.db_spacing, max_frames=args.max_frames,
                            seed=args.seed, **wander),
        query=PassConfig(lane_offset_m=args.query_lane, spacing_m=args.query_spacing, max_frames=args.max_frames,
                         occlusion=args.occlusion, appearance=args.appearance, change=args.change,
                         seed=args.seed + 1, **wander),
    )
    db, q = record_passes(cfg, args.out, progress=not args.quiet)
    print(json.dumps({"out": args.out, "database_frames": len(db), "database_m": round(db.path_length(), 1),
                      "query_frames": len(q), "query_m": round(q.path_length(), 1)}))
    return 0


def _detail_m(text: str) -> float | None:
    """``--detail-m``: metres (a number >= 0) or ``none``."""
    if text.strip().lower() == "none":
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected metres or 'none', got {text!r}") from None
    if not v >= 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0 or 'none', got {text!r}")
    return v


def _unit(text: str) -> float:
    """A number from 0 to 1 (``--sensor``, ``--attitude``)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}")
    return v


def cmd_bench(args) -> int:
    if args.what == "env":
        from satloc_env.experiments.bench import bench_env

        for n in args.num_envs:
            print(json.dumps(bench_env(args.resolution, args.steps, args.scene or "city", num_envs=n,
                                       detail_m=args.detail_m, sensor=args.sensor, attitude=args.attitude)),
                  flush=True)
    elif args.what == "startup":
        from satloc_env.experiments.bench import bench_startup

        for row in bench_startup(args.scene or "city", work=args.work or None):
            print(json.dumps(row), flush=True)
    elif args.what == "crossview":
        from satloc_env.experiments.bench import bench_crossview

        for row in bench_crossview(args.scene or "city", args.frames or 40, work=args.work or None, progress=not args.quiet):
            print(json.dumps(row), flush=True)
    elif args.what == "active":
        from satloc_env.experiments.bench import bench_active

        for row in bench_active(args.scene or "active_grid", args.episodes):
            print(json.dumps(row), flush=True)
    elif args.what == "osm":
        from satloc_env.experiments.bench import bench_osm

        for row in bench_osm(tuple(args.ways), args.work or None):
            print(json.dumps(row), flush=True)
    elif args.what == "vo":
        from satloc_env.experiments.bench import bench_vo

        for row in bench_vo(args.scene or "residential", args.frames or 250, args.work or None, args.kitti or None,
                            progress=not args.quiet):
            print(json.dumps(row), flush=True)
    else:
        from satloc_env.experiments.bench import bench_localize

        for row in bench_localize(args.sizes_km, args.work or None, scene=args.scene or "loop",
                                  queries=args.queries, progress=not args.quiet, device=args.device):
            print(json.dumps(row), flush=True)
    return 0


def cmd_agent(args) -> int:
    if args.what == "evaluate":
        from satloc_env.agents.evaluate import evaluate_agents

        cfg = dict(agents=tuple(a.strip() for a in args.agents.split(",") if a.strip()), episodes=args.episodes,
                   seed=10_000 if args.seed is None else args.seed, policy=args.policy)
        if args.maps:
            cfg["maps"] = tuple(args.maps)
        if args.config:
            cfg["env"] = _yaml_dict(args.config)
        evaluate_agents(cfg, args.out, progress=not args.quiet)
    elif args.what == "train":
        from satloc_env.agents.train import train_agent

        train_agent(args.out, args.timesteps, 0 if args.seed is None else args.seed, args.maps[0] if args.maps else "active_grid",
                    env=_yaml_dict(args.config) if args.config else None, progress=not args.quiet)
    else:
        from satloc_env.envs.active_map import build_active_map

        if not args.scene:
            raise ConfigError("agent map: --scene is required")
        build_active_map(dict(_yaml_dict(args.config) if args.config else {}, scene=args.scene), args.work or args.out,
                         out=Path(args.out) / f"{Path(args.scene).stem}.npz", progress=not args.quiet)
    return 0


def _yaml_dict(path: str) -> dict:
    import yaml

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"--config {p}: file not found")
    try:
        d = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"--config {p}: not valid YAML ({e})") from e
    if not isinstance(d, dict):
        raise ConfigError(f"--config {p}: expected a mapping of settings")
    return d


def cmd_scene(args) -> int:
    from satloc_env.envs.record import check_scene_routes
    from satloc_env.world.scene import load_scene

    scene = load_scene(args.scene, args.aliasing, args.satellite_gap)
    check_scene_routes(scene)   # every route drivable by the autopilot at the recorder's lane offsets
    if args.save:
        scene.save(args.save)
    if args.picture:
        _save_rgb(Path(args.picture), scene_picture(scene))
    print(json.dumps(scene.summary()))
    return 0


def _stage_config(cls, path: str | None, overrides: dict):
    """A stage's typed config from an optional YAML file plus command-line overrides (unknown keys raise)."""
    import yaml

    from satloc.config import from_dict

    data: dict = {}
    if path:
        p = Path(path)
        if not p.is_file():
            raise SatlocError(f"{p}: config file not found")
        data = yaml.safe_load(p.read_text()) or {}
    data.update({k: v for k, v in overrides.items() if v is not None})
    return from_dict(cls, data, f"{path}:" if path else "config")


def cmd_build(args) -> int:
    from satloc.pipeline import BuildConfig, build

    cfg = _stage_config(BuildConfig, args.config, {"features": args.features, "device": args.device})
    print(json.dumps(build(args.database, args.map, args.out, cfg, progress=not args.quiet)))
    return 0


def cmd_train_projection(args) -> int:
    from satloc.features.projection import ProjectionConfig
    from satloc.pipeline import train_projection

    p = train_projection(args.build, _stage_config(ProjectionConfig, args.config, {"device": args.device}),
                         progress=not args.quiet)
    print(json.dumps({"epochs": len(p.loss_curve), "converged": p.converged, "loss_first": p.loss_curve[0],
                      "loss_last": p.loss_curve[-1], "plot": str(Path(args.build) / "projection_loss.png")}))
    return 0


def _query_odometry(args, seq):
    """--track's motion between the frames of ``seq``: stereo visual odometry, or the poses plus noise."""
    from satloc.tracking.track import noisy_odometry

    if args.odometry == "visual":
        from satloc.tracking.vo import visual_odometry

        return visual_odometry(seq, progress=not args.quiet)
    if not np.all(np.isfinite(seq.poses)):
        raise SatlocError(f"{args.queries}: --odometry noisy_truth simulates odometry from the frames' "
                          "poses, and some frames have none")
    return noisy_odometry(seq.poses, tuple(args.odometry_noise), args.odometry_seed)


def cmd_localize_no_database(args) -> int:
    from satloc.localizers.crossview import CrossViewConfig
    from satloc.pipeline import localize_no_database
    from satloc.satmap import SatelliteMap

    if args.build:
        raise SatlocError(f"--no-database localizes against the satellite map alone; it takes no build directory "
                          f"(got {args.build!r})")
    if not args.satellite:
        raise SatlocError("--no-database needs --satellite: a satellite map directory (map.json inside) or a "
                          "georeferenced image")
    for flag in ("mode", "refine", "device"):
        if getattr(args, flag):
            raise SatlocError(f"--{flag} is an option of the database localizer, not of --no-database")
    from satloc.datasets import open_sequence

    seq = open_sequence(args.queries)   # a satloc sequence, a KITTI raw drive or a Malaga extract
    sat = Path(args.satellite)
    if (sat / "map.json").is_file():
        satmap = SatelliteMap.load(sat)
    elif sat.exists():
        from satloc.geodata.georef import load_map

        frame = seq.geo_frame
        if frame is None:
            raise SatlocError(f"{sat}: a georeferenced image needs the sequence's geo frame (its poses in a local "
                              f"metric frame of the Earth); sequence {args.queries} has none: give a map directory")
        xy = np.asarray(seq.poses, np.float64)[:, :2]
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if len(xy) == 0:
            raise SatlocError(f"{args.queries}: no frame has a pose to take the map's region from")
        m = (20.0 if args.radius is None else args.radius) + 60.0
        satmap = load_map(sat, None, frame=frame, region=(float(xy[:, 0].min() - m), float(xy[:, 1].min() - m),
                                                          float(xy[:, 0].max() + m), float(xy[:, 1].max() + m)))
    else:
        raise SatlocError(f"{sat}: satellite map not found")
    roads = None
    if args.roads:
        from satloc.geodata.vectors import read_road_lines

        roads = read_road_lines(args.roads)
    cfg = _stage_config(CrossViewConfig, args.config, {})
    odometry = _query_odometry(args, seq) if args.track else None
    s = localize_no_database(seq, satmap, args.out or ".", args.prior or "truth",
                          20.0 if args.radius is None else args.radius, 10.0 if args.yaw is None else args.yaw,
                          0 if args.prior_seed is None else args.prior_seed, odometry, roads, cfg,
                          progress=not args.quiet)
    print(json.dumps(s))
    return 0


def cmd_train_crossview(args) -> int:
    from satloc_env.experiments.train_crossview import train_crossview_scenes

    cfg = _yaml_dict(args.config) if args.config else {}
    if args.scenes:
        cfg["scenes"] = list(args.scenes)
    if args.frames is not None:
        cfg["frames"] = args.frames
    if args.epochs is not None:
        cfg.setdefault("train", {})["epochs"] = args.epochs
    log = (lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    s = train_crossview_scenes(args.out, cfg, progress=not args.quiet, log=log)
    print(json.dumps({k: s[k] for k in ("trained_on", "frames", "best_epoch", "train_s")}
                     | {"weights": str(Path(args.out) / "crossview.pt")}))
    return 0


def cmd_localize(args) -> int:
    if args.no_database:
        return cmd_localize_no_database(args)
    if not args.build:
        raise SatlocError("localize: give a build directory (satloc build), or --no-database --satellite MAP")
    for flag in ("satellite", "roads", "prior", "radius", "yaw", "prior_seed"):
        if getattr(args, flag) is not None:
            raise SatlocError(f"--{flag.replace('_', '-')} is an option of --no-database")
    from satloc.localizers.database import LocalizerConfig
    from satloc.pipeline import localize

    cfg = _stage_config(LocalizerConfig, args.config, {"mode": args.mode, "refine": True if args.refine else None,
                                                       "track": True if args.track else None,
                                                       "device": args.device})
    odometry, queries = None, args.queries
    if cfg.track:  # the motion between the sequence's frames: stereo visual odometry, or the poses plus noise
        from satloc.sequence import Sequence

        seq = queries = Sequence.load(args.queries)
        odometry = _query_odometry(args, seq)
    s = localize(args.build, queries, cfg, args.out or args.build, progress=not args.quiet, odometry=odometry)
    s.pop("errors")
    print(json.dumps(s))
    return 0


def build_parser() -> argparse.ArgumentParser:
    from satloc import __version__

    p = argparse.ArgumentParser(prog="satloc", description=__doc__)
    p.add_argument("--version", action="version", version=f"satloc {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="record, build, learn, localize with GO/NP/full/full+align, tracked too, on the default scene; "
                                    "print errors, write pictures")
    d.add_argument("--scene", default="city")
    d.add_argument("--out", default="satloc_demo")
    d.add_argument("--db-frames", type=int, default=400,
                   help="database frames to record (one every ~1.6 m at the default speed); 0: the whole route")
    d.add_argument("--query-frames", type=int, default=None)
    d.add_argument("--features", choices=["rgb", "semantic", "default"], default="default")
    d.add_argument("--keep-artefacts", action=argparse.BooleanOptionalAction, default=True,
                   help="keep the recording (rec/), the build (build/), the localizations and stage files beside "
                        "the pictures (default; a rerun reuses them, about 0.6 GB at the default size); "
                        "--no-keep-artefacts deletes them at the end")
    d.add_argument("--localizer", action="append", metavar="MODULE:NAME", help="a localizer of your own, graded beside the built-in ones: module:Name or path/to/file.py:Name (a class, a "
                    "function that makes one, or an instance with reset(context) and localize(query)); repeat for several")
    d.add_argument("--quiet", action="store_true")
    d.set_defaults(func=cmd_demo)

    ex = sub.add_parser("experiment", help="paper experiments on simulated scenes: table1; table2 (queries outside "
                                           "the map, every method, PR curves); sweep (every method over aliasing x "
                                           "occlusion x appearance x satellite gap); gap (each method's error "
                                           "against the satellite map's capture gap); aliasing (how often each "
                                           "single-image cue prefers a look-alike place); tune (the tuned "
                                           "settings chosen on a calibration scene no table tests on); fidelity "
                                           "(the default world against the paper's real KITTI figures and real "
                                           "street frames)")
    ex.add_argument("which", choices=["table1", "table2", "sweep", "gap", "aliasing", "tune", "fidelity"])
    ex.add_argument("--out", required=True)
    ex.add_argument("--scenes", nargs="+", default=["city", "residential"])
    ex.add_argument("--config", help="YAML with ExperimentConfig fields (satloc_env/experiments/scene_run.py); table2: "
                                     "Table2Config, sweep and gap: SweepConfig fields (satloc_env/experiments/tables.py; gap: "
                                     "over GAP_CURVE there), tune: "
                                     "TuneConfig fields (satloc_env/experiments/tune.py); --scenes is not used by these)")
    ex.add_argument("--localizer", action="append", metavar="MODULE:NAME", help="table1, sweep, gap: " + "a localizer of your own, graded beside the built-in ones: module:Name or path/to/file.py:Name (a class, a "
                    "function that makes one, or an instance with reset(context) and localize(query)); repeat for several")
    ex.add_argument("--quiet", action="store_true")
    ex.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                    help="table1, table2, sweep: run the independent units (scenes, protocols, passes, knob "
                         "combinations) as Ray tasks: a local Ray cluster of this machine's cores, or the cluster at "
                         "ADDRESS (e.g. auto, or host:6379 after `ray start --head`); the same CSV as without it. "
                         "Needs pip install -e '.[ray]' (satloc_env/experiments/scale.py)")
    ex.add_argument("--ray-threads", choices=["serial", "cpus"], default="serial",
                    help="with --ray: torch and BLAS threads of each task: serial (default) as many as a serial run "
                         "here, so that the CSV is byte-identical to a serial run's (more threads than cores while "
                         "several tasks compute); cpus: the task's CPUs (no oversubscription; their sums depend on "
                         "the thread count, so numbers may differ in the last digits)")
    ex.set_defaults(func=cmd_experiment)

    ev = sub.add_parser("evaluate", help="the method on real data: a KITTI raw drive or Malaga extract against a "
                                         "georeferenced satellite image; per-mode errors, results.csv, pictures")
    src = ev.add_mutually_exclusive_group(required=True)
    src.add_argument("--database", metavar="KITTI_DRIVE_DIR",
                     help="KITTI raw drive folder <date>/<date>_drive_<nnnn>_sync (the database)")
    src.add_argument("--malaga", metavar="EXTRACT_DIR", help="Malaga Urban extract folder (the database)")
    ev.add_argument("--queries", metavar="DIR", help="another drive / extract of the same dataset as the queries")
    ev.add_argument("--split", default=None,
                    help="without --queries: 'random:F' = a seeded random fraction F of the frames is the database, "
                         "the rest the queries (random:0.4 = 40 %% database, 60 %% queries; the default), or "
                         "'passes' = the first pass is the database, later passes over it the queries")
    ev.add_argument("--satellite", required=True, metavar="MAP",
                    help="georeferenced satellite image: GeoTIFF, image + world file, or XYZ tile folder; or "
                         "'lidar-mosaic' (KITTI drives with LiDAR: a stand-in made from the --database drive's own "
                         "images, written to OUT/lidar_mosaic.tif: a self-consistency check, not a satellite "
                         "evaluation)")
    ev.add_argument("--out", required=True, help="output folder (stages in it are reused by later runs)")
    ev.add_argument("--resolution", choices=["half", "full"], default=None,
                    help="half (default): images and camera resized by 1/2 (KITTI: 621x188); full: the data's size")
    ev.add_argument("--mpp", type=float, default=None, help="satellite metres per pixel (default 0.2)")
    ev.add_argument("--modes", nargs="+", default=None, metavar="MODE",
                    help="modes to localize with: go np full full+align go+track np+track full+track "
                         "full+track+align (default: all of these, as table1)")
    ev.add_argument("--config", help="YAML with EvaluateConfig fields (satloc_env/experiments/evaluate.py), e.g. 'margin_m: "
                                     "20' (the map's margin around the route)")
    ev.add_argument("--localizer", action="append", metavar="MODULE:NAME", help="a localizer of your own, graded beside the built-in ones: module:Name or path/to/file.py:Name (a class, a "
                    "function that makes one, or an instance with reset(context) and localize(query)); repeat for several")
    ev.add_argument("--quiet", action="store_true")
    ev.set_defaults(func=cmd_evaluate)

    vw = sub.add_parser("view", help="a Rerun recording (.rrd) of what a localizer did: an experiment folder's "
                        "methods query by query, or an episode driven on a scene (pip install 'satloc[viewer]')")
    vw.add_argument("folder", nargs="?", help="an experiment folder (satloc demo, a Table I scene folder, satloc "
                    "evaluate)")
    vw.add_argument("--scene", help="instead of a folder: drive an episode of SatLoc-v0 on this scene")
    vw.add_argument("--localizer", help="with --scene: the localizer (cross, auto, a build directory or "
                    "module:Name; default cross)")
    vw.add_argument("--track", action="store_true", help="with --scene: track the built-in localizer")
    vw.add_argument("--steps", type=int, default=100, help="with --scene: steps to drive")
    vw.add_argument("--localize-every", type=int, default=1, help="with --scene: localize every n-th step")
    vw.add_argument("--seed", type=int, default=0)
    vw.add_argument("--no-images", action="store_true", help="with a folder: leave out the stereo pairs")
    vw.add_argument("--out", help="the .rrd to write (default: FOLDER/view.rrd, or episode.rrd)")
    vw.add_argument("--quiet", action="store_true")
    vw.set_defaults(func=cmd_view)

    r = sub.add_parser("record", help="record database and query passes of a scene")
    r.add_argument("--scene", default="city")
    r.add_argument("--out", required=True)
    r.add_argument("--resolution", choices=["half", "full"], default="half")
    r.add_argument("--aliasing", type=float, default=None)
    r.add_argument("--satellite-gap", type=float, default=None,
                   help="the map as a capture of the world in [0, 1] (satloc_env.world.capture; default: the scene's)")
    r.add_argument("--wander", type=float, default=None,
                   help="both passes' lateral drift in the lane, std in metres (satloc_env.envs.vehicle.Wander; "
                        "default 0.3; 0: exactly on the lane offset)")
    r.add_argument("--speed-wander", type=float, default=None,
                   help="both passes' speed drift, relative std (default 0.1)")
    r.add_argument("--db-lane", type=float, default=-1.75)
    r.add_argument("--query-lane", type=float, default=-0.75)
    r.add_argument("--db-spacing", type=float, default=1.0)
    r.add_argument("--query-spacing", type=float, default=10.0)
    r.add_argument("--occlusion", type=float, default=0.3)
    r.add_argument("--appearance", type=float, default=0.5)
    r.add_argument("--change", type=float, default=0.5,
                   help="the query pass's revisit change of the world in [0, 1] (satloc_env.world.revisit)")
    r.add_argument("--max-frames", type=int, default=None)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=cmd_record)

    b = sub.add_parser("bench", help="print benchmark figures as JSON lines")
    b.add_argument("what", choices=["env", "localize", "vo", "active", "osm", "crossview", "startup"])
    b.add_argument("--resolution", choices=["half", "full"], default="half")
    b.add_argument("--steps", type=int, default=2000, help="env: steps timed (of all cars together)")
    b.add_argument("--num-envs", type=int, nargs="+", default=[1],
                   help="env: cars stepped together, one run each (e.g. 1 8): 1 is the single environment, more the "
                        "batched vector environment (satloc_env.envs.vector)")
    b.add_argument("--scene", default=None, help="env: city; localize: loop (the longest route); vo: residential; "
                                                 "active: the active map (active_grid); crossview, startup: city")
    b.add_argument("--episodes", type=int, default=20, help="active: episodes per agent")
    b.add_argument("--detail-m", type=_detail_m, default=LOD_M, metavar="M|none",
                   help=f"env: metres within which objects keep their full detail (default {LOD_M:g}; none: "
                        "everywhere; the environment's detail_m)")
    b.add_argument("--sensor", type=_unit, default=None, metavar="S",
                   help="env: the camera's noise, vignetting and motion blur, 0 to 1 (default: the environment's)")
    b.add_argument("--attitude", type=_unit, default=None, metavar="A",
                   help="env: the body's pitch and roll, 0 to 1 (default: the environment's)")
    b.add_argument("--ways", type=int, nargs="+", default=[1000, 10000],
                   help="osm: sizes of the synthetic OpenStreetMap extracts loaded (ways)")
    b.add_argument("--sizes-km", type=float, nargs="+", default=[0.25, 1.0, 4.0], help="localize: database sizes")
    b.add_argument("--queries", type=int, default=40, help="localize: queries timed per size")
    b.add_argument("--frames", type=int, default=None,
                   help="vo: frames of the simulated drive (one per simulator step, 0.8 m at 8 m/s; default 250); "
                        "crossview: frames 5 m apart (default 40)")
    b.add_argument("--kitti", help="vo: a KITTI raw drive folder (default: the excerpt in ../shared/realdata)")
    b.add_argument("--work", help="localize, vo, osm: folder for recordings and builds (reused; default: a temp dir)")
    b.add_argument("--device", default="auto", help=f"localize: {DEVICE_HELP}")
    b.add_argument("--quiet", action="store_true")
    b.set_defaults(func=cmd_bench)

    bl = sub.add_parser("build", help="build the ground-satellite dictionary of a database sequence")
    bl.add_argument("--database", required=True, help="database sequence directory")
    bl.add_argument("--map", required=True, help="satellite map directory")
    bl.add_argument("--out", required=True, help="build directory to write")
    bl.add_argument("--features", choices=["rgb", "semantic", "default"], default=None)
    bl.add_argument("--device", default=None, help=f"{DEVICE_HELP}; the FCN of the features")
    bl.add_argument("--config", help="YAML with BuildConfig fields")
    bl.add_argument("--quiet", action="store_true")
    bl.set_defaults(func=cmd_build)

    tp = sub.add_parser("train-projection", help="learn the projections W_g, W_s of a build")
    tp.add_argument("build")
    tp.add_argument("--config", help="YAML with ProjectionConfig fields")
    tp.add_argument("--device", default=None, help=DEVICE_HELP)
    tp.add_argument("--quiet", action="store_true")
    tp.set_defaults(func=cmd_train_projection)

    lo = sub.add_parser("localize", help="localize the frames of a query sequence against a build, or with "
                                         "--no-database against a satellite map alone")
    lo.add_argument("build", nargs="?", help="a build directory (satloc build); none with --no-database")
    lo.add_argument("--queries", required=True)
    lo.add_argument("--mode", choices=["full", "np", "go"], default=None)
    lo.add_argument("--refine", action="store_true", help="refine each estimate by bird's-eye alignment (satloc.tracking.align)")
    lo.add_argument("--track", action="store_true",
                    help="track the sequence with odometry (satloc.tracking.track)")
    lo.add_argument("--odometry", choices=("visual", "noisy_truth"), default="visual",
                    help="--track: stereo visual odometry of the frames (satloc.tracking.vo; the default) or the frames' "
                         "poses plus noise")
    lo.add_argument("--odometry-noise", type=float, nargs=2, default=[0.02, 0.01], metavar=("FRAC", "RAD"),
                    help="--odometry noisy_truth: noise std, fraction of the distance and radians per frame")
    lo.add_argument("--odometry-seed", type=int, default=0)
    lo.add_argument("--out", help="where to write results (default: the build directory; --no-database: the current one)")
    lo.add_argument("--device", default=None, help=f"{DEVICE_HELP}; the FCN of the query features")
    lo.add_argument("--config", help="YAML with LocalizerConfig fields (--no-database: CrossViewConfig fields)")
    lo.add_argument("--no-database", action="store_true",
                    help="localize with no database: each frame against --satellite within a prior (satloc.localizers.crossview)")
    lo.add_argument("--satellite", help="--no-database: a satellite map directory or a georeferenced image (with a "
                                        "sequence in a geo frame)")
    lo.add_argument("--roads", help="--no-database: road centre lines (GeoJSON, GPKG, OSM ...) bounding where the "
                                    "vehicle may be (default: the map's own road semantics)")
    lo.add_argument("--prior", default=None, help="--no-database: 'truth' (default: a prior drawn around each "
                    "frame's pose, a simulated GPS fix) or 'X,Y,YAW_DEG' (the first frame's; the rest tracked)")
    lo.add_argument("--radius", type=float, default=None, help="--no-database: the prior's radius, metres (20)")
    lo.add_argument("--yaw", type=float, default=None,
                    help="--no-database: the prior's heading range, +- degrees (10)")
    lo.add_argument("--prior-seed", type=int, default=None, help="--no-database --prior truth: the draws' seed (0)")
    lo.add_argument("--quiet", action="store_true")
    lo.set_defaults(func=cmd_localize)

    tc = sub.add_parser("train-crossview", help="learn the cross-view projections W_g, W_s for localizing with no "
                                               "database, on scenes other than the evaluation ones")
    tc.add_argument("--scenes", nargs="+", default=None, help="training scenes (default: calib/town_b, "
                                                              "calib/suburb_a, calib/suburb_b)")
    tc.add_argument("--out", required=True, help="folder for the recordings, crossview.pt and the learning curve")
    tc.add_argument("--frames", type=int, default=None, help="frames per scene (default 120, 4 m apart)")
    tc.add_argument("--epochs", type=int, default=None)
    tc.add_argument("--config", help="YAML with TrainCrossConfig fields (scenes, frames, spacing_m, train: ...)")
    tc.add_argument("--quiet", action="store_true")
    tc.set_defaults(func=cmd_train_crossview)

    sub.add_parser("train-features", help="train the semantic/edge FCN on simulator renders (see its --help)")

    ag = sub.add_parser("agent", help="active localization (satloc/ActiveLoc-v0): evaluate the agents (random, "
                                      "route, entropy, learned), train the learned one, or make a scene's active map")
    ag.add_argument("what", choices=["evaluate", "train", "map"])
    ag.add_argument("--agents", default="random,route,entropy,learned", help="evaluate: comma-separated")
    ag.add_argument("--episodes", type=int, default=100, help="evaluate: episodes per agent and map")
    ag.add_argument("--maps", nargs="+", default=None,
                    help="evaluate: active maps (scene names or .npz; default active_suburb, held out, and "
                         "active_grid); train: the one to train on (default active_grid)")
    ag.add_argument("--seed", type=int, default=None,
                    help="evaluate: episode i starts from reset(seed=SEED + i) (default 10000); train: the run's seed (0)")
    ag.add_argument("--timesteps", type=int, default=20000, help="train: decisions to train for")
    ag.add_argument("--policy", default=None, help="evaluate: the learned agent's weights (default: the shipped ones)")
    ag.add_argument("--scene", help="map: the scene (its database route must be a both-ways tour)")
    ag.add_argument("--work", help="map: folder for the recording and build (default: --out)")
    ag.add_argument("--config", help="YAML: evaluate/train: ActiveConfig fields; map: ActiveMapConfig fields")
    ag.add_argument("--out", required=True)
    ag.add_argument("--quiet", action="store_true")
    ag.set_defaults(func=cmd_agent)

    s = sub.add_parser("scene", help="generate a scene; print its summary, save it or draw it")
    s.add_argument("scene")
    s.add_argument("--aliasing", type=float, default=None)
    s.add_argument("--satellite-gap", type=float, default=None,
                   help="the map as a capture of the world in [0, 1] (satloc_env.world.capture; default: the scene's)")
    s.add_argument("--save", help="directory to save the generated scene to")
    s.add_argument("--picture", help="PNG (or JPEG) of the tile with its road graph, buildings, trees and route")
    s.set_defaults(func=cmd_scene)
    return p


#: the exit status after Ctrl-C (SIGINT), as shells report a command ended by SIGINT (128 + 2)
EXIT_INTERRUPTED = 130


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as the command's one line, ``satloc: warning: ...`` (not Python's form with the internal
    file, line number and source line). satloc's own warnings say what they are about; others keep their
    category's name."""
    text = " ".join(str(message).split())
    if not issubclass(category, SatlocWarning):
        text = f"{category.__name__}: {text}"
    print(f"satloc: warning: {text}", file=sys.stderr if file is None else file, flush=True)


def main(argv: list[str] | None = None) -> int:
    """Run a command; 2 with one line on a :class:`SatlocError`, 130 with one line on Ctrl-C (SIGINT).
    Warnings are printed as one line each (``satloc: warning: ...``).

    An interrupted command leaves its outputs as they were or marked incomplete (every file is written
    atomically; see each stage), and running it again resumes or starts over."""
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        if argv[:1] == ["train-features"]:  # its own parser (argparse cannot forward options through REMAINDER)
            from satloc_env.experiments.train_features import main as train_main

            return train_main(argv[1:]) or 0
        args = build_parser().parse_args(argv)
        return args.func(args)
    except SatlocError as e:
        print(f"satloc: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        nl = "\n" if sys.stderr.isatty() else ""  # end a progress bar's line first
        print(f"{nl}satloc: interrupted; run the command again to resume or start over", file=sys.stderr,
              flush=True)
        return EXIT_INTERRUPTED


def entry(argv: list[str] | None = None) -> None:
    """The ``satloc`` command: :func:`main`, then exit with its status. Once the command has finished, a
    Ctrl-C during the interpreter's shutdown is ignored (it would end the process with a traceback and a
    signal status although every output is complete)."""
    import signal
    import threading

    code = main(argv)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    entry()
