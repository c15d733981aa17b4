"""Train the learned active-localization agent (MaskablePPO over ActiveLoc-v0's observation) and compare it.

    pip install -e '.[rl]'
    python examples/train_agent.py --timesteps 20000 --out agent_out

Trains on the ``active_grid`` map (its own seeded starts), writes ``agent_out/active_policy.pt``, the learning
curve (``learning_curve.csv``/``.png``), then evaluates it beside the entropy baseline on held-out starts of the
held-out ``active_suburb`` map (``agent_out/eval/agents.csv``). The shipped policy
(``satloc_env/weights/active_policy.pt``) was made by this script with its defaults.
"""
import argparse
import sys
from pathlib import Path

from satloc.errors import run_script
from satloc_env.agents.evaluate import evaluate_agents
from satloc_env.agents.train import train_agent


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--timesteps", type=int, default=20000, help="decisions to train for")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--map", default="active_grid", help="the active map to train on")
    ap.add_argument("--episodes", type=int, default=50, help="evaluation episodes per agent (0: no evaluation)")
    ap.add_argument("--out", default="agent_out")
    args = ap.parse_args(argv)
    out = Path(args.out)
    policy = train_agent(out, args.timesteps, args.seed, args.map)
    if args.episodes > 0:
        evaluate_agents({"agents": ("entropy", "learned"), "episodes": args.episodes, "maps": ("active_suburb",),
                         "policy": str(policy)}, out / "eval")


if __name__ == "__main__":
    sys.exit(run_script(main))
