"""The measurement scripts under docs/tools that the documentation's figures come from: their pure parts."""
import importlib.util
from pathlib import Path

import pytest
import yaml

from satloc_env.world.capture import PARTS
from satloc_env.world.scene import load_spec

TOOLS = Path(__file__).resolve().parents[1] / "docs" / "tools"


def _tool(name):
    spec = importlib.util.spec_from_file_location(f"doc_tool_{name}", TOOLS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_env_first_steps_scene_without_lean(tmp_path):
    tool = _tool("env_first_steps")
    out = Path(tool.scene_without_lean("city", tmp_path))
    doc = yaml.safe_load(out.read_text())
    assert doc["name"] == "city_nolean" and out.parent == tmp_path
    assert doc["capture_parts"] == [p for p in PARTS if p != "lean"]
    spec, _ = load_spec(out)   # a valid scene: the city's own spec but for the capture's parts and the name
    city, _ = load_spec("city")
    assert spec.capture_parts == doc["capture_parts"] and spec.generator == city.generator
    assert spec.routes == city.routes and spec.seed == city.seed


def test_env_first_steps_refuses_scenes_without_lean(tmp_path):
    tool = _tool("env_first_steps")
    src = yaml.safe_load((Path(load_spec("city")[1]) / "city.yaml").read_text())
    src["capture_parts"] = [p for p in PARTS if p != "lean"]
    path = tmp_path / "flat.yaml"
    path.write_text(yaml.safe_dump(src))
    with pytest.raises(SystemExit, match="no lean"):
        tool.scene_without_lean(str(path), tmp_path / "out")
    image = tmp_path / "image.yaml"   # a scene over an image (its image need not exist to read the spec)
    image.write_text((Path(__file__).resolve().parents[1] / "scenes" / "real" / "vienna_schoenbrunn.yaml").read_text())
    with pytest.raises(SystemExit, match="not a grid scene"):
        tool.scene_without_lean(str(image), tmp_path / "out")
