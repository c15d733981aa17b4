"""Table I's ``cross-area`` protocol: the revisit queries localized with no database.

The place is known only from above: :class:`satloc.localizers.crossview.CrossViewLocalizer` compares each query with the
scene's satellite map (the recording's map: the capture at the configured satellite gap, never the ground the
camera sees) within a prior drawn around the query's true pose as a GPS fix gives it (``prior_radius_m``,
``prior_yaw_deg``; seeded by ``seed`` and the query's index, so every run draws the same priors). Nothing the
localizer uses was learned on the scene: the features are the shipped ``default`` ones (trained on
``scenes/fcn_train``), whatever ``features`` the database method of the same configuration uses.

Two rows: ``cross`` ("No database"), each query on its own, and ``cross+track`` ("No database + track"), the
queries in order, each frame's posterior multiplied by the previous answer moved by the tracked modes'
odometry (:class:`satloc.localizers.crossview.CrossViewTracker`; :func:`satloc_env.experiments.scene_run.tracked_odometry`,
visual odometry by default). The drivable area: the map's label raster where it has one (``drivable: auto``;
in a simulated scene the generated roads, as a real place's road vectors would give them).

The queries are the revisit protocol's (:func:`satloc_env.experiments.scene_run._covered`), so
:func:`cross_area_rows` puts the with-database modes and the baselines of the same scene folder beside them, on
the same queries, with the cross-view figures: mean (block-bootstrap interval), median, lateral and
longitudinal recall within 1 / 3 / 5 m and the median heading error (``cross_area.csv``, ``cross_area.md``).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from satloc import __version__ as SATLOC_VERSION
from satloc.config import to_dict
from satloc.errors import ConfigError, FormatError
from satloc.evaluation.metrics import pose_errors, recall_within
from satloc.features import make_extractor
from satloc.features.dictionary import SatelliteFeatures
from satloc.features.pixelwise import FEATURE_SETS, features_identity
from satloc.localizers.crossview import SHIPPED_PROJECTIONS, CrossViewLocalizer
from satloc.persist import atomic_path, header, load_npz, read_json, write_json
from satloc.satmap import SatelliteMap
from satloc.sequence import Sequence

from .scene_run import (
    BASELINE_NAMES,
    METHOD_NAMES,
    CrossAreaConfig,
    ExperimentConfig,
    _covered,
    earlier_rows,
    sequence_identity,
    table_stats,
    tracked_odometry,
    write_rows_csv,
)

#: bump when the no-database localizer's answers change for the same settings (its stamps then miss)
CROSS_VERSION = 2
#: the protocol's rows: method key -> display name
CROSS_NAMES = {"cross": "No database", "cross+track": "No database + track"}
#: the radii (metres) of the lateral and longitudinal recall columns
RECALL_RADII = (1.0, 3.0, 5.0)


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(np.asarray(a, np.float64)).tobytes())
    return h.hexdigest()[:32]


def satellite_features(sdir: Path, satmap: SatelliteMap, extractor) -> SatelliteFeatures:
    """The map's features: the build's (``sdir/build/satellite_features.npz``, the same map, extractor and FCN
    weights; a map's features hold nothing of the database) when there, else computed."""
    p = sdir / "build" / "satellite_features.npz"
    try:   # a build made with other FCN weights (build.json says which; builds before the field: not known)
        made = read_json(sdir / "build" / "build.json", "build").get("features_id")
    except (FormatError, OSError):
        made = None
    now = features_identity(extractor.name) if extractor.name in FEATURE_SETS else made
    if p.is_file() and made in (None, now):
        try:
            sf = SatelliteFeatures.load(p)
            if (sf.name == extractor.name and sf.features.shape[:2] == satmap.image.shape[:2]
                    and np.allclose(sf.origin, satmap.origin) and sf.meters_per_pixel == satmap.meters_per_pixel):
                return sf
        except FormatError:
            pass
    return SatelliteFeatures.compute(satmap, extractor)


def run_cross(q: Sequence, sel: np.ndarray, ca: CrossAreaConfig, odometry: np.ndarray, odometry_kind: str,
              out: Path, db_poses: np.ndarray, label: str, satmap: SatelliteMap, sdir: Path | None = None,
              progress: bool = True, log=print, pictures: bool = False, extra: list | None = None) -> dict:
    """Both rows of the protocol on the frames ``sel`` of ``q`` (true poses: the prior's centres and the
    truth) against ``satmap``, tracked by ``odometry`` ((len(sel), 3) between consecutive selected frames),
    into ``out`` (``localization_<row>.npz``, reused when done with the same settings, frames and odometry),
    then the localizers of ``extra`` ((key, name, instance), e.g. the reference floors and a user's:
    :func:`satloc_env.experiments.grading.extra_localizers`) on the same queries, priors and odometry, with no
    database. Every row runs through the common interface (:func:`satloc_env.experiments.grading.run_graded`).
    The gross error of a query with no answer is the farthest of ``db_poses`` (the tables' rule). ``sdir``:
    where a build's satellite features may be reused. Returns ``{row: summary}`` (with ``errors``)."""
    from satloc.localizers.crossview import NoDatabaseLocalizer
    from satloc.localizers.interface import Context

    from .grading import query_priors, run_graded

    out.mkdir(parents=True, exist_ok=True)
    truth = np.asarray(q.poses, np.float64)[sel]
    priors = query_priors(ca, truth, sel, q.timestamps)
    context = Context(q.camera, satmap, seed=ca.seed, database=None, place=label)
    proj_id = None   # learned channels: the file's content, not its name
    if ca.crossview.projections is not None:
        path = Path(SHIPPED_PROJECTIONS if ca.crossview.projections == "shipped" else ca.crossview.projections)
        proj_id = hashlib.sha256(path.read_bytes()).hexdigest()[:32] if path.is_file() else str(path)
    cv = None
    res: dict[str, dict] = {}
    for row in CROSS_NAMES:
        tracked = row.endswith("+track")
        stamp = {"cross_area": to_dict(ca), "projections": proj_id, "satloc": SATLOC_VERSION, "method": CROSS_VERSION,
                 "features_id": features_identity("default"),
                 "queries": sequence_identity(q), "frames": _digest(sel, truth),
                 "odometry": _digest(odometry) if tracked else None, "odometry_kind": odometry_kind if tracked else None}
        npz = out / f"localization_{row}.npz"
        a = None
        try:   # the stamp stored in the results file itself: a run that died between two files cannot mismatch
            a, meta = load_npz(npz, "localization")
            if meta.get("stamp") != json.loads(json.dumps(stamp)):
                a = None
            else:
                try:   # the time is in the summary beside it (the npz holds what was answered, not how fast)
                    secs = float(read_json(out / f"localization_{row}.json", "localization_summary")["s_per_query"])
                except (FormatError, KeyError, OSError, TypeError, ValueError):
                    secs = float(meta.get("s_per_query") or "nan")
                log(f"[{label}] {CROSS_NAMES[row]}: reused {npz}")
        except (FormatError, KeyError, OSError, ValueError, TypeError):
            a = None
        if a is None:
            if cv is None:
                ext = make_extractor("default")   # the shipped features, whatever the database method uses
                sf = satellite_features(sdir, satmap, ext) if sdir is not None else SatelliteFeatures.compute(satmap, ext)
                cv = CrossViewLocalizer(q.camera, sf, ext, ca.crossview, labels=satmap.labels)
            # a query with no fix (a receiver's outage) follows the track
            follow = (ca.crossview.track_radius_m, ca.crossview.track_yaw_deg) if tracked else None
            loc = NoDatabaseLocalizer(cv, track=tracked, follow=follow)
            m, _ = run_graded(loc, row, CROSS_NAMES[row], context, q, sel,
                              odometry if tracked else None, priors, out, db_poses, label, progress,
                              log=lambda s: None, meta={"stamp": stamp})
            secs = m["s_per_query"]
            if row == "cross":   # the pictures of earlier results are stale
                for old in out.glob("posterior_cross_q*.png"):
                    old.unlink()
        else:
            m = table_stats(a["errors"], truth, db_poses)
            m.update(queries=int(len(sel)), s_per_query=secs, errors=np.asarray(a["errors"], np.float64),
                     inlier_score=np.asarray(a["inlier_score"], np.float64))
        log(f"[{label}] {CROSS_NAMES[row]}: mean {m['mean_m']:.2f} m, median {m['median_m']:.2f} m, "
            f"{100 * m['within_1m']:.0f} % within 1 m over {len(sel)} queries, {secs:.3f} s per query")
        res[row] = m
        if row == "cross" and pictures:
            _pictures(ca, label, satmap, sdir, q, sel, priors, m["errors"], out)
    from .grading import prune_extra

    prune_extra(out, {k for k, _, _ in extra or ()})
    for key, name, obj in extra or ():   # the same queries, priors and odometry, known only from above
        m, _ = run_graded(obj, key, name, context, q, sel, odometry, priors, out, db_poses, label, progress, log,
                          meta={"odometry": odometry_kind})
        m["odometry"] = "" if key == "prior" else odometry_kind
        res[key] = m
    return res


def cross_area(cfg: ExperimentConfig, label: str, sdir: str | Path, progress: bool = True, log=print,
               folder: str = "cross_area") -> dict:
    """The protocol on the scene folder ``sdir`` (its recording ``rec/``; the stages of
    :func:`satloc_env.experiments.scene_run._stages` done): :func:`run_cross` on the revisit queries, into
    ``sdir/<folder>`` (``localization_<row>.npz`` with frames, estimates, truth, errors, inlier_score (the
    correlation), inlier, top_poses, top_probs, prior). Returns ``{row: summary}`` as
    :func:`satloc_env.experiments.tables.compare` does (with ``errors``)."""
    sdir = Path(sdir)
    db, q = Sequence.load(sdir / "rec" / "database"), Sequence.load(sdir / "rec" / "query")
    sel = _covered(cfg, db, q)
    odo = tracked_odometry(cfg, q, sel, sdir / "odometry_visual.npz")
    from .grading import extra_localizers

    return run_cross(q, sel, cfg.cross_area, odo, cfg.odometry, sdir / folder, db.poses, label,
                     SatelliteMap.load(sdir / "rec" / "map"), sdir, progress, log,
                     pictures=getattr(cfg, "pictures", True), extra=extra_localizers(cfg, set(CROSS_NAMES.values())))


def _pictures(ca: CrossAreaConfig, label: str, satmap: SatelliteMap, sdir: Path | None, q: Sequence,
              sel: np.ndarray, priors: list, errors: np.ndarray, out: Path) -> None:
    """``posterior_cross_q<i>.png``: the single-frame posterior over the prior disc of the best, a median and
    the worst query (every position searched, not only the stored strongest), drawn where not drawn yet."""
    import dataclasses

    from satloc.evaluation.plots import plot_cross_posterior
    from satloc.geometry import Pose2

    has = np.array([p is not None for p in priors])   # a query in a receiver's outage has no prior to draw
    order = np.flatnonzero(has)[np.argsort(np.nan_to_num(np.asarray(errors)[has], nan=1e9))]
    if not len(order):
        return
    picks = sorted({int(order[0]), int(order[len(order) // 2]), int(order[-1])})
    todo = [k for k in picks if not (out / f"posterior_cross_q{int(sel[k]):03d}.png").is_file()]
    if not todo:
        return
    ext = make_extractor("default")
    sf = satellite_features(sdir, satmap, ext) if sdir is not None else SatelliteFeatures.compute(satmap, ext)
    cv = CrossViewLocalizer(q.camera, sf, ext, dataclasses.replace(ca.crossview, top_k=10**7), labels=satmap.labels)
    for k in todo:
        i = int(sel[k])
        r = cv.localize(q[i], priors[k])
        plot_cross_posterior(satmap, r.candidates, r.posterior, priors[k], Pose2(*q.poses[i]), r.pose,
                             out / f"posterior_cross_q{i:03d}.png", title=f"{label} query {i}, no database")


#: cross_area.csv's columns
CROSS_COLUMNS = ("method", "scene", "map", "database", "queries", "mean_m", "ci95_low", "ci95_high", "median_m",
                 "within_1m", "lateral_1m", "lateral_3m", "lateral_5m", "longitudinal_1m", "longitudinal_3m",
                 "longitudinal_5m", "heading_median_deg", "failure_rate", "ci_method")


def _method_files(sdir: Path) -> list[tuple[str, str, Path]]:
    """(display name, database used, npz) of every method localized on the revisit queries of ``sdir``: the
    protocol's rows, the reference floors and the user's localizers it ran (no database), then the
    with-database modes and baselines of the revisit protocol."""
    found = [(CROSS_NAMES[r], "none", sdir / "cross_area" / f"localization_{r}.npz") for r in CROSS_NAMES]
    from .grading import REFERENCE_NAMES

    extra = []
    for p in (sdir / "cross_area").glob("localization_*.npz"):
        key = p.stem[len("localization_"):]
        if key in CROSS_NAMES:
            continue
        try:
            name = load_npz(p, "localization")[1].get("name") or key
        except FormatError:
            continue
        order = list(REFERENCE_NAMES).index(key) if key in REFERENCE_NAMES else len(REFERENCE_NAMES)
        extra.append((order, name, p))
    found += [(name, "none", p) for _, name, p in sorted(extra)]
    found += [(METHOD_NAMES[m], "database pass", sdir / f"localization_{m}.npz") for m in METHOD_NAMES]
    found += [(BASELINE_NAMES[b], "database pass", sdir / f"baseline_{b}.npz") for b in BASELINE_NAMES]
    return [f for f in found if f[2].is_file()]


#: what a scene's satellite map is (``map`` column of cross_area.csv), by its generator's type
MAP_KINDS = {"capture": "a capture of the world", "image": "same image, an upper bound",
             "image_cars": "same image, the camera's own parked cars, an upper bound"}


def map_kind(sdir: str | Path) -> str:
    """What the map of the scene recorded in ``sdir/rec`` is to its camera: :data:`MAP_KINDS` ``capture`` for a
    painted world (a grid or map vectors: the map is captured, never the ground the camera renders), ``image``
    for a scene over an image (the camera sees the image and the map is the same image captured: its
    figures are an upper bound; ``image_cars`` where the camera's world parks cars of its own on the image,
    ``generator.parked_per_km``), "" where the recording's scene cannot be read."""
    from satloc_env.world.scene import load_spec

    try:
        scene = json.loads((Path(sdir) / "rec" / "recording.json").read_text())["config"]["scene"]
        spec, _ = load_spec(scene)
        g = spec.generator_spec(str(scene))
    except (OSError, ValueError, KeyError, TypeError, ConfigError):
        return ""
    if g.type != "image":
        return MAP_KINDS["capture"]
    return MAP_KINDS["image_cars" if g.parked_per_km > 0 else "image"]


def cross_area_rows(sdir: str | Path, label: str) -> list[dict]:
    """The cross-area comparison of the scene folder ``sdir``: every method localized there on the revisit
    queries (the cross-view rows, the with-database modes and the baselines), each row with the columns of
    :data:`CROSS_COLUMNS` over the queries the cross-view rows evaluated."""
    sdir = Path(sdir)
    rows = []
    kind = map_kind(sdir)
    ref = None
    db = Sequence.load(sdir / "rec" / "database")
    for name, database, path in _method_files(sdir):
        a, _ = load_npz(path, "localization")
        frames = np.asarray(a["frames"], np.int64)
        if ref is None:
            ref = frames
        if not np.array_equal(frames, ref):   # another selection of queries (another run's): not comparable
            continue
        pe = pose_errors(a["estimates"], a["truth"])
        st = table_stats(pe["error"], a["truth"], db.poses)
        row = {"method": name, "scene": label, "map": kind, "database": database, "queries": int(len(frames)),
               **{k: st[k] for k in ("mean_m", "ci95_low", "ci95_high", "median_m", "within_1m", "failure_rate",
                                     "ci_method")}}
        for r in RECALL_RADII:
            row[f"lateral_{r:g}m"] = recall_within(pe["lateral"], r)
            row[f"longitudinal_{r:g}m"] = recall_within(pe["longitudinal"], r)
        h = pe["heading_deg"]
        row["heading_median_deg"] = float(np.median(np.where(np.isfinite(h), h, 180.0)))
        rows.append(row)
    return rows


def write_cross_area(out: str | Path, rows: list[dict], prior: str = "") -> None:
    """``cross_area.csv`` (:data:`CROSS_COLUMNS`), ``cross_area.json`` and ``cross_area.md`` (one table per
    scene; ``prior`` says the no-database rows' prior) into ``out``; the rows of scenes an earlier
    ``cross_area.json`` there holds and ``rows`` has not are kept (as Table I keeps its rows)."""
    out = Path(out)
    if not rows:
        raise ConfigError("cross-area: no method was localized on the cross-area queries")
    scenes = {r["scene"] for r in rows}
    kept, old = earlier_rows(out / "cross_area.json", "cross_area", [c for c in CROSS_COLUMNS if c != "map"],
                             lambda r: r.get("scene") in scenes)
    for r in kept:   # rows written before the map column
        r.setdefault("map", "")
    prior = prior or old.get("prior", "")
    rows = kept + list(rows)
    write_json(out / "cross_area.json", dict(header("cross_area"), prior=prior, rows=rows))
    write_rows_csv(out / "cross_area.csv", CROSS_COLUMNS, rows)
    lines = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        part = [r for r in rows if r["scene"] == scene]
        kind = part[0].get("map") or ""
        lines += [f"**{scene}** ({part[0]['queries']} queries, the revisit protocol's{'; ' + prior if prior else ''}"
                  f"{'; the map: ' + kind if kind else ''}):\n",
                  "| method | database | mean m (95 % CI) | median m | within 1 m | lateral 1 / 3 / 5 m | "
                  "longitudinal 1 / 3 / 5 m | heading median deg |", "|---|---|---|---|---|---|---|---|"]
        for r in part:
            def pct(k, r=r):
                return f"{100 * r[k]:.0f}"

            lines.append(f"| {r['method']} | {r['database']} | {r['mean_m']:.2f} ({r['ci95_low']:.2f}-"
                         f"{r['ci95_high']:.2f}) | {r['median_m']:.2f} | {pct('within_1m')} % | "
                         f"{pct('lateral_1m')} / {pct('lateral_3m')} / {pct('lateral_5m')} % | "
                         f"{pct('longitudinal_1m')} / {pct('longitudinal_3m')} / {pct('longitudinal_5m')} % | "
                         f"{r['heading_median_deg']:.1f} |")
        lines.append("")
    with atomic_path(out / "cross_area.md", suffix=".md") as tmp:
        tmp.write_text("\n".join(lines))
