"""What `make run` does with its curriculum: its wall time, and for each member's stages how P
went from the model the stage started from to its best, and why the stage ended.

Runs ``foldwise run CONFIG --members N`` (make run's command; N as make run picks it) in a
scratch data folder, timed, and reads the run's own database: ``stages.end_reason`` and the
evaluation of every model of every stage. The goals it reports against: the whole run within
15 minutes, no stage whose best mAP is 0, every stage's best P above its start, and at least
half of the stages ended by the windowed rule.

    python bench/curriculum.py --out bench/results/curriculum.json
    python bench/curriculum.py --config configs/smoke.yaml --members 1
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402

GOAL_SECONDS = 15 * 60


def read_stages(database: Path) -> list[dict]:
    """Every experiment's stages, in order, with each model's P and mAP at the cut: read from
    the run's database through ``services.queries``, as the CLI's stage table and the API read them."""
    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from db.models import Experiment
    from db.session import make_engine
    from services import queries

    engine = make_engine(f"sqlite:///{database}")
    out = []
    try:
        with Session(engine) as session:
            for experiment in session.scalars(select(Experiment).order_by(Experiment.id)):
                scores = queries.history(session, experiment.id)
                for stage in queries.stages(session, experiment.id):
                    p = stage["loop_score"]
                    out.append(
                        {
                            "seed": experiment.seed,
                            "stage": f"{stage['condition']}/{stage['difficulty']}",
                            "order": stage["order"],
                            "end_reason": stage["end_reason"],
                            "p": p,
                            "start_p": stage["start_p"],
                            "best_p": stage["best_p"],
                            "best_map": stage["best_map"],
                            "increments": sorted(
                                (
                                    {"k": entry["k"], "p": entry[p], "map": entry["map"]}
                                    for entry in scores
                                    if entry["stage"] == stage["order"]
                                ),
                                key=lambda entry: entry["k"],
                            ),
                        }
                    )
    finally:
        engine.dispose()
    return out


def goals(stages: list[dict], seconds: float) -> dict:
    learned = [s for s in stages if s["best_p"] is not None and s["best_p"] > (s["start_p"] or 0.0)]
    plateau = [s for s in stages if s["end_reason"] == "plateau"]
    return {
        "within_15_minutes": seconds <= GOAL_SECONDS,
        "no_stage_best_map_zero": all((s["best_map"] or 0.0) > 0.0 for s in stages),
        "every_stage_raised_p": len(learned) == len(stages),
        "half_ended_by_the_rule": 2 * len(plateau) >= len(stages),
        "stages_ended_by_the_rule": f"{len(plateau)} of {len(stages)}",
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs/quick.yaml")
    parser.add_argument("--members", type=int, default=None, help="default: make run's (2 for quick.yaml, else 1)")
    parser.add_argument("--work-dir", type=Path, default=ROOT / "var/bench/curriculum")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    members = args.members or (2 if args.config.resolve() == (ROOT / "configs/quick.yaml").resolve() else 1)

    if args.work_dir.exists():
        subprocess.run(["rm", "-rf", str(args.work_dir)], check=True)
    args.work_dir.mkdir(parents=True)
    env = {**os.environ, "FOLDWISE_DATA_DIR": str(args.work_dir)}
    env.pop("FOLDWISE_DATABASE_URL", None)
    command = [sys.executable, "-m", "services.cli", "run", str(args.config), "--members", str(members)]
    started = time.perf_counter()
    with (args.work_dir / "run.log").open("w") as log:
        done = subprocess.run(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"bench/curriculum.py: the run failed; see {args.work_dir / 'run.log'}")

    stages = read_stages(args.work_dir / "foldwise.db")
    report = {
        "config": str(args.config),
        "members": members,
        "command": f"foldwise run {args.config} --members {members}",
        "wall_seconds": seconds,
        "stages": stages,
        "goals": goals(stages, seconds),
        "machine": machine(),
    }
    rows = ", ".join(
        f"seed {s['seed']} {s['stage']} {s['start_p'] or 0:.3f}->{s['best_p']:.3f} ({s['end_reason']})" for s in stages
    )
    report["headline"] = f"{members} members in {seconds / 60:.1f} min; P from start to best: {rows}"
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
