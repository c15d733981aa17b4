"""Benchmarks that print figures (never timed tests)."""
from __future__ import annotations

import os
import resource
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from satloc.errors import ConfigError
from satloc.geometry import StereoCamera
from satloc_env.envs.drive import EnvConfig, SatLocEnv
from satloc_env.world.meshes import LOD_M


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def bench_env(resolution: str = "half", steps: int = 2000, scene: str = "city", warmup: int = 20,
              num_envs: int = 1, detail_m: float | None = LOD_M, sensor: float | None = None,
              attitude: float | None = None) -> dict:
    """Stereo colour + depth steps per second driven by the autopilot, memory over the run, and which GL driver
    rendered (``gl_renderer``: e.g. llvmpipe for Mesa's software rasterizer, the GPU's name on a vendor's
    driver). ``num_envs`` > 1: the batched vector environment (:class:`satloc_env.envs.vector.SatLocVectorEnv`) with
    that many cars; ``steps`` and ``steps_per_s`` then count the steps of all cars together (``steps`` is
    rounded up to a multiple of ``num_envs``). ``peak_rss_mb``: the largest resident size sampled during this
    run (after the warm-up steps, every 16 step calls and at the end), not the process's lifetime peak, so that
    runs of several ``num_envs`` in one process each report their own. ``detail_m``: the environment's setting
    (the distance within which objects keep their full detail; None: everywhere); ``sensor``, ``attitude``: the
    environment's camera noise and body motion (None: its defaults; the result names the values the steps
    ran with). ``cpu_ms_per_step``: the process's CPU time
    (all its threads, the rasterizer's included) per step, steadier than the wall clock on a shared machine."""
    if num_envs < 1:
        raise ConfigError(f"num_envs: expected an integer >= 1, got {num_envs}")
    kw = dict(scene=scene, resolution=resolution, depth=True, localizer=None, detail_m=detail_m)   # rendering only
    kw.update({k: v for k, v in (("sensor", sensor), ("attitude", attitude)) if v is not None})
    if num_envs == 1:
        env = SatLocEnv(**kw)
        reset = env.reset

        def step():
            return env.step(env.autopilot_action())[2:4]

        def renderer():
            return env._renderer
    else:
        from satloc_env.envs.vector import SatLocVectorEnv

        env = SatLocVectorEnv(num_envs, **kw)
        reset = env.reset

        def step():
            return env.step(env.autopilot_actions())[2:4]

        def renderer():
            return env._batch
    calls = -(-steps // num_envs)
    try:
        reset(seed=0)
        for _ in range(warmup):
            step()
        rss_start = _rss_mb()
        peak = rss_start
        episodes = num_envs
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(calls):
            term, trunc = step()
            if i % 16 == 15:
                peak = max(peak, _rss_mb())
            if num_envs == 1 and (term or trunc):
                env.reset(seed=episodes)
            episodes += int(np.count_nonzero(np.logical_or(term, trunc)))
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        rss_end = _rss_mb()
        peak = max(peak, rss_end)
        gl = renderer().gl_info
    finally:
        env.close()
    cam = StereoCamera.preset(resolution)
    cfg = EnvConfig(**{k: v for k, v in kw.items() if k in ("sensor", "attitude")})   # what the steps ran with
    total = calls * num_envs
    return {
        "bench": "env", "resolution": resolution, "width": cam.width, "height": cam.height, "scene": scene,
        "num_envs": num_envs, "detail_m": detail_m, "gl_renderer": gl["renderer"], "gl_version": gl["version"],
        "steps": total, "episodes": episodes, "steps_per_s": round(total / dt, 1),
        "ms_per_step": round(1000 * dt / total, 2), "cpu_ms_per_step": round(1000 * cpu / total, 2),
        "sensor": cfg.sensor, "attitude": cfg.attitude, "rss_start_mb": round(rss_start, 1),
        "rss_end_mb": round(rss_end, 1), "peak_rss_mb": round(peak, 1),
    }


def _frames_of(rec) -> int:
    return int(rec.name.rsplit("_", 1)[1])


def _bench_record_config(scene: str, frames: int):
    from satloc_env.envs.record import PassConfig, RecordConfig

    return RecordConfig(scene=scene, database=PassConfig(max_frames=frames),
                        query=PassConfig(lane_offset_m=-0.75, spacing_m=5.0, occlusion=0.3, appearance=0.5, seed=1,
                                         max_frames=250))


def bench_recording(work, scene: str, frames: int):
    """The recording folder of ``satloc bench localize`` in ``work``: ``rec_<scene>_<database frames>``. An
    existing complete recording of the same scene with at least ``frames`` database frames, recorded as this
    version records it (its ``recording.json`` stamp: satellite gap, drift, passes), is reused (its first
    frames serve every size); otherwise a new folder for ``frames`` frames. Returns ``(folder, reuse)``."""
    from satloc.persist import read_json
    from satloc_env.envs.record import STATUS, record_stamp

    from .scene_run import scene_label

    label = scene_label(scene).replace("/", "_")
    done = []
    for d in Path(work).glob(f"rec_{label}_*"):
        tail = d.name[len(f"rec_{label}_"):]
        if not (tail.isdigit() and int(tail) >= frames and (d / "query" / "sequence.json").is_file()):
            continue
        try:
            st = read_json(d / STATUS, "recording")
        except Exception:   # no stamp or a damaged one: not reused
            continue
        if st.get("complete") and st.get("config") == record_stamp(_bench_record_config(scene, int(tail))):
            done.append((int(tail), d))
    if done:
        return min(done)[1], True
    return Path(work) / f"rec_{label}_{frames}", False


def bench_localize(sizes_km=(0.25, 1.0, 4.0), work=None, scene: str = "loop", queries: int = 40,
                   progress: bool = True, mode: str = "full", device: str = "auto") -> "Iterator[dict]":
    """Localization speed against databases of increasing path length (one JSON-able row per size).

    One database pass (frames every metre) and one query pass of ``scene`` are recorded in ``work`` (reused
    when a recording there covers the longest size, :func:`bench_recording`; a route shorter than that size is
    an error); each size builds a dictionary from the first ``size`` km of the database, learns the
    projections, and times ``queries`` queries end to end (features, stereo depth, scoring) taken from the
    query pass where it lies on that part of the database: ``queries_per_s`` as a stream of queries is
    localized (:meth:`Localizer.localize_stream`: frames read from disk, the next frame's depth and features
    overlapping the current one's scoring), ``ms_per_query`` as the latency of one :meth:`Localizer.localize`
    call on a frame in memory (``sequential_queries_per_s`` its inverse), ``refined_*`` the stream again with
    the bird's-eye refinement. Build and training times are reported too. Features and projection learning
    run on ``device`` (:mod:`satloc.device`); each row names the device it resolved to."""
    import tempfile
    from pathlib import Path

    from satloc.device import resolve_device
    from satloc.errors import ConfigError
    from satloc.features.projection import ProjectionConfig
    from satloc.geometry import arc_length
    from satloc.localizers.database import LocalizerConfig
    from satloc.pipeline import BuildConfig, build, load_localizer, train_projection
    from satloc.sequence import Sequence
    from satloc_env.envs.record import record_passes

    from .scene_run import covered_queries

    dev = str(resolve_device(device))   # before any work: a device that is not there fails at once
    work = Path(work) if work else Path(tempfile.mkdtemp(prefix="satloc_bench_"))
    longest = max(sizes_km)
    # the recorder keeps a frame about every 1.6 m at its default speed and spacing (see satloc demo --help)
    rec, reuse = bench_recording(work, scene, int(longest * 1000 / 1.5) + 50)
    if not reuse:
        record_passes(_bench_record_config(scene, _frames_of(rec)), rec, progress)
    db_all, q = Sequence.load(rec / "database"), Sequence.load(rec / "query")
    s = arc_length(db_all.poses)
    if s[-1] < longest * 1000.0 - 5.0:   # a build must not measure a shorter database than its row says
        raise ConfigError(f"bench localize: scene {scene!r}'s database route gives {s[-1] / 1000:.2f} km, less "
                          f"than the {longest:g} km asked (--sizes-km); ask for sizes up to that length")
    for km in sizes_km:
        n = int(np.searchsorted(s, km * 1000.0)) + 1
        db = db_all.head(n)
        bdir = work / f"build_{km:g}km"
        t0 = time.perf_counter()
        summary = build(rec / "database", rec / "map", bdir, BuildConfig(max_frames=n, device=dev), progress)
        t1 = time.perf_counter()
        train_projection(bdir, ProjectionConfig(device=dev), progress=progress)
        t2 = time.perf_counter()
        loc = load_localizer(bdir, LocalizerConfig(mode=mode, device=dev), cache_table=False, progress=progress)
        t3 = time.perf_counter()
        sel = covered_queries(db, q, 3.0)
        sel = sel[np.linspace(0, len(sel) - 1, min(queries, len(sel))).astype(int)] if len(sel) else sel
        frames = [q[int(i)] for i in sel]
        loc.localize(frames[0], refine=True)  # warm-up (lazy FCN weights, faiss threads, the aligner)
        t4 = time.perf_counter()
        for f in frames:  # one call at a time: the latency of a single query
            loc.localize(f)
        t5 = time.perf_counter()
        # a stream of queries as the command line and experiments localize them, read from disk as they come
        errs = [r.estimate.distance(f.pose) for r, f in zip(loc.localize_stream(q[int(i)] for i in sel), frames)]
        t6 = time.perf_counter()
        errs_r = [r.estimate.distance(f.pose)
                  for r, f in zip(loc.localize_stream((q[int(i)] for i in sel), refine=True), frames)]
        t7 = time.perf_counter()
        yield {"bench": "localize", "scene": scene, "mode": mode, "device": dev, "db_km": round(db.path_length() / 1000, 3),
               "db_frames": n, "entries": summary["entries"], "queries": len(frames),
               "queries_per_s": round(len(frames) / (t6 - t5), 2), "ms_per_query": round(1000 * (t5 - t4) / len(frames), 1),
               "sequential_queries_per_s": round(len(frames) / (t5 - t4), 2),
               "mean_error_m": round(float(np.mean(errs)), 3), "median_error_m": round(float(np.median(errs)), 3),
               "refined_queries_per_s": round(len(frames) / (t7 - t6), 2),
               "refined_mean_error_m": round(float(np.mean(errs_r)), 3),
               "refined_median_error_m": round(float(np.median(errs_r)), 3),
               "build_s": round(t1 - t0, 1), "train_projection_s": round(t2 - t1, 1),
               "localizer_init_s": round(t3 - t2, 1), "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
               "load_avg_1m": round(os.getloadavg()[0], 2)}    # above the cores used: timings shared the CPU
        del loc


def bench_soak(steps: int = 20000, queries: int = 2000, scene: str = "city", emit=None, **kw) -> dict:
    """The soak benchmark (:mod:`satloc_env.experiments.soak`): RSS and open file descriptors over ``steps`` env steps with
    the localizer and tracking, then over ``queries`` queries of ``localize_stream``. ``emit`` receives every
    sample and summary as it comes (a JSON-able dict); ``kw`` are further :class:`satloc_env.experiments.soak.SoakConfig`
    fields. Returns the summaries and samples (see :func:`satloc_env.experiments.soak.soak`)."""
    from .soak import SoakConfig, soak

    return soak(SoakConfig(steps=steps, queries=queries, scene=scene, **kw), emit=emit)


#: the real KITTI excerpt beside the repository (../shared/realdata, see its README): non-commercial, read in place
KITTI_EXCERPT = (Path(__file__).resolve().parents[3] / "shared" / "realdata" / "kitti_raw_2011_09_26_drive_0023_7frames"
                 / "2011_09_26" / "2011_09_26_drive_0023_sync")


def _timed_vo(seq, config) -> tuple[np.ndarray, float]:
    """Visual odometry of ``seq`` (frames already in memory) and its wall time per frame in ms."""
    from satloc.tracking.vo import visual_odometry

    t0 = time.perf_counter()
    odo = visual_odometry(seq, config)
    return odo, round(1000 * (time.perf_counter() - t0) / len(seq), 1)


def bench_vo(scene: str = "residential", frames: int = 250, work=None, kitti=None, progress: bool = True,
             config=None) -> "Iterator[dict]":
    """Stereo visual odometry (:mod:`satloc.tracking.vo`) drift and speed, one JSON-able row per measurement.

    Simulator: a drive of ``frames`` frames, one per simulator step (0.8 m at the recorder's 8 m/s), on the
    database route of ``scene`` in the right lane, recorded into ``work`` (reused when present; default a temp
    dir); VO from stereo against the true poses, and with the frames' true depth for comparison
    (``depth_source: frame``). Real data: the KITTI excerpt ``kitti`` (default :data:`KITTI_EXCERPT`; a
    ``skipped`` row when it is absent): VO at full and half resolution against the OXTS poses and against the
    OXTS-integrated odometry (:func:`satloc.datasets.kitti.oxts_odometry`), which is itself measured against the
    poses on both clocks. Drift figures are :func:`satloc.tracking.vo.odometry_drift`'s (translation error as % of the
    distance, heading drift in degrees per 100 m; ``segments`` over 50 and 100 m windows where the drive is that
    long). ``ms_per_frame``: VO wall time on frames in memory (stereo depth included: ``stereo_ms_per_frame``)."""
    import dataclasses
    import tempfile

    from satloc.config import to_dict
    from satloc.sequence import Sequence
    from satloc.stereo import StereoDepth
    from satloc.tracking.vo import VOConfig, integrate_odometry, odometry_drift
    from satloc_env.envs.record import PassConfig, make_env, record_pass

    config = config or VOConfig()
    work = Path(work) if work else Path(tempfile.mkdtemp(prefix="satloc_bench_vo_"))
    drive_dir = work / f"{Path(scene).stem}_{frames}"
    t0 = time.perf_counter()
    p = PassConfig(spacing_m=0.0, max_frames=frames)
    if (drive_dir / "sequence.json").is_file() and Sequence.load(drive_dir).meta.get("pass_config") != to_dict(p):
        import shutil

        shutil.rmtree(drive_dir)   # a drive recorded otherwise (before the drift, or another pass): again
    if not (drive_dir / "sequence.json").is_file():
        env = make_env(scene=scene, localizer=None, depth=True)
        try:
            env.reset(seed=0)
            record_pass(env, p, env.unwrapped.scene.spec.database_route,
                        drive_dir, "vo", progress, {"source": "satloc_env", "scene": env.unwrapped.scene.name})
        finally:
            env.close()
    loaded = Sequence.load(drive_dir)
    seq = Sequence(loaded.camera, list(loaded), loaded.name, loaded.meta)   # in memory: timings without reading
    record_s = round(time.perf_counter() - t0, 1)
    stereo = StereoDepth(seq.camera, config.stereo)
    t1 = time.perf_counter()
    for f in seq:
        stereo(f.left, f.right)
    stereo_ms = round(1000 * (time.perf_counter() - t1) / len(seq), 1)
    # the frames' true depth for comparison; its flat ground spans 0.65 px of disparity over 3x3 (VOConfig)
    for source, edge in (("stereo", config.depth_edge_px), ("frame", max(config.depth_edge_px, 1.0))):
        odo, ms = _timed_vo(seq, dataclasses.replace(config, depth_source=source, depth_edge_px=edge))
        yield {"bench": "vo", "data": "sim", "scene": scene, "depth_source": source, "depth_edge_px": edge,
               "width": seq.camera.width, "height": seq.camera.height,
               **odometry_drift(odo, seq.poses, (50.0, 100.0)), "ms_per_frame": ms,
               "stereo_ms_per_frame": stereo_ms, "record_or_load_s": record_s,
               "load_avg_1m": round(os.getloadavg()[0], 2)}

    kitti = Path(kitti) if kitti else KITTI_EXCERPT
    if not kitti.is_dir():
        yield {"bench": "vo", "data": "kitti",
               "skipped": f"no KITTI drive at {kitti} (see ../shared/realdata/README.md)"}
        return
    from satloc.datasets.kitti import load_kitti, oxts_odometry

    drive = load_kitti(kitti)
    poses = drive.poses
    oxts = {clock: oxts_odometry(drive, clock) for clock in ("image", "oxts")}
    oxts_poses = integrate_odometry(oxts["image"], poses[0])
    for clock, odo in oxts.items():
        yield {"bench": "vo", "data": "kitti_oxts", "drive": drive.name, "clock": clock,
               **odometry_drift(odo, poses, ())}
    cam = drive.camera
    for resolution, camera in (("full", cam), ("half", cam.resized(cam.width // 2, (cam.height + 1) // 2, 0.5))):
        view = drive.view(camera=camera)
        frames_kitti = Sequence(camera, list(view), view.name, view.meta)
        odo, ms = _timed_vo(frames_kitti, config)
        yield {"bench": "vo", "data": "kitti", "drive": drive.name, "resolution": resolution, "width": camera.width,
               "height": camera.height, "vs_poses": odometry_drift(odo, poses, ()),
               "vs_oxts": odometry_drift(odo, oxts_poses, ()), "ms_per_frame": ms,
               "load_avg_1m": round(os.getloadavg()[0], 2)}


def bench_active(map: str = "active_grid", episodes: int = 20, agents: tuple[str, ...] = ("random", "route",
                                                                                             "entropy", "learned"),
                 seed: int = 20_000) -> list[dict]:
    """ActiveLoc-v0 decisions per second with each agent (environment plus the agent's choice), over
    ``episodes`` episodes from ``reset(seed=seed + i)``; ``agent_ms`` is the agent's share per decision."""
    from satloc_env.agents.evaluate import run_episode
    from satloc_env.agents.policies import make_agent
    from satloc_env.envs.active import ActiveLocEnv

    env = ActiveLocEnv(map=map)
    rows = []
    for name in agents:
        agent = make_agent(name, seed=seed)
        t0 = time.perf_counter()
        eps = [run_episode(env, agent, seed + i) for i in range(episodes)]
        dt = time.perf_counter() - t0
        dec = sum(e["decisions"] for e in eps)
        rows.append({"bench": "active", "map": env.map.scene, "agent": name, "episodes": episodes, "decisions": dec,
                     "decisions_per_s": round(dec / dt, 1), "ms_per_decision": round(1000 * dt / max(dec, 1), 1),
                     "agent_ms": round(1000 * sum(e["act_s"] for e in eps) / max(dec, 1), 1)})
    return rows


def synthetic_osm(path, ways: int = 10_000, seed: int = 0, pitch_m: float = 60.0, lat0: float = 48.0,
                  lon0: float = 11.0) -> tuple[int, float]:
    """Write an OpenStreetMap XML extract of about ``ways`` residential ways (at most that many): a street grid
    of blocks ``pitch_m`` apart, each way one block's side (as OSM cuts ways at junctions), the nodes jittered
    by 3 m (seeded). Returns (ways written, the grid's side in metres)."""
    import math

    k = max(1, int((-2 + math.sqrt(4 + 8 * ways)) // 4))      # 2 k (k + 1) ways <= ways
    rng = np.random.default_rng(seed)
    jit = rng.normal(0.0, 3.0, (k + 1, k + 1, 2))
    m_lat = 111_320.0
    m_lon = m_lat * math.cos(math.radians(lat0))
    nid = {(i, j): i * (k + 1) + j + 1 for i in range(k + 1) for j in range(k + 1)}
    edges = [((i, j), (i, j + 1)) for i in range(k + 1) for j in range(k)] + \
        [((i, j), (i + 1, j)) for j in range(k + 1) for i in range(k)]
    with open(path, "w") as f:
        f.write('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="satloc bench osm">\n')
        for (i, j), n in nid.items():
            x, y = i * pitch_m + jit[i, j, 0], j * pitch_m + jit[i, j, 1]
            f.write(f'  <node id="{n}" lat="{lat0 + y / m_lat:.7f}" lon="{lon0 + x / m_lon:.7f}"/>\n')
        for w, (a, b) in enumerate(edges):
            f.write(f'  <way id="{w + 1}"><nd ref="{nid[a]}"/><nd ref="{nid[b]}"/>'
                    '<tag k="highway" v="residential"/></way>\n')
        f.write("</osm>\n")
    return len(edges), k * pitch_m


def bench_osm(ways: tuple[int, ...] = (1_000, 10_000), work=None) -> Iterator[dict]:
    """Loading an OpenStreetMap extract's roads: for each size, a synthetic extract (:func:`synthetic_osm`)
    read (GDAL's OSM driver, :func:`satloc.geodata.vectors.read_road_lines`), taken to UTM, and made a road
    graph (:func:`satloc_env.world.roadgraph.graph_from_lines`: clipping, snapping ends through a spatial
    index, noding, merging); seconds for each stage and in all."""
    import tempfile

    from satloc.geodata.vectors import read_road_lines
    from satloc_env.world.roadgraph import GraphParams, graph_from_lines

    work = Path(work) if work else Path(tempfile.mkdtemp(prefix="satloc_bench_osm_"))
    work.mkdir(parents=True, exist_ok=True)
    for n in ways:
        path = work / f"grid_{n}.osm"
        written, side = synthetic_osm(path, n)
        t0 = time.perf_counter()
        roads = read_road_lines(path)
        t1 = time.perf_counter()
        utm = roads.to_crs("EPSG:32632")
        t2 = time.perf_counter()
        low = np.min([xy.min(axis=0) for xy in utm.lines], axis=0) - 10.0     # the tile: the lines' extent
        high = np.max([xy.max(axis=0) for xy in utm.lines], axis=0) + 10.0    # and 10 m (UTM is not lon/lat)
        lines = [xy - low for xy in utm.lines]
        graph = graph_from_lines(lines, utm.widths, *(high - low), GraphParams(), utm.layers)
        t3 = time.perf_counter()
        yield {"bench": "osm", "ways": written, "side_m": side, "file_mb": round(path.stat().st_size / 2**20, 1),
               "read_s": round(t1 - t0, 2), "to_crs_s": round(t2 - t1, 2), "graph_s": round(t3 - t2, 2),
               "total_s": round(t3 - t0, 2), "graph_edges": graph.graph.number_of_edges(),
               "graph_km": round(graph.length_m / 1000, 1), "load_avg_1m": round(os.getloadavg()[0], 2)}


def bench_crossview(scene: str = "city", frames: int = 40, radius_m: float = 20.0, yaw_deg: float = 10.0,
                    work=None, progress: bool = True) -> "Iterator[dict]":
    """Localization with no database (:mod:`satloc.localizers.crossview`): seconds per frame and frames per second at half
    resolution (620x188) from a ``radius_m`` / ``yaw_deg`` prior, single frame and tracked (the tracker's
    ``fuse``: the whole prior searched each frame), one row each; and the one-off satellite features of the map.
    The frames: a drive of ``frames`` frames one every 5 m along ``scene``'s query lane, recorded into ``work``
    (reused; default a temp dir) and held in memory; priors drawn around the true poses (seed 0). Times are the
    whole :meth:`satloc.localizers.crossview.CrossViewLocalizer.localize` (stereo depth, features, bird's-eye view,
    search); ``error`` columns are reported so a speed is never read apart from what it gives."""
    import tempfile

    from satloc.config import to_dict
    from satloc.evaluation.metrics import pose_errors
    from satloc.features import make_extractor
    from satloc.features.dictionary import SatelliteFeatures
    from satloc.geometry import Pose2
    from satloc.localizers.crossview import CrossViewLocalizer, draw_prior, localize_frames
    from satloc.satmap import SatelliteMap
    from satloc.sequence import Sequence
    from satloc_env.envs.record import PassConfig, make_env, record_pass

    work = Path(work) if work else Path(tempfile.mkdtemp(prefix="satloc_bench_cross_"))
    drive = work / f"{Path(scene).stem}_cross_{frames}"
    p = PassConfig(lane_offset_m=-0.75, spacing_m=5.0, max_frames=frames)
    map_dir = work / f"{Path(scene).stem}_map"
    if not ((drive / "sequence.json").is_file() and (map_dir / "map.json").is_file()
            and Sequence.load(drive).meta.get("pass_config") == to_dict(p)):
        import shutil

        # an interrupted run's, or a drive recorded otherwise (another pass, or before the body's attitude):
        # recorded again with the map
        shutil.rmtree(drive, ignore_errors=True)
        env = make_env(scene=scene, localizer=None)
        try:
            env.reset(seed=0)
            record_pass(env, p, env.unwrapped.scene.spec.database_route, drive, "cross", progress,
                        {"source": "satloc_env", "scene": env.unwrapped.scene.name})
            env.unwrapped.scene.satmap.save(map_dir)
        finally:
            env.close()
    loaded = Sequence.load(drive)
    seq = Sequence(loaded.camera, list(loaded), loaded.name, loaded.meta)
    sm = SatelliteMap.load(map_dir)
    ext = make_extractor("default")
    t = time.perf_counter()
    sf = SatelliteFeatures.compute(sm, ext)
    yield {"bench": "crossview", "what": "satellite features (once per map)", "scene": scene,
           "map_px": list(sm.image.shape[:2]), "s": round(time.perf_counter() - t, 2)}
    cv = CrossViewLocalizer(seq.camera, sf, ext, labels=sm.labels)
    truth = np.asarray(seq.poses, np.float64)
    rng = np.random.default_rng(0)
    priors = [draw_prior(p, radius_m, yaw_deg, rng) for p in truth]
    # the true motion between frames as the tracked row's odometry: its time, not the odometry's, is measured
    odo = np.full((len(seq), 3), np.nan)
    for i in range(1, len(seq)):
        odo[i] = Pose2(*truth[i - 1]).between(Pose2(*truth[i])).as_array()
    cv.localize(seq[0], priors[0])   # warm-up: the first call's allocations (no network runs on the ground image)
    for name, o in (("single frame", None), ("tracked (fuse)", odo)):
        r = localize_frames(cv, list(seq), priors, o, progress)
        pe = pose_errors(r["estimates"], truth)
        s = float(np.mean(r["seconds"]))
        yield {"bench": "crossview", "what": name, "scene": scene, "resolution": f"{seq.camera.width}x{seq.camera.height}",
               "prior": f"+-{radius_m:g} m / +-{yaw_deg:g} deg", "frames": len(seq), "s_per_frame": round(s, 4),
               "frames_per_s": round(1.0 / s, 2), "median_error_m": round(float(np.nanmedian(pe["error"])), 3),
               "threads": os.cpu_count()}


_STARTUP_SCRIPT = """
import json, sys, time
t0 = time.perf_counter()
import gymnasium as gym
import satloc_env
t1 = time.perf_counter()
env = gym.make("satloc/SatLoc-v0", scene=sys.argv[1])
t2 = time.perf_counter()
obs, info = env.reset(seed=0)
t3 = time.perf_counter()
env.close()
print(json.dumps({"import_s": round(t1 - t0, 2), "make_s": round(t2 - t1, 2), "reset_s": round(t3 - t2, 2),
                  "total_s": round(t3 - t0, 2), "error_m": round(float(info["error_m"]), 3)}))
"""


def bench_startup(scene: str = "city", runs: int = 2, work=None) -> Iterator[dict]:
    """``import satloc_env``, ``gym.make("satloc/SatLoc-v0")`` and the first ``reset`` with the default localizer
    (``cross``), each in a fresh Python process: first with an empty cache (``SATLOC_CACHE`` a new folder: the scene
    built, the map's features computed, both kept), then ``runs`` times with the cache it left (warm: the scene,
    its world, the features and the learned channels read back). One row per process: ``cache`` cold or warm and
    the seconds of each part."""
    import json
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory(dir=work) as tmp:
        env = dict(os.environ, SATLOC_CACHE=str(Path(tmp) / "cache"))
        for i in range(1 + runs):
            r = subprocess.run([sys.executable, "-c", _STARTUP_SCRIPT, scene], capture_output=True, text=True,
                               env=env, timeout=1200)
            if r.returncode != 0:
                raise ConfigError(f"bench startup: the process failed: {r.stderr.strip()[-2000:]}")
            row = json.loads(r.stdout.strip().splitlines()[-1])
            yield {"bench": "startup", "scene": scene, "cache": "cold" if i == 0 else "warm", **row}
