"""The map of an active-localization task (:mod:`satloc_env.envs.active`): a scene's streets as directed legs, the
localizer's candidate poses on them, and the localizer's posterior of a frame every few metres of every leg.

An agent of ``satloc/ActiveLoc-v0`` chooses at each junction which street to take; between junctions the
tracked localizer (:class:`satloc.tracking.track.Tracker`) fuses the posteriors of the frames the car passes. Rendering
and localizing those frames while an agent trains would cost about a second per decision on 2 cores, so they are
done once per scene, here: :func:`build_active_map`

1. records the scene's database route (the ``tour`` of the ActiveLoc scenes: every street once in each direction, see
   :func:`both_ways_circuit`)
   twice with the simulator: a database pass (1 m spacing) and a query pass under another day's conditions
   (:data:`satloc_env.envs.record.QUERY_CHANGE`, occluders, appearance, the other lane offset) with a frame every
   ``frame_spacing_m``;
2. builds the method's dictionary and learns its projections on the database pass (the pipeline's stages);
3. localizes every query frame with the full method, scoring every candidate (no vote pruning: what the
   localizer does while a tracker has not locked, :mod:`satloc.tracking.track`) and keeps each posterior's non-zero
   entries (the co-occurrence score is 0 wherever no pair matches: 500-2,000 of the 18,000 candidates of
   ``active_grid``) down to ``min_relative`` of its largest (stored compactly, see :meth:`ActiveMap.save`). Keeping only the 256 largest, as a
   first version did, dropped up to 57 % of a frame's mass on that grid of look-alike blocks, where the
   truth's score ranks among hundreds of its twins': the truth got the tracker's floor and most episodes
   locked onto a twin;
4. assigns every query frame and every candidate pose to the leg it lies on.

The result, an :class:`ActiveMap`, is one npz (``satloc-active-map``). The environment then replays those real
posteriors along whatever streets the agent picks: a frame's posterior is the one the localizer gave for the
frame recorded at that place and heading. What is approximated: the car passes the recorded frames' poses,
and a frame recorded just before a junction was taken on the tour's own way through it (the last few metres
of a leg may already turn the tour's way).

The tour's waypoints are the junctions, in driving order: leg i runs from waypoint i to waypoint i + 1 (the
last back to the first); each ordered pair of adjacent junctions is a leg exactly once. At a junction the
branches (legs leaving it, except the way back) are put into :data:`SLOTS` by their turn angle: left
(> 45 degrees), straight, right (< -45 degrees).
"""
from __future__ import annotations

import itertools
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from satloc.config import to_dict
from satloc.errors import ConfigError, FormatError
from satloc.geometry import wrap_angle
from satloc.persist import ArraySpec, load_npz, read_json, save_npz, write_json
from satloc_env.world.scene import SCENES_DIR

__all__ = ["ACTIVE_FORMAT", "SLOTS", "ActiveMapConfig", "ActiveMap", "both_ways_circuit", "build_active_map",
           "active_map_path", "SHIPPED_DIR"]

ACTIVE_FORMAT = "satloc-active-map"
#: the action slots of a junction, by the turn of the branch: left (> 45 degrees), straight, right (< -45)
SLOTS = ("left", "straight", "right")
_SLOT_TURN = math.radians(45.0)

#: where the package's active maps lie (``scenes/active/<scene>.npz``)
SHIPPED_DIR = SCENES_DIR / "active"


@dataclass(frozen=True)
class ActiveMapConfig:
    """How :func:`build_active_map` makes an active map (the defaults made the shipped ones)."""

    scene: str = "active_grid"
    resolution: str = "half"
    database_spacing_m: float = 1.0      # database pass: a frame every this many metres
    frame_spacing_m: float = 5.0         # query pass: a frame (a localization) every this many metres
    candidate_spacing_m: float = 1.0     # the localizer's candidates along the database path ...
    lateral_offsets_m: tuple[float, ...] = (-1.0, 0.0, 1.0)   # ... and across it
    min_relative: float = 1e-4           # posterior entries below this fraction of the frame's largest are dropped
    query_seed: int = 1

    def __post_init__(self):
        if not _FLOOR <= self.min_relative < 1 or min(self.frame_spacing_m, self.database_spacing_m,
                                                       self.candidate_spacing_m) <= 0:
            raise ConfigError(f"active map: min_relative in [{_FLOOR:g}, 1) (a map stores values down to {_FLOOR:g} "
                              "of each frame's largest) and spacings > 0 are required")


def both_ways_circuit(graph) -> list:
    """A closed walk (node list, first == last) over every edge of the undirected ``graph`` (networkx, simple)
    once in each direction, never turning back at a node that has another way out.

    At every node the arriving directions are paired with the leaving ones by rotating the sorted neighbour
    list (arriving from neighbour i, leave to neighbour i + 1: never back, unless the node is a dead end), which
    splits the streets into closed walks; walks meeting at a node are then merged by swapping two of its
    pairings (keeping both free of U-turns). The route the ``tour:`` of the ActiveLoc scenes was made with.

    Such a swap exists only where four or more streets meet (at a T-junction every swap makes a U-turn), so some
    connected graphs that have a tour are refused (e.g. a square with one diagonal): ConfigError. The grids of
    the ActiveLoc scenes are toured."""
    nodes = sorted(graph.nodes)
    trans: dict[tuple, Any] = {}
    for n in nodes:
        nb = sorted(graph.neighbors(n))
        if not nb:
            continue
        for i, a in enumerate(nb):
            trans[(a, n)] = nb[(i + 1) % len(nb)]

    def cycles() -> list[list[tuple]]:
        seen: set = set()
        out = []
        for e in sorted(trans):
            if e in seen:
                continue
            cyc, cur = [], e
            while cur not in seen:
                seen.add(cur)
                cyc.append(cur)
                cur = (cur[1], trans[cur])
            out.append(cyc)
        return out

    cs = cycles()
    while len(cs) > 1:
        cid = {e: i for i, c in enumerate(cs) for e in c}
        merged = False
        for n in nodes:
            arriving = [(a, n) for a in sorted(graph.neighbors(n))]
            for e1, e2 in itertools.combinations(arriving, 2):
                o1, o2 = trans[e1], trans[e2]
                if cid[e1] != cid[e2] and o2 != e1[0] and o1 != e2[0]:
                    trans[e1], trans[e2] = o2, o1
                    merged = True
                    break
            if merged:
                break
        if not merged:
            raise ConfigError(f"both_ways_circuit: {len(cs)} closed walks could not be merged: the graph is not "
                              "connected, or its walks meet only where fewer than four streets meet (this method "
                              "merges walks only at such crossings; give the scene a tour of your own)")
        cs = cycles()
    if not cs:
        raise ConfigError("both_ways_circuit: the graph has no edge")
    return [cs[0][0][0]] + [n for _, n in cs[0]]


def active_map_path(scene: str | os.PathLike) -> Path:
    """The npz of an active map: a path to one, or a scene name with a map in :data:`SHIPPED_DIR`."""
    p = Path(scene)
    if p.suffix == ".npz":
        if not p.is_file():
            raise ConfigError(f"active map {p}: file not found")
        return p
    shipped = SHIPPED_DIR / f"{p.name}.npz"
    if shipped.is_file():
        return shipped
    have = sorted(q.stem for q in SHIPPED_DIR.glob("*.npz")) if SHIPPED_DIR.is_dir() else []
    raise ConfigError(f"active map {str(scene)!r}: no such file, and no shipped map of that scene (shipped: "
                      f"{', '.join(have) or 'none'}); make one with `satloc agent map --scene SCENE --out DIR`")


_SPEC = {
    "nodes": ArraySpec("f", ("N", 2)),
    "legs": ArraySpec("iu", ("L", 2), min=0),
    "candidates": ArraySpec("f", ("M", 3)),
    "cand_leg": ArraySpec("iu", ("M",), min=0),
    "cand_rest": ArraySpec("f", ("M",)),
    "frame_pose": ArraySpec("f", ("Q", 3)),
    "frame_leg": ArraySpec("iu", ("Q",), min=0),
    "frame_rest": ArraySpec("f", ("Q",)),
    "post_ptr": ArraySpec("iu", ("Q1",), min=0),
    "post_gap": ArraySpec("iu", ("E",), min=0),
    "post_level": ArraySpec("u", ("E",)),
    "post_max": ArraySpec("f", ("Q",), min=0),
}
#: posterior values are stored as uint8 levels of -log10(value / the frame's largest), LEVELS per decade
LEVELS = 255 / 4.0
#: the smallest value a stored posterior row holds, relative to its largest (level 255: 4 decades down)
_FLOOR = 10.0 ** (-255 / LEVELS)


class ActiveMap:
    """Junctions ``nodes`` (N, 2) map metres, directed ``legs`` (L, 2) node pairs in tour order, the
    localizer's ``candidates`` (M, 3) with the leg each lies on (``cand_leg``) and its distance to that leg's
    end (``cand_rest``), and per recorded frame its true pose, leg, distance to the leg's end and posterior
    over the candidates (sparse rows: :meth:`posterior`). ``meta``: how it was made."""

    def __init__(self, arrays: dict[str, np.ndarray], meta: dict, where: str = "active map"):
        self.meta = dict(meta)
        self.where = where
        # the satellite gap its posteriors were localized at: a map made before the knob (no ``satellite_gap``
        # in its meta, e.g. the shipped maps) localized on the ground's copy, gap 0, with lane-exact passes
        self.satellite_gap = float(self.meta.get("satellite_gap", 0.0))
        self.nodes = np.asarray(arrays["nodes"], np.float64)
        self.legs = np.asarray(arrays["legs"], np.int64)
        self.candidates = np.asarray(arrays["candidates"], np.float64)
        self.cand_leg = np.asarray(arrays["cand_leg"], np.int64)
        self.cand_rest = np.asarray(arrays["cand_rest"], np.float64)
        self.frame_pose = np.asarray(arrays["frame_pose"], np.float64)
        self.frame_leg = np.asarray(arrays["frame_leg"], np.int64)
        self.frame_rest = np.asarray(arrays["frame_rest"], np.float64)
        self._ptr = np.asarray(arrays["post_ptr"], np.int64)
        self._idx = np.asarray(arrays["post_idx"], np.int64)
        self._val = np.asarray(arrays["post_val"], np.float64)
        self._check()
        a, b = self.legs[:, 0], self.legs[:, 1]
        d = self.nodes[b] - self.nodes[a]
        self.leg_length = np.hypot(d[:, 0], d[:, 1])
        self.leg_heading = np.arctan2(d[:, 1], d[:, 0])
        #: the leg that runs from each leg's end to its start (every leg has one)
        index = {(int(u), int(v)): i for i, (u, v) in enumerate(self.legs)}
        self.reverse = np.array([index[(int(v), int(u))] for u, v in self.legs])
        #: per leg, its frames in driving order (farthest from the leg's end first)
        order = np.lexsort((-self.frame_rest, self.frame_leg))
        self.leg_frames = np.split(order, np.searchsorted(self.frame_leg[order], np.arange(1, len(self.legs))))
        #: per leg: the branch at its end in each slot (-1: none), the way back excluded
        self.branches = np.full((len(self.legs), len(SLOTS)), -1, np.int64)
        self.turns = np.zeros((len(self.legs), len(SLOTS)))
        leaving: dict[int, list[int]] = {}
        for i, (u, _) in enumerate(self.legs):
            leaving.setdefault(int(u), []).append(i)
        for i, (u, v) in enumerate(self.legs):
            for j in leaving.get(int(v), []):
                if self.legs[j, 1] == u:
                    continue
                turn = float(wrap_angle(self.leg_heading[j] - self.leg_heading[i]))
                slot = 0 if turn > _SLOT_TURN else (2 if turn < -_SLOT_TURN else 1)
                if self.branches[i, slot] >= 0:
                    raise FormatError(f"{where}: two branches turn {SLOTS[slot]} at junction {int(v)} "
                                      f"(legs {self.branches[i, slot]} and {j}); ActiveLoc needs at most one per slot")
                self.branches[i, slot], self.turns[i, slot] = j, turn
        self.next_in_tour = (np.arange(len(self.legs)) + 1) % len(self.legs)

    def _check(self) -> None:
        w = self.where
        n, l, m, q = len(self.nodes), len(self.legs), len(self.candidates), len(self.frame_pose)
        if l == 0 or q == 0 or m == 0:
            raise FormatError(f"{w}: no legs, frames or candidates")
        if self.legs.max() >= n or self.cand_leg.max() >= l or self.frame_leg.max() >= l:
            raise FormatError(f"{w}: a leg, candidate or frame refers to a junction or leg that does not exist")
        if len(self._ptr) != q + 1 or self._ptr[0] != 0 or np.any(np.diff(self._ptr) < 0) \
                or self._ptr[-1] != len(self._idx) or len(self._idx) != len(self._val):
            raise FormatError(f"{w}: damaged posterior rows (post_ptr / post_idx / post_val)")
        if len(self._idx) and (self._idx.max() >= m or self._idx.min() < 0):
            raise FormatError(f"{w}: a posterior entry refers to a candidate that does not exist")
        inner = np.ones(len(self._idx), bool)          # entries that follow another of the same row
        inner[self._ptr[:-1][np.diff(self._ptr) > 0]] = False
        if np.any(np.diff(self._idx)[inner[1:]] <= 0):
            raise FormatError(f"{w}: the candidates of a posterior row must be in increasing order, each once")
        if not np.all(np.isfinite(self._val) & (self._val > 0)):
            raise FormatError(f"{w}: posterior values must be finite and > 0 (rows hold only their non-zero entries)")
        pairs = {(int(u), int(v)) for u, v in self.legs}
        if len(pairs) != l or any((v, u) not in pairs for u, v in pairs):
            raise FormatError(f"{w}: every street must be one leg in each direction (each pair once)")
        empty = [i for i in range(l) if not np.any(self.frame_leg == i)]
        if empty:
            raise FormatError(f"{w}: legs {empty[:5]} have no recorded frame")

    def posterior(self, frame: int) -> np.ndarray:
        """The localizer's posterior P(L | I) over the candidates for recorded frame ``frame`` (dense, (M,));
    all zeros where the frame could not be localized (no grid sample with depth: an occluder fills the view)."""
        p = np.zeros(len(self.candidates))
        a, b = self._ptr[frame], self._ptr[frame + 1]
        p[self._idx[a:b]] = self._val[a:b]
        return p

    @property
    def scene(self) -> str:
        return str(self.meta.get("scene", "?"))

    def save(self, path: str | os.PathLike) -> None:
        """Write the map (npz, format ``satloc-active-map``). Posterior rows are stored compactly: candidate
        indices as gaps from the previous entry of the row (uint16 when they fit), values as uint8 levels of
        -log10(value / the row's largest), :data:`LEVELS` per decade (steps of 3.7 %, so a stored value is within
        1.8 % of the original; level 255 is 4 decades below the row's largest), and each row's largest as float32.
        A value further below its row's largest than that cannot be stored: ValueError, nothing written (maps
        built with ``min_relative`` >= 1e-4 have none)."""
        q = len(self.frame_pose)
        rows = np.repeat(np.arange(q), np.diff(self._ptr))
        first = np.zeros(len(self._idx), bool)
        first[self._ptr[:-1][np.diff(self._ptr) > 0]] = True
        gap = np.where(first, self._idx, self._idx - np.concatenate([[0], self._idx[:-1]]))
        vmax = np.zeros(q)
        np.maximum.at(vmax, rows, self._val)
        raw = -np.log10(self._val / vmax[rows]) * LEVELS
        bad = np.flatnonzero(raw > 255.5)
        if len(bad):
            k = int(bad[0])
            raise ValueError(f"{path}: frame {int(rows[k])} has a posterior value of {10 ** (-raw[k] / LEVELS):.3g} of "
                             f"its row's largest, below the {_FLOOR:g} a map can store; drop such entries before saving "
                             "(nothing written)")
        level = np.clip(np.round(raw), 0, 255)
        arrays = dict(nodes=self.nodes, legs=self.legs, candidates=self.candidates, cand_leg=self.cand_leg,
                      cand_rest=self.cand_rest, frame_pose=self.frame_pose, frame_leg=self.frame_leg,
                      frame_rest=self.frame_rest, post_ptr=self._ptr,
                      post_gap=gap.astype(np.uint16 if gap.max(initial=0) < 2 ** 16 else np.int64),
                      post_level=level.astype(np.uint8), post_max=vmax.astype(np.float32))
        save_npz(path, ACTIVE_FORMAT, arrays, self.meta)

    @classmethod
    def load(cls, path_or_scene: str | os.PathLike) -> "ActiveMap":
        """From an npz written by :meth:`save`, or the shipped map of a scene name (:func:`active_map_path`)."""
        path = active_map_path(path_or_scene)
        arrays, meta = load_npz(path, ACTIVE_FORMAT, _SPEC)
        ptr = np.asarray(arrays["post_ptr"], np.int64)
        gap = np.asarray(arrays.pop("post_gap"), np.int64)
        if len(ptr) != len(arrays["frame_pose"]) + 1 or ptr[0] != 0 or np.any(np.diff(ptr) < 0) or ptr[-1] != len(gap):
            raise FormatError(f"{path}: damaged posterior rows (post_ptr)")
        counts = np.diff(ptr)
        rows = np.repeat(np.arange(len(counts)), counts)
        # undo the gaps: a cumulative sum restarted at the first entry of each row
        csum = np.cumsum(gap)
        start = np.repeat(csum[ptr[:-1][counts > 0]] - gap[ptr[:-1][counts > 0]], counts[counts > 0])
        arrays["post_idx"] = csum - start
        level = np.asarray(arrays.pop("post_level"), np.float64)
        arrays["post_val"] = np.asarray(arrays.pop("post_max"), np.float64)[rows] * 10.0 ** (-level / LEVELS)
        return cls(arrays, meta, where=str(path))


# --- building -------------------------------------------------------------------------------------------
def _legs_of_route(route) -> tuple[np.ndarray, np.ndarray]:
    """Junctions and legs of a closed route whose waypoints are junctions."""
    if not route.closed or route.laps != 1:
        raise ConfigError(f"active map: route {route.name} must be closed, one lap (its waypoints the junctions, "
                          "every street once each way)")
    pts = route.points[:-1]
    key = [tuple(np.round(p, 3)) for p in pts]
    ids: dict[tuple, int] = {}
    for k in key:
        ids.setdefault(k, len(ids))
    nodes = np.array(list(ids.keys()), np.float64)
    seq = [ids[k] for k in key]
    legs = np.array([(seq[i], seq[(i + 1) % len(seq)]) for i in range(len(seq))], np.int64)
    return nodes, legs


def _leg_of_poses(poses: np.ndarray, nodes: np.ndarray, legs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For poses (n, 3): the leg each lies on (nearest leg segment among those heading within 60 degrees of
    it, distance plus 5 m per radian of heading difference) and the distance to that leg's end."""
    a, b = nodes[legs[:, 0]], nodes[legs[:, 1]]
    ab = b - a
    length = np.hypot(ab[:, 0], ab[:, 1])
    heading = np.arctan2(ab[:, 1], ab[:, 0])
    out_leg = np.empty(len(poses), np.int64)
    out_rest = np.empty(len(poses))
    for s in range(0, len(poses), 4096):
        p = poses[s:s + 4096]
        t = np.clip(((p[:, None, :2] - a[None]) * ab[None]).sum(-1) / length[None] ** 2, 0, 1)   # (n, L)
        q = a[None] + t[..., None] * ab[None]
        d = np.hypot(*(q - p[:, None, :2]).transpose(2, 0, 1))
        dh = np.abs(wrap_angle(p[:, None, 2] - heading[None]))
        cost = np.where(dh <= math.radians(60.0), d + 5.0 * dh, np.inf)
        cost = np.where(np.isfinite(cost).any(1, keepdims=True), cost, d + 5.0 * dh)
        j = np.argmin(cost, axis=1)
        out_leg[s:s + len(p)] = j
        out_rest[s:s + len(p)] = (1.0 - t[np.arange(len(p)), j]) * length[j]
    return out_leg, out_rest


def _recorded(out: Path, rec) -> bool:
    """Whether ``out`` holds a complete recording of ``rec`` (same scene files and satloc version)."""
    from satloc import __version__

    from .record import STATUS, record_stamp, scene_identity

    try:
        st = read_json(out / STATUS, "recording")
    except FormatError:
        return False
    return bool(st.get("complete")) and st.get("config") == record_stamp(rec) \
        and st.get("scene_sha256") == scene_identity(rec.scene)[2] and st.get("satloc_version") == __version__


def build_active_map(config: ActiveMapConfig | dict | None = None, work: str | os.PathLike = "active_work",
                     out: str | os.PathLike | None = None, progress: bool = True, log=print) -> Path:
    """Record, build and localize (see the module docstring) into ``work`` and write the map to ``out``
    (default ``work/<scene>.npz``). Finished stages in ``work`` are reused (the recorder's own resume and a
    stamp per stage). Returns the map's path."""
    from satloc.config import from_dict
    from satloc.features.projection import ProjectionConfig
    from satloc.localizers.database import LocalizerConfig
    from satloc.pipeline import BuildConfig, build, load_localizer, train_projection
    from satloc.sequence import Sequence
    from satloc_env.world.scene import load_scene

    from .record import PassConfig, RecordConfig, record_passes, record_stamp, scene_identity

    if config is None:
        cfg = ActiveMapConfig()
    elif isinstance(config, dict):
        cfg = from_dict(ActiveMapConfig, config, "active map config")
    else:
        cfg = config
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    scene = load_scene(cfg.scene)
    route = scene.spec.database_route
    if scene.spec.query_route != route:
        raise ConfigError(f"active map: scene {cfg.scene!r} must drive one route in both passes (database_route "
                          f"{route!r}, query_route {scene.spec.query_route!r}): a closed route whose waypoints are the "
                          "junctions in driving order, every street once each way (satloc_env.envs.active_map.both_ways_circuit)")
    nodes, legs = _legs_of_route(scene.routes[route])
    pairs = [(int(u), int(v)) for u, v in legs]
    if len(set(pairs)) != len(pairs) or any((v, u) not in set(pairs) for u, v in pairs):
        raise ConfigError(f"active map: scene {cfg.scene!r}: route {route!r} must drive every street once in each "
                          "direction between junctions (its waypoints the junctions in driving order; "
                          "satloc_env.envs.active_map.both_ways_circuit makes one)")
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    rec = RecordConfig(scene=cfg.scene, resolution=cfg.resolution,
                       database=PassConfig(spacing_m=cfg.database_spacing_m),
                       query=PassConfig(lane_offset_m=-0.75, spacing_m=cfg.frame_spacing_m,
                                        occlusion=0.3, appearance=0.5, change=0.5, seed=cfg.query_seed))
    if not _recorded(work / "rec", rec):
        record_passes(rec, work / "rec", progress)
    times["record_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    bdir = work / "build"
    stamp = {"record": record_stamp(rec), "build": to_dict(BuildConfig(), runtime=False),
             "projection": to_dict(ProjectionConfig(), runtime=False)}
    done = work / "build_stage.json"
    if not (done.is_file() and read_json(done) == stamp and (bdir / "projections.pt").is_file()):
        done.unlink(missing_ok=True)
        log(f"[{cfg.scene}] building the dictionary and learning the projections")
        build(work / "rec" / "database", work / "rec" / "map", bdir, BuildConfig(), progress)
        train_projection(bdir, ProjectionConfig(), progress)
        write_json(done, stamp)
    times["build_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    lc = LocalizerConfig(candidate_spacing_m=cfg.candidate_spacing_m, lateral_offsets_m=cfg.lateral_offsets_m,
                         prune_regions=0)
    loc = load_localizer(bdir, lc, progress=progress)
    query = Sequence.load(work / "rec" / "query")
    poses = np.asarray(query.poses, np.float64)
    from tqdm import tqdm

    ptr, idx, val = [0], [], []
    failed = 0
    for r in tqdm(loc.localize_stream(iter(query), errors="yield"), total=len(query), desc="localizing the frames",
                  unit="frame", disable=not progress, leave=False):
        if isinstance(r, ConfigError):   # e.g. an occluder fills the view: no posterior (the tracker only moves)
            failed += 1
            idx.append(np.zeros(0, np.int64))
            val.append(np.zeros(0))
            ptr.append(ptr[-1])
            continue
        p = np.asarray(r.posterior, np.float64)
        top = np.flatnonzero((p > 0) & (p >= cfg.min_relative * p.max()))
        idx.append(top)
        val.append(p[top])
        ptr.append(ptr[-1] + len(top))
    times["localize_s"] = time.perf_counter() - t0
    cands = np.asarray(loc.candidates, np.float64)
    cand_leg, cand_rest = _leg_of_poses(cands, nodes, legs)
    frame_leg, frame_rest = _leg_of_poses(poses, nodes, legs)
    _, _, sha, _ = scene_identity(cfg.scene)
    meta = dict(scene=scene.name, scene_sha256=sha, satellite_gap=scene.spec.knobs.satellite_gap,
                passes={"database": to_dict(rec.database), "query": to_dict(rec.query)},
                config=to_dict(cfg), localizer=to_dict(lc, runtime=False),
                frames=len(poses), unlocalized_frames=failed, candidates=len(cands), times_s={k: round(v, 1) for k, v in times.items()})
    amap = ActiveMap(dict(nodes=nodes, legs=legs, candidates=cands, cand_leg=cand_leg, cand_rest=cand_rest,
                          frame_pose=poses, frame_leg=frame_leg, frame_rest=frame_rest,
                          post_ptr=np.asarray(ptr, np.int64), post_idx=np.concatenate(idx).astype(np.int64),
                          post_val=np.concatenate(val)), meta, where=f"active map of {cfg.scene}")
    path = Path(out) if out is not None else work / f"{scene.name}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    amap.save(path)
    log(f"[{cfg.scene}] active map {path}: {len(legs)} legs, {len(poses)} frames, {len(cands)} candidates "
        f"({', '.join(f'{k} {v:.0f} s' for k, v in times.items())})")
    return path
