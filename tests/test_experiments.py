"""Smoke tests: the benchmark scripts in experiments/ run end to end with tiny settings."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _run(args):
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=300, check=True)


def test_bench_rollout_step_prints_a_ratio():
    out = _run(["experiments/bench_rollout_step.py", "--batch", "1", "2", "--width", "16", "--order", "3",
                "--repeats", "2", "--threads", "1"]).stdout
    rows = [line for line in out.splitlines() if line.strip().startswith(("1 ", "2 "))]
    assert len(rows) == 2 and all("×" in r for r in rows)


def test_probe_settings_reports_json():
    out = _run(["experiments/probe_settings.py", "--seconds", "1", "--train", "2", "--test", "1", "--width", "16",
                "--threads", "1"]).stdout
    report = json.loads(out)
    assert report["steps"] >= 1 and 0 <= report["ring_share_of_sq_error"] <= 1
    assert len(report["eps_along_codes"]) == 7
