"""Step ActiveLoc-v0 in a script: one episode per agent from the same start, printed decision by decision.

    python examples/active_agents.py --map active_suburb --seed 10000

At each junction the agent picks left, straight or right among the branches ``info["action_mask"]`` allows;
the tracked localizer fuses a frame every 5 m until its belief locks (or the distance budget runs out).
"""
import argparse
import sys

import gymnasium as gym

import satloc_env  # noqa: F401  (registers satloc/ActiveLoc-v0)
from satloc.errors import run_script
from satloc_env.agents.policies import AGENTS, make_agent
from satloc_env.envs.active_map import SLOTS


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", default="active_suburb")
    ap.add_argument("--seed", type=int, default=10000)
    ap.add_argument("--agents", nargs="+", default=list(AGENTS), choices=AGENTS)
    args = ap.parse_args(argv)
    env = gym.make("satloc/ActiveLoc-v0", map=args.map)
    for name in args.agents:
        agent = make_agent(name, seed=args.seed)
        obs, info = env.reset(seed=args.seed)
        line = [f"{name:8s} start: H {info['entropy']:.1f}"]
        while True:
            a = agent.act(env.unwrapped, obs, info)
            obs, _, term, trunc, info = env.step(a)
            line.append(f"{SLOTS[a]} -> {info['distance_m']:.0f} m, H {info['entropy']:.1f}")
            if term or trunc:
                break
        end = "localized" if info["success"] else ("WRONG LOCK" if info["wrong_lock"] else "budget spent")
        print("; ".join(line) + f"; {end}, error {info['error_m']:.1f} m after {info['distance_m']:.0f} m")
    env.close()


if __name__ == "__main__":
    sys.exit(run_script(main))
