"""What the optional capture parts (issue 46) do to the no-database localizer, on a calibration recording.

    satloc experiment tune --out tune             # records the calibration pass on calib/town_a (before 2026-12-07: fcn_train/town_a, the plain world)
    python docs/tools/capture_calibration.py tune/rec 8 3 capture_cal.json [variant ...] [--tracked]

The recording's own map is the default capture; each variant captures the recording's scene again with the
default parts plus those it names (``deep_shadows``, ``traffic``, ``coarse_texture``; ``+`` joins several; ``default``
for none; ``default-texture`` leaves a default part out; ``copy`` for no capture at all: the ground the camera renders, over an image the image itself), and ``@semantic`` or ``@none`` after it localizes on the map as a bare GeoTIFF gives it (no labels:
the drivable area from the features' own semantics, or none), not with the map's labels as by default; and
``#grey`` at the end localizes with the fixed grey-level channel instead of the shipped learned ones
(``#path/to/crossview.pt``: with those learned channels); ``%key=value,...`` at the very end sets fields of
the localizer's ``CrossViewConfig`` (YAML values: ``default%coast=false``, ``default%hidden_classes=[building,tree]``). The
camera's frames, their priors (uniform within 20 m and 10 degrees, seeded by the seed and the frame's index)
and the odometry unchanged. Takes every STEP-th frame of the query pass, localizes single frames and tracked
with the shipped features and the default settings, with SEEDS seeds of the priors, and prints and writes per
variant: the mean and median error, the shares within 1 m and beyond 10 m, and the lateral and longitudinal
shares within 1 m; with several variants, each variant's mean minus the first's (the same frames, each frame's
error the mean over its seeds) with a 95 % paired stationary block bootstrap interval over the frames.
``--tracked`` runs the tracked localizations alone (no single frames).
"""
import json
import re
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from satloc import Sequence
from satloc.features import make_extractor
from satloc.features.dictionary import SatelliteFeatures
from satloc.evaluation.metrics import paired_bootstrap_ci
from satloc.localizers.crossview import CrossViewConfig, CrossViewLocalizer, draw_prior, localize_frames
from satloc.satmap import SatelliteMap
from satloc.tracking.track import compose_between

DEFAULT_VARIANTS = ["default", "deep_shadows", "traffic", "coarse_texture", "deep_shadows+traffic+coarse_texture"]


def variant_map(rec: Path, sm: SatelliteMap, variant: str) -> SatelliteMap:
    if variant == "default":
        return sm
    from satloc_env.world.capture import PARTS, capture_tile
    from satloc_env.world.scene import load_scene

    cfg = json.loads((rec / "recording.json").read_text())["config"]
    sc = load_scene(cfg["scene"])
    if not np.array_equal(sc.satmap.image, sm.image):
        raise SystemExit(f"{rec}: its map is not the default capture of {cfg['scene']} as this code builds it")
    spec = sc.spec
    if variant == "copy":    # no capture: the ground the camera renders (a scene over an image: the image itself)
        lay = sc.layout
        if spec.generator.get("type") == "image":
            return SatelliteMap(lay.ground_rgb, sm.meters_per_pixel, sm.origin, lay.ground_labels, sm.frame)
        img, lab = capture_tile(lay, spec.meters_per_pixel, spec.seed, 0.0)
        return SatelliteMap(img, sm.meters_per_pixel, sm.origin, lab, sm.frame)
    parts = list(PARTS)
    for tok in variant.replace("-", " -").replace("+", " +").split():
        if tok.startswith("-"):
            parts.remove(tok[1:])
        elif tok.strip("+") != "default":
            parts.append(tok.strip("+"))
    if spec.generator.get("type") == "image":
        from satloc_env.world.capture import capture_image

        img, lab = capture_image(sc.layout, spec.meters_per_pixel, spec.seed, spec.knobs.satellite_gap, parts)
    else:
        img, lab = capture_tile(sc.layout, spec.meters_per_pixel, spec.seed, spec.knobs.satellite_gap, parts)
    return SatelliteMap(img, sm.meters_per_pixel, sm.origin, lab, sm.frame)


def errors(est: np.ndarray, truth: np.ndarray) -> dict:
    d = est[:, :2] - truth[:, :2]
    e = np.hypot(d[:, 0], d[:, 1])
    c, s = np.cos(truth[:, 2]), np.sin(truth[:, 2])
    lon, lat = np.abs(d[:, 0] * c + d[:, 1] * s), np.abs(-d[:, 0] * s + d[:, 1] * c)
    ok = np.isfinite(e)
    return dict(n=int(e.size), answered=float(ok.mean()), mean=float(e[ok].mean()),
                median=float(np.median(np.where(ok, e, np.inf))), within1=float(np.mean(e < 1)),
                beyond10=float(np.mean(np.where(ok, e, np.inf) > 10)), lateral1=float(np.mean(lat < 1)),
                longitudinal1=float(np.mean(lon < 1)))


def main(rec: Path, step: int, n_seeds: int, dest: Path, variants: list[str], modes=(False, True)) -> None:
    seq, sm0 = Sequence.load(rec / "query"), SatelliteMap.load(rec / "map")
    ext = make_extractor("default")
    idx = np.arange(0, len(seq), step)
    truth = np.asarray(seq.poses, np.float64)[idx]
    steps = np.load(rec.parent / "odometry_visual.npz", allow_pickle=False)["steps"]
    odo = compose_between(steps, idx)
    out = []
    for variant in variants:
        t0 = time.time()
        variant_, _, fields = variant.partition("%")
        head, _, grey = variant_.partition("#")
        parts, _, drivable = head.partition("@")
        sm = variant_map(rec, sm0, parts)
        sf = SatelliteFeatures.compute(sm, ext)
        kw = {} if not grey else {"projections": None} if grey == "grey" else {"projections": grey}
        for item in filter(None, re.split(r",(?![^\[]*\])", fields)):   # commas inside [...] belong to a list
            key, _, value = item.partition("=")
            kw[key.strip()] = yaml.safe_load(value)
        if drivable:
            cv = CrossViewLocalizer(seq.camera, sf, ext, CrossViewConfig(drivable=drivable, **kw))
        else:
            cv = CrossViewLocalizer(seq.camera, sf, ext, CrossViewConfig(**kw), labels=sm.labels)
        for track in modes:
            ests, truths = [], []
            for seed in range(n_seeds):
                priors = [draw_prior(t, 20.0, 10.0, np.random.default_rng([seed, int(i)])) for t, i in zip(truth, idx)]
                r = localize_frames(cv, (seq[int(i)] for i in idx), priors, odo if track else None,
                                    **({"follow": (5.0, 4.0)} if track else {}))
                ests.append(np.asarray(r["estimates"], np.float64))
                truths.append(truth)
            err = np.hypot(*(np.stack(ests)[..., :2] - truth[:, :2]).transpose(2, 0, 1))   # (seeds, frames); NaN: no answer
            per_frame = err.mean(axis=0)   # NaN where a seed has no answer
            row = dict(variant=variant, track=track, seeds=n_seeds,
                       **errors(np.concatenate(ests), np.concatenate(truths)),
                       per_seed_mean=[float(x) for x in np.nanmean(err, axis=1)],
                       seconds=round(time.time() - t0, 1),
                       per_frame=[float(x) if np.isfinite(x) else None for x in per_frame])
            first = next((o for o in out if o["track"] == track), None)
            if first is not None:   # this variant against the first, frame by frame
                a, b = per_frame, np.array(first["per_frame"], np.float64)   # None -> NaN
                ok = np.isfinite(a) & np.isfinite(b)
                lo, hi = paired_bootstrap_ci(a[ok], b[ok])
                row["minus_first"] = dict(frames=int(ok.sum()), mean=float(a[ok].mean() - b[ok].mean()), ci95=[lo, hi])
            out.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "per_frame"}), flush=True)
        dest.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    args = [a for a in sys.argv[5:] if a != "--tracked"]
    main(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4]), args or DEFAULT_VARIANTS,
         (True,) if "--tracked" in sys.argv[5:] else (False, True))
