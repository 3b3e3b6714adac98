"""The project speaks of itself: its code, versions and measurements dated by commit, never of rounds
of work, tracker numbers, "this" machine or material outside the repository."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# built from pieces so that this file does not match itself
WORDS = ["[Ss]essions? [0-9]", "[Ii]ssue #?[0-9]", "this " + "machine", r"\.\./" + "shared"]
PATTERN = re.compile("|".join(WORDS))
PLACES = ["README.md", "ARCHITECTURE.md", "CHANGELOG.md", "docs", "pdem", "tools", "tests", "inputs",
          "plugins", "examples", "studies"]
TEXT = {".md", ".py", ".toml", ".csv", ".txt", ".json", ".cfg", ".sh", ""}


def _files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", *PLACES], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split()
        files = [ROOT / f for f in out]
    except (OSError, subprocess.CalledProcessError):  # not a git checkout: every file below
        files = [p for place in PLACES for p in (ROOT / place).rglob("*") if p.is_file()]
    return [p for p in files if p.suffix in TEXT and p.is_file()]


def test_the_pattern_is_not_vacuous():
    for text in ("as measured in sess" + "ion 12", "see iss" + "ue #40", "on this " + "machine",
                 "../" + "shared/bench"):
        assert PATTERN.search(text), text


@pytest.mark.parametrize("place", PLACES)
def test_no_work_log_wording(place):
    hits = []
    for path in _files():
        rel = path.relative_to(ROOT)
        if not (str(rel) == place or str(rel).startswith(place + "/")):
            continue
        for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if PATTERN.search(line):
                hits.append(f"{rel}:{lineno}: {line.strip()[:120]}")
    assert not hits, "date figures by version or commit, not by work round:\n" + "\n".join(hits[:20])
