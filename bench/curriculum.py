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
import sqlite3
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
    """Every experiment's stages, in order, with each model's P and mAP at the cut."""
    db = sqlite3.connect(database)
    try:
        experiments = db.execute(
            "SELECT id, seed, json_extract(config, '$.evaluation.loop_score') FROM experiments ORDER BY id"
        ).fetchall()
        out = []
        for experiment_id, seed, loop_score in experiments:
            column = "map_unthresholded" if loop_score == "map_unthresholded" else "map"
            stages = db.execute(
                """SELECT id, "order", condition, difficulty, end_reason, init_model_id, best_model_id
                   FROM stages WHERE experiment_id = ? ORDER BY "order\"""",
                (experiment_id,),
            ).fetchall()
            p_of = dict(
                db.execute(
                    f"""SELECT m.id, e.{column} FROM models m JOIN evaluations e ON e.model_id = m.id
                        WHERE m.experiment_id = ?""",
                    (experiment_id,),
                ).fetchall()
            )
            for stage_id, order, condition, difficulty, reason, init_id, best_id in stages:
                models = db.execute(
                    f"""SELECT m.increment, e.{column}, e.map FROM models m JOIN evaluations e ON e.model_id = m.id
                        WHERE m.stage_id = ? ORDER BY m.increment""",
                    (stage_id,),
                ).fetchall()
                best = db.execute("SELECT map FROM evaluations WHERE model_id = ?", (best_id,)).fetchone()
                out.append(
                    {
                        "seed": seed,
                        "stage": f"{condition}/{difficulty}",
                        "order": order,
                        "end_reason": reason,
                        "p": column,
                        "start_p": p_of.get(init_id) if init_id is not None else None,
                        "best_p": p_of.get(best_id),
                        "best_map": best[0] if best else None,
                        "increments": [{"k": k, "p": p, "map": m} for k, p, m in models],
                    }
                )
        return out
    finally:
        db.close()


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
