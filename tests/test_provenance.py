"""docs/provenance.md records every shipped binary file (issue 37): each row's size and SHA-256 match the
file, and every binary file git tracks has a row, so a file changed or added without its record fails."""
from __future__ import annotations

import hashlib
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: what counts as a binary or generated file to record
BINARY = (".pt", ".npz", ".tif", ".png", ".jpg", ".jpeg", ".gif", ".osm", ".geojson", ".csv")
ROW = re.compile(r"^\| `([^`]+)` \| (\d+) \| `([0-9a-f]{64})` \| (\w*) \| (.+) \|$")


def _records() -> dict[str, tuple[int, str]]:
    rows = {}
    for line in (ROOT / "docs" / "provenance.md").read_text().splitlines():
        m = ROW.match(line)
        if m:
            rows[m.group(1)] = (int(m.group(2)), m.group(3))
    return rows


def test_every_record_matches_its_file():
    rows = _records()
    assert len(rows) >= 30
    bad = []
    for path, (size, sha) in rows.items():
        data = (ROOT / path).read_bytes()
        if len(data) != size or hashlib.sha256(data).hexdigest() != sha:
            bad.append(path)
    assert not bad, f"changed without their provenance record (docs/provenance.md): {bad}"


def test_every_shipped_binary_has_a_record():
    try:
        files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    tracked = [f for f in files.splitlines() if f.lower().endswith(BINARY) and not f.startswith("tests/")]
    missing = sorted(set(tracked) - set(_records()))
    assert not missing, f"binary files with no row in docs/provenance.md: {missing}"
