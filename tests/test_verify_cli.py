"""`haactl verify` output contract: violations with seeds, and the exact last line."""

import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent / "haactl"


def run(*args):
    return subprocess.run([str(BIN), "verify", *args], capture_output=True, text=True, timeout=600)


def test_clean_run_last_line_and_exit_code():
    r = run("oac", "--schedules", "40", "--seed", "0", "--hosts", "5")
    lines = r.stdout.strip().splitlines()
    assert lines[-1] == "verify oac: 40 schedules, 0 violations", r.stdout + r.stderr
    assert r.returncode == 0
    assert "schedules/minute" in r.stdout


def test_broken_algorithm_is_reported_with_seed_and_exit_1():
    r = run("oac", "--schedules", "30", "--seed", "0", "--hosts", "7", "--mutate", "skip-order-gate")
    lines = r.stdout.strip().splitlines()
    assert r.returncode == 1
    assert lines[-1].startswith("verify oac: 30 schedules, ") and not lines[-1].endswith(" 0 violations")
    assert any(ln.startswith("VIOLATION seed=") and "AC-Total-Order" in ln for ln in lines)
    assert any("reproduce: haactl verify oac --seed" in ln for ln in lines)


def test_resume_from_checkpoint(tmp_path):
    ck = tmp_path / "ck.json"
    r = run("ufd", "--schedules", "6", "--seed", "10", "--hosts", "4", "--checkpoint", str(ck))
    assert r.returncode == 0 and ck.exists()
    r2 = run("ufd", "--schedules", "10", "--seed", "10", "--hosts", "4", "--checkpoint", str(ck), "--resume")
    assert "resuming at seed 16, 4 schedules left" in r2.stderr
    assert r2.stdout.strip().splitlines()[-1] == "verify ufd: 4 schedules, 0 violations"


def test_bad_arguments_are_clear_errors():
    r = run("paxos", "--schedules", "1")
    assert r.returncode == 2 and "unknown algorithm" in r.stderr
    r = run("oac", "--schedules", "1", "--mutate", "bogus")
    assert r.returncode == 2 and "unknown mutation" in r.stderr


def test_group_verifiers_clean_runs_keep_the_contract():
    for alg in ("membership", "ddb"):
        r = run(alg, "--schedules", "10", "--seed", "0", "--hosts", "5", "--workers", "2")
        lines = r.stdout.strip().splitlines()
        assert lines[-1] == f"verify {alg}: 10 schedules, 0 violations", r.stdout + r.stderr
        assert r.returncode == 0
        assert "schedules/minute on 2 worker(s)" in r.stdout and "liveness checked in 10/10" in r.stdout


def test_broken_ddb_is_reported_with_seed_excerpt_and_a_reproduce_command_that_breaks_it_again():
    r = run("ddb", "--schedules", "4", "--seed", "0", "--mutate", "stale-snapshot", "--excerpts", "1")
    lines = r.stdout.strip().splitlines()
    assert r.returncode == 1
    assert lines[-1].startswith("verify ddb: 4 schedules, ") and not lines[-1].endswith(" 0 violations")
    assert any(ln.startswith("VIOLATION seed=") and "DDB-Joiner-Consistency" in ln for ln in lines)
    assert any(ln.startswith("  scenario: seed=") for ln in lines)  # the trace excerpt
    assert any("reproduce: haactl verify ddb --seed" in ln and "--mutate stale-snapshot --trace" in ln for ln in lines)


def test_group_trace_and_resume(tmp_path):
    r = run("membership", "--schedules", "1", "--seed", "3", "--hosts", "4", "--trace")
    assert r.returncode == 0 and r.stdout.startswith("# seed=3 ")
    assert " view 1 at " in r.stdout and "# trace hash " in r.stdout
    ck = tmp_path / "ck.json"
    r = run("membership", "--schedules", "3", "--seed", "0", "--hosts", "4", "--checkpoint", str(ck))
    assert r.returncode == 0 and ck.exists()
    r2 = run("membership", "--schedules", "5", "--seed", "0", "--hosts", "4", "--checkpoint", str(ck), "--resume")
    assert "resuming at seed 3, 2 schedules left" in r2.stderr
    assert r2.stdout.strip().splitlines()[-1] == "verify membership: 2 schedules, 0 violations"
