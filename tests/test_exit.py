"""A script that makes an environment and ends without closing it prints nothing at exit."""
import subprocess
import sys
import textwrap

import pytest

SINGLE = """
    env = gym.make("satloc/SatLoc-v0", scene="city", localizer=None)
    env.reset(seed=0)
    env.step(env.unwrapped.autopilot_action())
"""
VECTOR = """
    cars = gym.make_vec("satloc/SatLoc-v0", num_envs=2, localizer=None)
    cars.reset(seed=0)
    cars.step(cars.unwrapped.autopilot_actions())
"""


@pytest.mark.parametrize("body", [SINGLE, VECTOR], ids=["single", "vector"])
def test_an_environment_left_open_prints_nothing_at_exit(tmp_path, body):
    script = tmp_path / "left_open.py"
    script.write_text("import gymnasium as gym\nimport satloc_env\n" + textwrap.dedent(body) + "print('done')\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "done\n" and r.stderr == "", (r.stdout, r.stderr)
