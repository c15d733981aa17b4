"""Soak benchmark: memory and open files over a long run (a benchmark that prints figures, not a timed test).

Two phases, one process:

* **env**: ``satloc/SatLoc-v0`` driven by its autopilot with a localizer and tracking (``localizer_track``) for
  ``steps`` steps, in episodes of at most ``episode_steps`` (a new episode with a new seed at every end);
* **stream**: :meth:`satloc.localizers.database.Localizer.localize_stream` over ``queries`` queries, tracked, taken in a
  cycle from a short query pass that the env records into a temporary sequence folder, so that each query is
  read from disk (PNG files opened and closed) as ``satloc localize`` reads them.

Every ``sample_every`` steps (``query_sample_every`` queries) it prints a JSON line with the resident memory
(``rss_mb``: psutil when installed, else ``VmRSS`` of ``/proc/self/status``), the open file descriptors
(``fds``: the entries of ``/proc/self/fd``) and the rate since the previous sample, and after each phase a summary
line: RSS and fds at its start and end, the peak RSS (``VmHWM``, reset at the start of the phase where the kernel
allows it, see ``peak_scope``), the least-squares slopes ``rss_slope_mb_per_1000`` and ``fds_slope_per_1000``
over the samples after ``warmup`` steps (queries), and steps (queries) per second. ``--out`` also writes it all
as one JSON file (written atomically).

The localizer: by default (``--localizer small``) a small build of the scene's first ``small_frames`` database
frames with the default feature set, built once into the auto localizer's cache (:mod:`satloc_env.envs.auto_localizer`)
beside, not in place of, the full ``"auto"`` entry; ``--localizer auto`` uses the env's default (the whole
database pass; its first build takes many minutes) and a directory a build of ``satloc build``.

``--tracemalloc`` also compares Python allocation snapshots taken after the warm-up and at the end of each phase
and prints the 10 largest growths (slow: use it to locate a leak, not to measure).

Usage::

    python -m satloc_env.experiments.soak --steps 20000 --queries 2000 --scene city --out soak.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from satloc.config import to_dict
from satloc.errors import ConfigError


@dataclass
class SoakConfig:
    steps: int = 20000                  # env steps (over several episodes)
    queries: int = 2000                 # localize_stream queries
    scene: str = "city"
    episode_steps: int = 300            # an episode's max_steps (it also ends at the route's end or off the road)
    localize_every: int = 1             # the env localizes at reset and every N steps
    track: bool = True                  # localizer_track in the env; a tracker in the stream
    sample_every: int = 500             # steps between samples
    query_sample_every: int = 100       # queries between samples
    warmup: float = 0.1                 # the fraction of each phase left out of the slopes
    localizer: str = "small"            # "small", "auto" or a build directory
    small_frames: int = 200             # database frames of the "small" build
    small_features: str = "default"     # its feature set
    query_frames: int = 40              # frames of the query pass the stream cycles through
    query_spacing_steps: int = 3        # env steps between two of them
    resolution: str = "half"
    seed: int = 0
    cache_dir: str | None = None        # the small build's cache root (default: the auto localizer's)

    def __post_init__(self):
        for k in ("steps", "queries", "episode_steps", "localize_every", "sample_every", "query_sample_every",
                  "small_frames", "query_frames", "query_spacing_steps"):
            if getattr(self, k) < 1:
                raise ConfigError(f"soak {k}: expected an integer >= 1, got {getattr(self, k)}")
        if not 0.0 <= self.warmup < 1.0:
            raise ConfigError(f"soak warmup: expected a fraction in [0, 1), got {self.warmup}")


# --- measurements ---------------------------------------------------------------------------------------------
def _status_kb(field: str) -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return float(line.split()[1])
    except OSError:
        pass
    return None


def rss_mb() -> float:
    """Resident memory of this process, MB (psutil when installed, else ``VmRSS``)."""
    try:
        import psutil
    except ImportError:
        kb = _status_kb("VmRSS")
        return float("nan") if kb is None else kb / 1024
    return psutil.Process().memory_info().rss / 2**20


def peak_rss_mb() -> float:
    """Peak resident memory (``VmHWM``), MB."""
    kb = _status_kb("VmHWM")
    if kb is None:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return kb / 1024


def reset_peak() -> bool:
    """Reset ``VmHWM`` to the current RSS (Linux >= 4.0: ``5`` into ``/proc/self/clear_refs``); False if refused."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def open_fds() -> int:
    """Open file descriptors of this process (the listing's own descriptor excluded)."""
    try:
        return len(os.listdir("/proc/self/fd")) - 1
    except OSError:
        return -1


def slope_per_1000(x, y) -> float:
    """Least-squares slope of ``y`` against ``x``, per 1000 of ``x`` (NaN for fewer than 2 distinct x)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if len(x) < 2 or np.ptp(x) == 0:
        return float("nan")
    return float(np.polyfit(x, y, 1)[0] * 1000)


class _Phase:
    """Samples of one phase and its summary."""

    def __init__(self, name: str, unit: str, total: int, warmup: float, emit: Callable[[dict], None],
                 trace: bool):
        self.name, self.unit, self.total, self.emit, self.trace = name, unit, total, emit, trace
        self.warmup_n = int(round(warmup * total))
        self.peak_scope = "phase" if reset_peak() else "process"
        self.samples: list[dict] = []
        self.t0 = self.t_last = time.perf_counter()
        self.n_last = 0
        self.snap = None
        self.sample(0)

    def sample(self, n: int, **extra) -> None:
        now = time.perf_counter()
        rate = (n - self.n_last) / (now - self.t_last) if n > self.n_last else float("nan")
        s = {"soak": self.name, self.unit: n, "rss_mb": round(rss_mb(), 1), "fds": open_fds(),
             "elapsed_s": round(now - self.t0, 1), f"{self.unit}_per_s": _r(rate, 2), **extra}
        self.samples.append(s)
        self.t_last, self.n_last = now, n
        self.emit(s)
        if self.trace and self.snap is None and n >= self.warmup_n:
            import tracemalloc

            self.snap = tracemalloc.take_snapshot()

    def summary(self, n: int, **extra) -> dict:
        if self.samples[-1][self.unit] != n:
            self.sample(n)
        dt = time.perf_counter() - self.t0
        after = [s for s in self.samples if s[self.unit] >= self.warmup_n]
        xs = [s[self.unit] for s in after]
        first, last = self.samples[0], self.samples[-1]
        out = {"soak": self.name, "summary": True, self.unit: n,
               "rss_start_mb": first["rss_mb"], "rss_end_mb": last["rss_mb"],
               "rss_peak_mb": round(max(peak_rss_mb(), max(s["rss_mb"] for s in self.samples)), 1),
               "peak_scope": self.peak_scope,
               "rss_max_sampled_mb": max(s["rss_mb"] for s in self.samples),
               "rss_after_warmup_mb": after[0]["rss_mb"] if after else None,
               "fds_start": first["fds"], "fds_end": last["fds"], "fds_max": max(s["fds"] for s in self.samples),
               f"warmup_{self.unit}": self.warmup_n,
               "rss_slope_mb_per_1000": _r(slope_per_1000(xs, [s["rss_mb"] for s in after]), 3),
               "fds_slope_per_1000": _r(slope_per_1000(xs, [s["fds"] for s in after]), 3),
               f"{self.unit}_per_s": _r(n / dt if dt > 0 else float("nan"), 2), "seconds": round(dt, 1),
               "load_avg_1m": round(os.getloadavg()[0], 2), **extra}
        if self.trace and self.snap is not None:
            import tracemalloc

            stats = tracemalloc.take_snapshot().compare_to(self.snap, "lineno")[:10]
            out["tracemalloc_top"] = [f"{s.traceback[0].filename}:{s.traceback[0].lineno} "
                                      f"{s.size_diff / 1024:+.1f} KiB ({s.count_diff:+d} blocks)" for s in stats]
        return out


def _r(v: float, nd: int):
    """``v`` rounded (no -0.0), None when it is not finite (JSON has no NaN)."""
    return None if v is None or not math.isfinite(v) else round(v, nd) + 0.0


# --- the run --------------------------------------------------------------------------------------------------
def _localizer_arg(cfg: SoakConfig, progress: bool, build_config=None, projection_config=None) -> tuple[str, str]:
    """(the env's ``localizer`` argument, a description of it)."""
    if cfg.localizer == "auto":
        return "auto", f"auto (the whole database pass of {cfg.scene!r})"
    if cfg.localizer != "small":
        return cfg.localizer, f"build directory {cfg.localizer}"
    from satloc.pipeline import BuildConfig
    from satloc_env.envs.auto_localizer import auto_build_dir

    bc = build_config if build_config is not None else BuildConfig(features=cfg.small_features)
    b = auto_build_dir(cfg.scene, None, cfg.resolution, progress, max_frames=cfg.small_frames, build_config=bc,
                       projection_config=projection_config, cache_dir=cfg.cache_dir)
    return str(b), (f"small: the first {cfg.small_frames} database frames of {cfg.scene!r}, features "
                    f"{bc.features!r} ({b})")


def soak(cfg: SoakConfig = SoakConfig(), emit: Callable[[dict], None] | None = None, progress: bool = False,
         tracemalloc_on: bool = False, build_config=None, projection_config=None) -> dict:
    """Run both phases; returns ``{"config", "localizer", "env", "stream", "samples"}`` (the summaries and every
    sample). ``emit`` receives each sample and summary as it comes (e.g. to print JSON lines).
    ``build_config``/``projection_config`` replace the small build's (tests)."""
    import gymnasium as gym

    from satloc.sequence import Frame, Sequence
    from satloc.tracking.track import relative_motion
    from satloc_env.envs import ENV_ID

    emit = emit or (lambda d: None)
    if tracemalloc_on:
        import tracemalloc

        tracemalloc.start()
    process_start = {"rss_mb": round(rss_mb(), 1), "fds": open_fds()}
    loc_arg, loc_desc = _localizer_arg(cfg, progress, build_config, projection_config)
    env = gym.make(ENV_ID, scene=cfg.scene, resolution=cfg.resolution, localizer=loc_arg,
                   localizer_track=cfg.track, localize_every=cfg.localize_every, max_steps=cfg.episode_steps)
    samples: list[dict] = []

    def record(d: dict) -> None:
        if not d.get("summary"):
            samples.append(d)
        emit(d)

    try:
        # --- phase 1: the environment ------------------------------------------------------------------
        env.reset(seed=cfg.seed)           # loads the scene, the localizer (and builds "auto" on first use)
        episodes, localized, finite, err_sum = 1, 0, 0, 0.0
        phase = _Phase("env", "steps", cfg.steps, cfg.warmup, record, tracemalloc_on)
        for i in range(1, cfg.steps + 1):
            _, _, term, trunc, info = env.step(env.unwrapped.autopilot_action())
            if "localized_step" in info and info["localized_step"] == info["step"]:   # localized at this step
                localized += 1
                if np.isfinite(info["error_m"]):
                    finite += 1
                    err_sum += float(info["error_m"])
            if term or trunc:
                env.reset(seed=cfg.seed + episodes)
                episodes += 1
            if i % cfg.sample_every == 0:
                phase.sample(i, episodes=episodes)
        env_summary = phase.summary(cfg.steps, episodes=episodes, localizations=localized,
                                    localizations_with_result=finite,
                                    mean_error_m=_r(err_sum / finite if finite else float("nan"), 2))
        record(env_summary)
        # --- phase 2: localize_stream over queries read from disk ----------------------------------------
        loc = getattr(env.unwrapped.localizer, "engine", None)   # the paper's method itself: its stream
        u = env.unwrapped
        with tempfile.TemporaryDirectory(prefix="satloc_soak_") as tmp:
            env.reset(seed=cfg.seed + 10_000, options={"lane_offset_m": -1.25})   # another lane than the database
            frames = []
            for k in range(cfg.query_frames * cfg.query_spacing_steps):
                _, _, term, trunc, _ = env.step(u.autopilot_action())
                if k % cfg.query_spacing_steps == 0:
                    o = u._last_obs
                    frames.append(Frame(o["left"].copy(), o["right"].copy(), u.pose, u.steps * u._episode.dt))
                if term or trunc:
                    break
            Sequence(u.camera, frames, "soak_query").save(Path(tmp) / "query")
            del frames
            seq = Sequence.load(Path(tmp) / "query")
            n = len(seq)
            poses = seq.poses
            cycle = [relative_motion(_pose(poses[k - 1]), _pose(poses[k])) for k in range(n)]  # [0]: last -> first
            tracker = loc.tracker() if cfg.track else None
            odometry = (cycle[j % n] for j in range(cfg.queries)) if cfg.track else None
            phase = _Phase("stream", "queries", cfg.queries, cfg.warmup, record, tracemalloc_on)
            q_errors, q_sum, q_fin = 0, 0.0, 0
            stream = loc.localize_stream((seq[j % n] for j in range(cfg.queries)), errors="yield", tracker=tracker,
                                         odometry=odometry)
            for j, r in enumerate(stream, 1):
                if isinstance(r, ConfigError):
                    q_errors += 1
                else:
                    q_fin += 1
                    q_sum += r.estimate.distance(_pose(poses[(j - 1) % n]))
                if j % cfg.query_sample_every == 0:
                    phase.sample(j)
            del stream, seq
        stream_summary = phase.summary(cfg.queries, query_frames=n, frames_without_result=q_errors,
                                       mean_error_m=_r(q_sum / q_fin if q_fin else float("nan"), 2))
        record(stream_summary)
    finally:
        env.close()
        if tracemalloc_on:
            import tracemalloc

            tracemalloc.stop()
    return {"config": to_dict(cfg), "localizer": loc_desc, "process_start": process_start, "env": env_summary,
            "stream": stream_summary, "samples": samples}


def _pose(p):
    from satloc.geometry import Pose2

    return Pose2(*np.asarray(p, np.float64))


def main(argv: list[str] | None = None) -> int:
    d = SoakConfig()
    ap = argparse.ArgumentParser(prog="python -m satloc_env.experiments.soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=d.steps, help="env steps (default %(default)s)")
    ap.add_argument("--queries", type=int, default=d.queries, help="localize_stream queries (default %(default)s)")
    ap.add_argument("--scene", default=d.scene, help="scene name, YAML or saved scene (default %(default)s)")
    ap.add_argument("--episode-steps", type=int, default=d.episode_steps, help="max steps of an episode")
    ap.add_argument("--localize-every", type=int, default=d.localize_every, help="localize every N env steps")
    ap.add_argument("--sample-every", type=int, default=d.sample_every, help="env steps between samples")
    ap.add_argument("--query-sample-every", type=int, default=d.query_sample_every, help="queries between samples")
    ap.add_argument("--warmup", type=float, default=d.warmup, help="fraction of a phase left out of the slopes")
    ap.add_argument("--localizer", default=d.localizer, help="'small' (default), 'auto' or a build directory")
    ap.add_argument("--small-frames", type=int, default=d.small_frames, help="database frames of the small build")
    ap.add_argument("--small-features", default=d.small_features, choices=("default", "rgb", "semantic"))
    ap.add_argument("--no-track", action="store_true", help="no tracking (env and stream)")
    ap.add_argument("--resolution", default=d.resolution, choices=("half", "full"))
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--cache-dir", default=None, help="cache root of the small build (default: the auto cache's)")
    ap.add_argument("--tracemalloc", action="store_true", help="report the largest Python allocation growths")
    ap.add_argument("--progress", action="store_true", help="show build progress on stderr")
    ap.add_argument("--out", default=None, help="also write everything as one JSON file")
    a = ap.parse_args(argv)
    try:
        cfg = SoakConfig(steps=a.steps, queries=a.queries, scene=a.scene, episode_steps=a.episode_steps,
                         localize_every=a.localize_every, track=not a.no_track, sample_every=a.sample_every,
                         query_sample_every=a.query_sample_every, warmup=a.warmup, localizer=a.localizer,
                         small_frames=a.small_frames, small_features=a.small_features, resolution=a.resolution,
                         seed=a.seed, cache_dir=a.cache_dir)
        res = soak(cfg, emit=lambda x: print(json.dumps(x), flush=True), progress=a.progress,
                   tracemalloc_on=a.tracemalloc)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.out:
        from satloc.persist import atomic_path

        with atomic_path(a.out) as tmp:
            tmp.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
