"""Agents for ``satloc/ActiveLoc-v0``: the policies, their evaluation and the learned one's training.

* :mod:`~satloc_env.agents.policies`: random, route, entropy (greedy expected entropy) and learned agents;
* :mod:`~satloc_env.agents.evaluate`: every agent from the same seeded starts, the table and pictures;
* :mod:`~satloc_env.agents.train`: MaskablePPO training of the learned agent (the ``rl`` extra).

It may import :mod:`satloc` and :mod:`satloc_env`'s world, render and envs layers; never the experiments
or the command line (an import-linter contract in ``pyproject.toml`` checks it). The names of the former
module ``satloc_env.agents`` are re-exported here.
"""
from .evaluate import CSV_COLUMNS, EvalConfig, evaluate_agents, plot_episode, run_episode
from .policies import AGENTS, POLICY_PATH, EntropyAgent, LearnedAgent, RandomAgent, RouteAgent, make_agent
from .train import train_agent

__all__ = ["RandomAgent", "RouteAgent", "EntropyAgent", "LearnedAgent", "make_agent", "AGENTS", "POLICY_PATH",
           "run_episode", "evaluate_agents", "train_agent", "plot_episode", "CSV_COLUMNS", "EvalConfig"]

from satloc._moved import forward_names as _forward_names  # noqa: E402

# the former module's other names (satloc_env.agents.<name>), with a FutureWarning naming their home
__getattr__ = _forward_names(__name__, ("satloc_env.agents.policies", "satloc_env.agents.evaluate", "satloc_env.agents.train"))
