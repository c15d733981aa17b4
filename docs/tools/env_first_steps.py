"""The no-database localizer's error over an environment's first steps, seed by seed.

    python docs/tools/env_first_steps.py [--scene city] [--seeds 6] [--steps 40] [--single] [--no-lean]
                                         [--hidden [CLASS ...]]

Drives ``satloc/SatLoc-v0`` with the autopilot for ``--steps`` steps from each of ``--seeds`` resets (seeds 0,
1, ...), localizing every step with the default ``localizer="cross"``, tracked (``localizer_track=True``) unless
``--single``, and prints each seed's errors in metres, then the mean, the median, the share within 1 m and the
largest error over all steps. ``--no-lean`` drives the same scene with its satellite map captured without the
capture's ``lean`` part (the sensor off nadir: roofs and canopies displaced from their footprints; see
``satloc_env.world.capture``), written as a scene YAML beside a temporary copy, every other part as the scene has
it. ``--hidden CLASS ...``: the localizer's ``CrossViewConfig.hidden_classes`` (the map's classes left out of the
comparison; by default none; ``--hidden`` alone: none, explicitly). What it measured is in docs/results.md
(the track's belief).
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import yaml


def scene_without_lean(scene: str, where: Path) -> str:
    """A YAML path of ``scene`` (a shipped name or a YAML file) whose capture leaves out ``lean``."""
    from satloc_env.world.capture import PARTS
    from satloc_env.world.scene import load_spec, scene_path

    spec, _ = load_spec(scene)
    if spec.generator.get("type") != "grid":
        raise SystemExit(f"{scene}: not a grid scene (a scene over an image has no lean, and its files are relative "
                         "to its YAML); give a grid scene")
    doc = yaml.safe_load(scene_path(scene).read_text())
    parts = list(PARTS if spec.capture_parts is None else spec.capture_parts)
    if "lean" not in parts:
        raise SystemExit(f"{scene}: its capture has no lean to leave out (parts {parts})")
    doc["capture_parts"] = [p for p in parts if p != "lean"]
    doc["name"] = f"{doc['name']}_nolean"
    out = where / f"{doc['name']}.yaml"
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return str(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="city")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--single", action="store_true", help="single frames, no tracking")
    ap.add_argument("--no-lean", action="store_true", help="the map captured without the sensor's lean")
    ap.add_argument("--hidden", nargs="*", default=None, metavar="CLASS",
                    help="CrossViewConfig.hidden_classes (default: none)")
    ap.add_argument("--json", default=None, help="write {seed: [errors]} here")
    a = ap.parse_args(argv)
    if a.hidden is not None:   # the environment's cross-view localizer made with these classes hidden
        import functools

        from satloc.localizers.crossview import CrossViewConfig
        from satloc_env.envs import cross_localizer as cl

        cl.cross_localizer = functools.partial(cl.cross_localizer, config=CrossViewConfig(hidden_classes=tuple(a.hidden)))

    import gymnasium as gym

    import satloc_env  # noqa: F401  (registers the environments)

    with tempfile.TemporaryDirectory() as tmp:
        scene = scene_without_lean(a.scene, Path(tmp)) if a.no_lean else a.scene
        env = gym.make("satloc/SatLoc-v0", scene=scene, localizer_track=not a.single)
        out = {}
        for seed in range(a.seeds):
            env.reset(seed=seed)
            errors = []
            for _ in range(a.steps):
                _, _, terminated, truncated, info = env.step(env.unwrapped.autopilot_action())
                errors.append(float(info.get("error_m", np.nan)))
                if terminated or truncated:
                    break
            out[seed] = errors
            print(seed, np.round(errors, 1).tolist(), flush=True)
        env.close()
    e = np.concatenate([np.asarray(v) for v in out.values()])
    hidden = "" if a.hidden is None else f", hidden {a.hidden or 'none'}"
    print(f"{'single' if a.single else 'tracked'}{', no lean' if a.no_lean else ''}{hidden}: {len(e)} steps, mean "
          f"{np.nanmean(e):.2f} m, median {np.nanmedian(e):.2f} m, within 1 m {np.mean(e <= 1.0):.0%}, "
          f"largest {np.nanmax(e):.1f} m")
    if a.json:
        Path(a.json).write_text(json.dumps(out))


if __name__ == "__main__":
    main()
