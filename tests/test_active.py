"""satloc/ActiveLoc-v0 (satloc_env.envs.active), its maps (satloc_env.envs.active_map) and agents (satloc_env.agents)."""
import csv
import math

import gymnasium as gym
import networkx as nx
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import satloc_env
from satloc.errors import ConfigError, FormatError
from satloc_env.agents.evaluate import CSV_COLUMNS, evaluate_agents, run_episode
from satloc_env.agents.policies import EntropyAgent, LearnedAgent, RouteAgent, make_agent
from satloc_env.envs.active import ActiveLocEnv
from satloc_env.envs.active_map import SLOTS, ActiveMap, _leg_of_poses, both_ways_circuit


@pytest.fixture(scope="module")
def town():
    return ActiveMap.load("active_town")


def test_check_env_registered():
    env = gym.make(satloc_env.ACTIVE_ID)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("scene, streets", [("active_town", 17), ("active_grid", 60), ("active_suburb", 49)])
def test_shipped_maps_match_their_scenes(scene, streets):
    from satloc_env.envs.record import scene_identity
    from satloc_env.world.scene import load_scene

    m = ActiveMap.load(scene)
    assert m.meta["scene"] == scene and m.meta["scene_sha256"] == scene_identity(scene)[2]   # rebuilt after edits
    assert len(m.legs) == 2 * streets and len(np.unique(m.frame_leg)) == 2 * streets   # every street, each way
    route = load_scene(scene).routes["tour"]
    np.testing.assert_allclose(m.nodes[m.legs[:, 0]], route.points[:-1], atol=1e-3)   # legs in tour order
    assert all(len(f) >= 6 for f in m.leg_frames)                      # a frame every ~5 m of 50-70 m legs
    q = int(m.leg_frames[0][3])
    p = m.posterior(q)
    assert p.shape == (len(m.candidates),) and p.sum() == pytest.approx(1.0, abs=0.05)
    # frames and candidates lie on their legs: within the lane offsets of the leg's centre line
    a, b = m.nodes[m.legs[m.frame_leg, 0]], m.nodes[m.legs[m.frame_leg, 1]]
    ab = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    rel = m.frame_pose[:, :2] - a
    lateral = np.abs(ab[:, 0] * rel[:, 1] - ab[:, 1] * rel[:, 0])
    assert np.median(lateral) < 1.5


def _drive(env, seed, actions_rng, n=6):
    obs, info = env.reset(seed=seed)
    out = [(obs.copy(), dict(info))]
    for _ in range(n):
        a = int(actions_rng.choice(np.flatnonzero(info["action_mask"])))
        obs, r, term, trunc, info = env.step(a)
        out.append((obs.copy(), r, term, trunc, dict(info)))
        if term or trunc:
            break
    return out


def _same(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return a == b


def test_determinism_same_seed_same_actions():
    runs = [_drive(ActiveLocEnv(map="active_town"), 3, np.random.default_rng(0)) for _ in range(2)]
    assert _same(runs[0], runs[1])
    other = _drive(ActiveLocEnv(map="active_town"), 4, np.random.default_rng(0))
    assert not np.array_equal(runs[0][0][0], other[0][0])


def test_action_mask_and_invalid_action(town):
    env = ActiveLocEnv(map="active_town")
    obs, info = env.reset(seed=5)
    for _ in range(5):
        mask = info["action_mask"].astype(bool)
        assert mask.shape == (len(SLOTS),) and mask.sum() >= 2            # a decision: at least two branches
        np.testing.assert_array_equal(mask, env.action_masks())
        np.testing.assert_array_equal(mask, town.branches[env.leg] >= 0)
        assert town.reverse[env.leg] not in town.branches[env.leg]        # never the way back
        assert env.observation_space.contains(obs)
        # the observation's slot entries say which branches exist
        f = satloc_env.envs.active.OBS_FIELDS
        np.testing.assert_array_equal([obs[f.index(f"{s}_exists")] for s in SLOTS], mask.astype(np.float32))
        obs, _, term, trunc, info = env.step(int(np.flatnonzero(mask)[0]))
        if term or trunc:
            break
    # a masked-out action takes the first allowed branch and says so
    twin_a, twin_b = ActiveLocEnv(map="active_town"), ActiveLocEnv(map="active_town")
    seed = next(s for s in range(100) if (twin_a.reset(seed=s)[1]["action_mask"] == 0).any())   # a T-junction
    _, info = twin_a.reset(seed=seed)
    twin_b.reset(seed=seed)
    bad = int(np.flatnonzero(info["action_mask"] == 0)[0])
    first = int(np.flatnonzero(info["action_mask"])[0])
    oa, ra, *_, ia = twin_a.step(bad)
    ob, rb, *_, ib = twin_b.step(first)
    assert ia["invalid_action"] and not ib["invalid_action"]
    np.testing.assert_array_equal(oa, ob)
    assert ra == rb


def test_success_and_rewards():
    env = ActiveLocEnv(map="active_town")
    agent = RouteAgent()
    for seed in range(30):
        obs, info = env.reset(seed=seed)
        before = info["distance_m"]      # reset drives to the first junction
        while True:
            obs, r, term, trunc, info = env.step(agent.act(env, obs, info))
            d = info["distance_m"] - before
            before = info["distance_m"]
            if term or trunc:
                break
            assert r == pytest.approx(-d / 100.0)
        if info["success"]:
            assert term and not trunc and info["locked"] and info["error_m"] <= 10.0
            assert r == pytest.approx(-d / 100.0 + 5.0)
            with pytest.raises(RuntimeError, match="ended"):
                env.step(0)
            return
    pytest.fail("the route agent never localized in 30 episodes")


def test_wrong_lock_and_truncation():
    # success_m tiny: every lock is a wrong one
    env = ActiveLocEnv(map="active_town", success_m=1e-3, budget_m=5000.0)
    ep = run_episode(env, RouteAgent(), seed=1)
    assert ep["outcome"] == "wrong_lock" and ep["wrong_lock"] and not ep["success"]
    obs, info = env.reset(seed=1)
    while True:
        obs, r, term, trunc, info = env.step(RouteAgent().act(env, obs, info))
        if term or trunc:
            break
    assert term and not trunc and info["wrong_lock"] and r < -4.0
    # a small budget: truncated, no bonus or penalty
    env = ActiveLocEnv(map="active_town", budget_m=40.0)
    eps = [run_episode(env, RouteAgent(), seed=s) for s in range(6)]
    cut = [e for e in eps if e["truncated"]]
    assert cut and all(e["outcome"] == "budget" and not e["success"] and 40.0 <= e["distance_m"] < 47.0 for e in cut)


def test_config_errors():
    with pytest.raises(ConfigError, match="bogus"):
        ActiveLocEnv(map="active_town", bogus=1)
    with pytest.raises(ConfigError):
        ActiveLocEnv(map="active_town", fuse_every=0)
    with pytest.raises(ConfigError, match="no shipped map"):
        ActiveLocEnv(map="no_such_scene")
    env = ActiveLocEnv(map="active_town")
    env.reset(seed=0, options={"fuse_every": 2, "tracking": {"lock_mass": 0.95}})
    assert env.config.fuse_every == 2 and env.config.tracking.lock_mass == 0.95
    assert env.config.tracking.sigma_m == 1.0          # the other tracking settings are kept


def test_damaged_map(tmp_path, town):
    p = tmp_path / "m.npz"
    town.save(p)
    assert ActiveMap.load(p).legs.shape == town.legs.shape
    p.write_bytes(p.read_bytes()[:500])
    with pytest.raises(FormatError, match="m.npz"):
        ActiveMap.load(p)


@pytest.mark.parametrize("name", ["random", "route", "entropy", "learned"])
def test_agents_act_within_the_mask(name):
    agent = make_agent(name, seed=0)
    env = ActiveLocEnv(map="active_town")
    obs, info = env.reset(seed=11)
    for _ in range(3):
        a = agent.act(env, obs, info)
        assert info["action_mask"][a] == 1
        obs, _, term, trunc, info = env.step(a)
        assert not info["invalid_action"]
        if term or trunc:
            break


def test_entropy_agent_paths(town):
    env = ActiveLocEnv(map="active_town")
    env.reset(seed=3)
    agent = EntropyAgent()
    cand = int(np.argmax(env.tracker.belief))
    for slot in range(3):
        path = agent._path(env, cand, slot)
        nxt = town.branches[town.cand_leg[cand], slot]
        if nxt < 0:
            assert path is None
        else:   # the frames ahead on the candidate's leg, then the whole branch, in driving order
            assert path[-len(town.leg_frames[nxt]):] == [int(q) for q in town.leg_frames[nxt]]
            assert all(town.frame_leg[q] == town.cand_leg[cand] for q in path[:-len(town.leg_frames[nxt])])


def test_both_ways_circuit():
    g = nx.grid_2d_graph(4, 3)
    walk = both_ways_circuit(g)
    assert walk[0] == walk[-1]
    steps = list(zip(walk[:-1], walk[1:]))
    assert sorted(steps) == sorted([(u, v) for u, v in g.edges] + [(v, u) for u, v in g.edges])
    turns = list(zip(steps[:-1], steps[1:])) + [(steps[-1], steps[0])]
    assert not any(a == (b[1], b[0]) for a, b in turns)   # no U-turn


def test_map_needs_a_both_ways_tour(tmp_path):
    from satloc_env.envs.active_map import build_active_map

    with pytest.raises(ConfigError, match="once in each direction"):
        build_active_map({"scene": "city"}, tmp_path, progress=False)
    assert not any(tmp_path.iterdir())                    # refused before any work


def test_leg_of_poses():
    nodes = np.array([[0.0, 0.0], [60.0, 0.0]])
    legs = np.array([[0, 1], [1, 0]])
    poses = np.array([[10.0, -1.0, 0.0], [10.0, 1.0, math.pi], [59.0, 0.0, 0.1]])
    leg, rest = _leg_of_poses(poses, nodes, legs)
    np.testing.assert_array_equal(leg, [0, 1, 0])
    np.testing.assert_allclose(rest, [50.0, 10.0, 1.0])


def test_evaluate_writes_table(tmp_path):
    rows = evaluate_agents({"agents": ("random", "route"), "episodes": 3, "maps": ("active_town",)}, tmp_path,
                           progress=False, log=lambda *a: None)
    with open(tmp_path / "agents.csv") as f:
        got = list(csv.DictReader(f))
    assert list(got[0].keys()) == CSV_COLUMNS
    assert [r["agent"] for r in got] == ["random", "route"] == [r["agent"] for r in rows]
    for r in got:
        assert 0.0 <= float(r["success_rate"]) <= 100.0
        assert float(r["ci95_low"]) <= float(r["success_rate"]) <= float(r["ci95_high"])
    with open(tmp_path / "episodes.csv") as f:
        assert len(list(csv.DictReader(f))) == 6
    assert (tmp_path / "episode.png").stat().st_size > 10_000


def test_cli_agent_evaluate(tmp_path):
    from satloc_env.cli import main

    assert main(["agent", "evaluate", "--agents", "route,learned", "--episodes", "1", "--maps", "active_suburb",
                 "--out", str(tmp_path), "--quiet"]) == 0
    assert (tmp_path / "agents.csv").is_file()
    assert (tmp_path / "learning_curve.png").stat().st_size > 10_000   # the shipped policy's training curve
    assert main(["agent", "evaluate", "--agents", "psychic", "--episodes", "1", "--out", str(tmp_path)]) == 2


def test_train_tiny(tmp_path):
    pytest.importorskip("sb3_contrib")
    from satloc_env.agents.train import train_agent

    path = train_agent(tmp_path, timesteps=64, map="active_town", n_envs=2, n_steps=32, log=lambda *a: None)
    agent = LearnedAgent(path)
    env = ActiveLocEnv(map="active_town")
    obs, info = env.reset(seed=0)
    assert info["action_mask"][agent.act(env, obs, info)] == 1
    assert (tmp_path / "learning_curve.csv").is_file()
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a policy")
    with pytest.raises(FormatError, match="bad.pt"):
        LearnedAgent(bad)


def test_entropy_lookahead_moves_the_belief_from_the_place_to_the_path():
    """Driven from the true place, the agent's predicted belief ends where the path ends (it moves the belief
    from the place to the first frame before fusing it, as the environment moves it by the odometry)."""
    env = ActiveLocEnv(map="active_town")
    agent = EntropyAgent()
    m = env.map
    ends = []
    for seed in range(4):
        _, info = env.reset(seed=seed)
        on_leg = np.flatnonzero(m.cand_leg == env.leg)
        cand = int(on_leg[np.argmin(np.hypot(*(m.candidates[on_leg, :2] - env.pose[:2]).T))])   # the truth
        for slot in np.flatnonzero(info["action_mask"]):
            path = agent._path(env, cand, int(slot))
            b = agent._belief_after(env, cand, path)
            mode, end = m.candidates[int(np.argmax(b))], m.frame_pose[path[-1]]
            ends.append(math.hypot(mode[0] - end[0], mode[1] - end[1]))
    assert len(ends) >= 6 and np.median(ends) < 5.0 and max(ends) < 15.0, ends


def test_active_config_and_map_checks(tmp_path, town):
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="evidence"):
            ActiveLocEnv(map="active_town", evidence=bad)
    env = ActiveLocEnv(map="active_town")
    env.reset(seed=0)
    with pytest.raises(ConfigError, match="no shipped map"):
        env.reset(seed=0, options={"map": "no_such_scene", "fuse_every": 3})
    assert env.config.map == "active_town" and env.config.fuse_every == 1 and env.map.scene == "active_town"
    env.reset(seed=0)                                   # still the old map and settings
    from satloc_env.envs.active_map import ActiveMapConfig
    with pytest.raises(ConfigError, match="min_relative"):
        ActiveMapConfig(min_relative=1e-6)               # below what a stored row can hold
    arrays = {k: getattr(town, k) for k in ("nodes", "legs", "candidates", "cand_leg", "cand_rest", "frame_pose",
                                            "frame_leg", "frame_rest")}
    ptr, idx, val = town._ptr.copy(), town._idx.copy(), town._val.copy()
    tiny = val.copy()
    tiny[ptr[0] + 1] = val[ptr[0]:ptr[1]].max() * 1e-6  # 6 decades below the row's largest: cannot be stored
    m = ActiveMap(dict(arrays, post_ptr=ptr, post_idx=idx, post_val=tiny), town.meta)
    with pytest.raises(ValueError, match="0.0001"):
        m.save(tmp_path / "tiny.npz")
    assert not list(tmp_path.iterdir())                 # nothing written
    swapped = idx.copy()
    swapped[ptr[0]], swapped[ptr[0] + 1] = idx[ptr[0] + 1], idx[ptr[0]]
    with pytest.raises(FormatError, match="increasing"):
        ActiveMap(dict(arrays, post_ptr=ptr, post_idx=swapped, post_val=val), town.meta)
    with pytest.raises(ConfigError, match="at least one agent"):
        evaluate_agents(dict(agents=[], maps=["active_town"], episodes=1), out=tmp_path / "ev", progress=False)
