"""The package layering (pyproject.toml's import-linter contracts): the tree keeps it, and an upward import
breaks it with a message naming both modules."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
        "sys.exit(lint_imports_command())"]


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    # the tree under test first; a PYTHONPATH already set (import-linter installed with --target, say) after it
    paths = [str(cwd)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env = {"PYTHONPATH": os.pathsep.join(paths), "PATH": "/usr/bin:/bin"}
    return subprocess.run(LINT, cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def test_the_tree_keeps_the_layers():
    r = _lint(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "3 kept, 0 broken" in r.stdout


def _copy_tree(dst: Path) -> None:
    for pkg in ("satloc", "satloc_env"):
        shutil.copytree(ROOT / pkg, dst / pkg, ignore=shutil.ignore_patterns("*.pt", "*.csv", "*.json", "__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", dst / "pyproject.toml")


@pytest.mark.parametrize("importer, imported", [
    ("satloc_env/world/paint.py", "satloc_env.experiments.tables"),   # world reaching the experiments
    ("satloc_env/render/stereo.py", "satloc_env.envs.drive"),          # render reaching an environment
    ("satloc_env/envs/vehicle.py", "satloc_env.agents.policies"),      # an environment reaching the agents
    ("satloc/tracking/track.py", "satloc_env.world.route"),           # the method reaching the simulator
    ("satloc/tracking/vo.py", "satloc.localizers.database"),          # tracking reaching a localizer
    ("satloc/features/dictionary.py", "satloc.evaluation.metrics"),   # features reaching the evaluation
    ("satloc/geometry.py", "satloc.features.pixelwise"),              # the data model reaching the features
])
def test_an_upward_import_breaks_the_contract(tmp_path, importer, imported):
    _copy_tree(tmp_path)
    f = tmp_path / importer
    f.write_text(f.read_text() + f"\n\ndef _upward():\n    import {imported}  # noqa: F401\n")
    r = _lint(tmp_path)
    assert r.returncode != 0
    assert "BROKEN" in r.stdout
    src = importer[:-3].replace("/", ".")
    assert f"{src} -> {imported}" in r.stdout, r.stdout
