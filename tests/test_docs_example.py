"""The pytest example of docs/guide/python.md (docs/examples/test_my_axis.py) runs as a user's CI would run it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parent.parent / "docs" / "examples" / "test_my_axis.py"


def test_the_docs_pytest_example_passes(tmp_path):
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=", str(EXAMPLE),
           "--rootdir", str(tmp_path)]
    env = {k: v for k, v in os.environ.items() if k != "DRIVECTL_CONFIG"}
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=300, env=env)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "3 passed" in out.stdout
