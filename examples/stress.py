"""Stress-test the localizer over perceptual aliasing and occlusion on a synthetic scene.

For every aliasing level (the share of city blocks that are exact copies of others) a database pass is
recorded and built; for every occlusion level a query pass (other lane, other appearance, that share of
parked vehicles and pedestrians) is localized against it. Prints a table, writes ``stress.csv`` and
``stress.png`` (mean error against aliasing, one line per occlusion level and mode). Beside the modes: the
reference floors (the prior alone, dead reckoning) and, with ``--localizer``, localizers of your own, each
graded as the modes are (``module:Name`` or ``path/to/file.py:Name``, see examples/own_localizer.py).

    python examples/stress.py --scene city --aliasing 0 0.5 1 --occlusion 0 0.3 0.6 --db-frames 150 --out stress_out
    python examples/stress.py --localizer examples/own_localizer.py:GpsOdometryFilter --out stress_out
"""
import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from satloc.errors import run_script
from satloc_env.experiments.scene_run import METHOD_NAMES, ExperimentConfig, run_scene


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="city")
    ap.add_argument("--aliasing", type=float, nargs="+", default=[0.0, 0.5, 1.0])
    ap.add_argument("--occlusion", type=float, nargs="+", default=[0.0, 0.3, 0.6])
    ap.add_argument("--db-frames", type=int, default=150, help="database frames (about 1.6 m apart)")
    ap.add_argument("--query-frames", type=int, default=None, help="query frames (10 m apart; default: all "
                    "that lie on the database section)")
    ap.add_argument("--modes", nargs="+", default=["go", "np"], choices=sorted(METHOD_NAMES), metavar="MODE",
                    help="e.g. go np full full+align go+track full+track+align (+track: the query pass as one "
                    "sequence with simulated odometry)")
    ap.add_argument("--features", default="default")
    ap.add_argument("--localizer", action="append", default=[], metavar="MODULE:NAME",
                    help="a localizer of your own beside the modes (module:Name or path/to/file.py:Name); repeat "
                    "for several")
    ap.add_argument("--no-references", action="store_true", help="leave out the reference floors (prior alone, "
                    "dead reckoning)")
    ap.add_argument("--out", default="stress_out")
    args = ap.parse_args(argv)

    out = Path(args.out)
    rows = []
    for a in args.aliasing:
        for o in args.occlusion:
            cfg = ExperimentConfig(scene=args.scene, aliasing=a, occlusion=o, database_frames=args.db_frames,
                                   query_frames=args.query_frames, features=args.features, modes=tuple(args.modes),
                                   localizers=tuple(args.localizer),
                                   references=() if args.no_references else ExperimentConfig().references)
            # one folder per setting; settings that share a database reuse nothing here, kept simple
            summary = run_scene(cfg, out / f"a{a:g}_o{o:g}", progress=False, log=lambda m: None)
            others = [(m.get("name", k), m) for k, m in summary.get("localizers", {}).items()]
            for mode, m in list(summary["modes"].items()) + others:
                rows.append(dict(aliasing=a, occlusion=o, mode=mode, mean_m=round(m["mean_m"], 3),
                                 median_m=round(m["median_m"], 3), within_1m=round(m["within_1m"], 3),
                                 queries=m["queries"]))
                print(f"aliasing {a:4.2f}  occlusion {o:4.2f}  {mode:16s}  mean {m['mean_m']:7.2f} m  "
                      f"median {m['median_m']:6.2f} m  within 1 m {100 * m['within_1m']:3.0f} %  "
                      f"({m['queries']} queries)", flush=True)
    with open(out / "stress.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(rows, out / "stress.png")
    print(f"wrote {out / 'stress.csv'} and {out / 'stress.png'}")
    return rows


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=110)
    for mode in sorted({r["mode"] for r in rows}):
        for o in sorted({r["occlusion"] for r in rows}):
            pts = sorted((r["aliasing"], r["mean_m"]) for r in rows if r["mode"] == mode and r["occlusion"] == o)
            x, y = np.array(pts).T
            ax.plot(x, y, marker="o", label=f"{mode}, occlusion {o:g}")
    ax.set_xlabel("aliasing (share of copied blocks)")
    ax.set_ylabel("mean error (m)")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(run_script(main))
