"""What every bench script writes: the machine a result was measured on, and the JSON report."""

from __future__ import annotations

import json
import os
import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def machine() -> dict:
    """The CPU, its core count, Python's version, the date and the commit, for a report's ``machine``."""
    import datetime

    from bench.render import cpu_model

    # BENCH_COMMIT names the commit where the tree was copied without its own history (a GPU
    # machine's copy), whose git folder, if any, need not be at that commit.
    commit = os.environ.get("BENCH_COMMIT")
    if not commit:
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            commit = None
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "commit": commit,
    }


def write_report(report: dict, out: Path | None) -> dict:
    """The report as JSON on stdout, and in ``out`` where given."""
    text = json.dumps(report, indent=2, default=float)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    print(text)
    return report
