"""Modules that moved (CHANGELOG.md): the old names import the same module objects, with one FutureWarning at
the line that used them; ``python -m`` with an old name says where the module went."""
import subprocess
import sys
import textwrap

USER = textwrap.dedent("""
    import warnings
    warnings.simplefilter("default")
    import satloc_env
    import satloc_env.env as env_old                          # line 5
    from satloc.georef import load_map                        # line 6
    tables_old = satloc_env.compare                           # line 7
    from satloc_env.world import pad_texture                  # line 8
    import satloc_env.env                                     # line 9: warned once already
    import satloc_env.envs.drive, satloc_env.experiments.tables, satloc_env.world.meshes, satloc.geodata.georef
    assert env_old is satloc_env.envs.drive and env_old.SatLocEnv is satloc_env.SatLocEnv
    assert tables_old is satloc_env.experiments.tables
    assert load_map is satloc.geodata.georef.load_map and pad_texture is satloc_env.world.meshes.pad_texture
    assert env_old.__spec__.name == "satloc_env.envs.drive" and tables_old.__name__ == "satloc_env.experiments.tables"
    from satloc_env.render import StereoRenderer
    from satloc_env.agents import evaluate_agents, train_agent
    import satloc_env.render.stereo, satloc_env.agents.evaluate
    assert StereoRenderer is satloc_env.render.stereo.StereoRenderer
    assert evaluate_agents is satloc_env.agents.evaluate.evaluate_agents
    print("ok")
""")


def test_old_names_are_the_new_modules_with_one_warning_each(tmp_path):
    script = tmp_path / "user.py"
    script.write_text(USER)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "ok\n"
    warned = [ln for ln in r.stderr.splitlines() if "FutureWarning" in ln]
    assert [w.split(": FutureWarning: ")[0].rsplit(":", 1)[1] for w in warned] == ["5", "6", "7", "8"], r.stderr
    assert "satloc_env.env moved to satloc_env.envs.drive" in warned[0]
    assert "satloc.georef moved to satloc.geodata.georef" in warned[1]
    assert "satloc_env.compare moved to satloc_env.experiments.tables" in warned[2]
    assert "satloc_env.world.pad_texture moved to satloc_env.world.meshes.pad_texture" in warned[3]


def test_python_m_with_an_old_name_says_where_it_went():
    r = subprocess.run([sys.executable, "-m", "satloc_env.determinism", "--help"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode != 0
    assert "satloc_env.determinism moved to satloc_env.experiments.determinism: run python -m " \
           "satloc_env.experiments.determinism" in r.stderr
    assert "Traceback" not in r.stderr


METHOD_USER = textwrap.dedent("""
    import warnings
    warnings.simplefilter("default")
    import satloc
    from satloc.localizer import Localizer, LocalizerConfig     # line 5
    from satloc.crossview import CrossViewLocalizer            # line 6
    import satloc.track as track                               # line 7
    metrics = satloc.metrics                                   # line 8
    from satloc.features import make_extractor                 # the package keeps the old module's names
    from satloc.crossview import localize_sequence              # line 10: a module warned already ...
    import satloc.localizers.database, satloc.localizers.crossview, satloc.tracking.track, satloc.evaluation.metrics
    import satloc.features.pixelwise, satloc.pipeline
    assert Localizer is satloc.localizers.database.Localizer
    assert CrossViewLocalizer is satloc.localizers.crossview.CrossViewLocalizer
    assert track is satloc.tracking.track and metrics is satloc.evaluation.metrics
    assert make_extractor is satloc.features.pixelwise.make_extractor
    assert localize_sequence is satloc.pipeline.localize_no_database
    print("ok")
""")


def test_the_method_arranged_by_trade_keeps_its_old_names(tmp_path):
    script = tmp_path / "user.py"
    script.write_text(METHOD_USER)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "ok\n"
    warned = [ln for ln in r.stderr.splitlines() if "FutureWarning" in ln]
    assert [w.split(": FutureWarning: ")[0].rsplit(":", 1)[1] for w in warned] == ["5", "6", "7", "8", "10"], r.stderr
    assert "satloc.localizer moved to satloc.localizers.database" in warned[0]
    assert "satloc.metrics moved to satloc.evaluation.metrics" in warned[3]
    assert "localize_sequence moved to satloc.pipeline.localize_no_database" in warned[4]
