"""An experiment folder as a Rerun recording (``satloc view FOLDER``): every method localized there, query by
query (:mod:`satloc_env.envs.viewer` for what is logged and how to open it)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from satloc.errors import ConfigError, FormatError
from satloc.persist import load_npz
from satloc_env.envs.viewer import METHOD_RGB, TRUTH_RGB, EpisodeRecording

__all__ = ["view_folder"]


def _folder_files(folder: Path) -> list[tuple[str, Path]]:
    """(method name, npz) of every localization in ``folder`` (the modes', the baselines', the cross-area rows',
    the reference floors' and a user's), named as the tables name them."""
    from .tables import method_name

    found = []
    for p in sorted(folder.glob("localization_*.npz")) + sorted(folder.glob("baseline_*.npz")) + sorted(
            (folder / "cross_area").glob("localization_*.npz")):
        key = p.stem.split("_", 1)[1]
        try:
            meta = load_npz(p, "localization")[1]
        except FormatError:
            continue
        try:
            name = meta.get("name") or method_name(key)
        except KeyError:
            name = key
        if p.parent.name == "cross_area" and any(n == name for n, _ in found):
            name += " (no database)"
        found.append((name, p))
    return found


def _folder_map(folder: Path):
    from satloc.satmap import SatelliteMap

    for d in (folder / "rec" / "map", folder / "map", folder.parent / "rec" / "map"):
        if (d / "map.json").is_file():
            return SatelliteMap.load(d)
    raise ConfigError(f"{folder}: no satellite map found (rec/map or map/): not an experiment folder of satloc "
                      "demo, satloc experiment or satloc evaluate")


def _folder_queries(folder: Path, frames: np.ndarray, truth: np.ndarray):
    """The query sequence of ``folder`` whose poses at ``frames`` are ``truth`` (a recording's query pass, or a
    protocol's second pass), else None."""
    from satloc.sequence import Sequence

    for d in (folder / "rec" / "query", folder / "second", folder.parent / "rec" / "query"):
        if not (d / "sequence.json").is_file():
            continue
        try:
            seq = Sequence.load(d)
        except (FormatError, ConfigError, OSError):
            continue
        if frames.max() < len(seq) and np.allclose(np.asarray(seq.poses)[frames], truth, equal_nan=True, atol=1e-6):
            return seq
    return None


def view_folder(folder: str | Path, out: str | Path, images: bool = True, progress: bool = False) -> dict:
    """Write ``out`` (an ``.rrd``): every method localized in the experiment ``folder`` (see the module docstring)
    on the timeline ``query``: per method its estimate trail and pose, its posterior's strongest entries, its
    error (``error_m/<method>``), the query's prior where the folder stored it; the true trail; with ``images``,
    the query frames' stereo pairs where the folder holds the recording. Returns what was written (methods,
    queries, whether images were found)."""
    folder = Path(folder)
    files = _folder_files(folder)
    if not files:
        raise ConfigError(f"{folder}: no localization_*.npz or baseline_*.npz: localize first (satloc demo, satloc "
                          "experiment, satloc evaluate), then view the folder")
    runs = []
    for name, p in files:
        a, _ = load_npz(p, "localization")
        runs.append((name, a))
    frames = np.asarray(runs[0][1]["frames"], np.int64)
    truth = np.asarray(runs[0][1]["truth"], np.float64)
    runs = [(n, a) for n, a in runs if np.array_equal(np.asarray(a["frames"], np.int64), frames)]
    sm = _folder_map(folder)
    seq = _folder_queries(folder, frames, truth) if images else None
    r = EpisodeRecording(out)
    r.log_map(sm)
    from tqdm.auto import tqdm

    for i in tqdm(range(len(frames)), desc="viewer", unit="query", disable=not progress, leave=False):
        r.at("query", i)
        if seq is not None:
            f = seq[int(frames[i])]
            r.log_views(f.left, f.right)
        r.log_trail("map/truth", truth[: i + 1, :2], TRUTH_RGB)
        r.log_pose("map/car", truth[i], TRUTH_RGB)
        for k, (name, a) in enumerate(runs):
            key = "methods/" + r.rr.escape_entity_path_part(name)
            rgb = METHOD_RGB[k % len(METHOD_RGB)]
            est = np.asarray(a["estimates"], np.float64)
            r.log_trail(f"{key}/trail", est[: i + 1, :2], rgb)
            r.log_pose(f"{key}/estimate", est[i], rgb)
            if "top_poses" in a and "top_probs" in a:
                r.log_posterior(f"{key}/posterior", a["top_poses"][i], a["top_probs"][i])
            if "prior" in a:
                pr = np.asarray(a["prior"], np.float64)[i]
                r.log_prior(f"{key}/prior", pr if pr[3] > 0 else None)
            r.log_scalar(f"error_m/{r.rr.escape_entity_path_part(name)}", float(np.asarray(a["errors"])[i]))
    r.close()
    return {"methods": [n for n, _ in runs], "queries": int(len(frames)), "images": seq is not None,
            "output": str(out)}
