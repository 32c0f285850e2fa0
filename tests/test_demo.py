"""`haactl demo` end to end on real processes: survivors agree after a host is killed half way."""

import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent / "haactl"


def test_demo_survivors_agree(tmp_path):
    r = subprocess.run(
        [str(BIN), "demo", "--hosts", "4", "--transactions", "200", "--data-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "identical on every survivor (3 survivors)" in r.stdout
    assert "killed half way" in r.stdout
    assert "propose → decide" in r.stdout and "OAC messages per transaction" in r.stdout
    assert (tmp_path / "h1" / "h1.jsonl").exists()
