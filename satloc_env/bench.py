"""Benchmarks that print figures (never timed tests)."""
from __future__ import annotations

import resource
import time

from .env import SatLocEnv


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def bench_env(resolution: str = "half", steps: int = 2000, scene: str = "city", warmup: int = 20) -> dict:
    """Stereo colour + depth steps per second driven by the autopilot, and memory over the run."""
    env = SatLocEnv(scene=scene, resolution=resolution, depth=True)
    try:
        env.reset(seed=0)
        for _ in range(warmup):
            env.step(env.autopilot_action())
        rss_start = _rss_mb()
        episodes = 1
        t0 = time.perf_counter()
        for _ in range(steps):
            _, _, term, trunc, _ = env.step(env.autopilot_action())
            if term or trunc:
                env.reset(seed=episodes)
                episodes += 1
        dt = time.perf_counter() - t0
        rss_end = _rss_mb()
    finally:
        env.close()
    cam = env.camera
    return {
        "bench": "env", "resolution": resolution, "width": cam.width, "height": cam.height, "scene": scene,
        "steps": steps, "episodes": episodes, "steps_per_s": round(steps / dt, 1),
        "ms_per_step": round(1000 * dt / steps, 2), "rss_start_mb": round(rss_start, 1),
        "rss_end_mb": round(rss_end, 1), "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }
