"""Lint as a test, as ROS packages run ament_flake8 / ament_pep257: ``ruff check`` over the
checkout with the rules of ``ruff.toml`` (pyflakes, pycodestyle, import order, bugbear,
pyupgrade, pep257 docstrings on the package's public API)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RUFF = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")
pytestmark = pytest.mark.skipif(RUFF is None, reason="ruff is not installed (pip install -e '.[test]' installs it)")


def _ruff(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([RUFF, "check", "--no-cache", *args], cwd=cwd, capture_output=True, text=True, timeout=120)


def test_the_checkout_is_lint_clean():
    res = _ruff(".")
    assert res.returncode == 0, res.stdout + res.stderr


def test_the_lint_catches_what_it_should(tmp_path):
    """The configuration is live: an unused import and an undocumented public function fail."""
    pkg = tmp_path / "bev_mapper_core"
    pkg.mkdir()
    (pkg / "bad.py").write_text("import os\n\n\ndef public(x):\n    return x\n")
    res = _ruff("--config", str(REPO / "ruff.toml"), str(pkg / "bad.py"), cwd=tmp_path)
    assert res.returncode == 1
    assert "F401" in res.stdout and "D103" in res.stdout, res.stdout
