"""Failure-driven against uniform θ sampling, at equal CPU time (``curriculum.mixed.sampling``).

Two curricula of one config, the same seed, side by side (a process and a thread each): one
draws every mixed increment's (condition, difficulty) cells alike, the other draws part of them
where the latest scored model fails. Both train the same increments: the stopping rule is
turned off (M = N = the cap), so that neither stops earlier and the CPU each spends is the same
work. Reported for each:

* P (the loop's score on the standard test set) against the CPU seconds spent so far (render,
  train and evaluation of each increment), and the seconds until P first reached a target
  (``--target``; by default 0.95 of the lower of the two final P);
* the final model's mAP, precision and recall at the threshold on out-of-domain sets made by
  ``bench/wild_sets.py`` (the default recipe and the held-apart photographs), which the training
  never renders (``bench/compare_models.py``'s).

    python bench/sampling.py --out bench/results/sampling.json
    python bench/sampling.py --increments 3 --n-ood 60 --n-ood-apart 60   # quicker
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from bench.compare_models import ood_sets, score_set  # noqa: E402
from bench.report import machine, write_report  # noqa: E402

RULES = ("uniform", "failure")


def rule_config(base: dict, rule: str, increments: int, share: float) -> dict:
    """``base`` drawing its mixed θ by ``rule``, each stage exactly ``increments`` long, one thread."""
    config = {key: (dict(value) if isinstance(value, dict) else value) for key, value in base.items()}
    curriculum = dict(config.get("curriculum") or {})
    if not curriculum.get("mixed"):
        raise SystemExit("bench/sampling.py: the config has no curriculum.mixed stage to draw θ for")
    curriculum["mixed"] = {
        **curriculum["mixed"],
        "sampling": rule,
        "failure_share": share,
        "active_learning": {},  # the stages' own settings below apply to every stage alike
    }
    config["curriculum"] = curriculum
    # M + N > the cap: the windowed rule never fires, every stage trains `increments` increments.
    config["active_learning"] = {
        **(config.get("active_learning") or {}),
        "M": increments,
        "N": increments,
        "max_increments": increments,
    }
    config["detector"] = {**(config.get("detector") or {}), "num_threads": 1}
    config["name"] = f"{config.get('name', 'experiment')}-{rule}"
    return config


def read_run(data_dir: Path, database: Path | None = None) -> dict:
    """P against cumulative CPU seconds, and the final model's checkpoint, from a run's SQLite
    database (``foldwise run``'s own in ``data_dir`` unless given), read through ``services.queries``."""
    from collections import Counter

    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from db.models import Experiment, Model, ParameterSet
    from db.session import make_engine
    from services import queries

    engine = make_engine(f"sqlite:///{database or data_dir / 'foldwise.db'}")
    try:
        with Session(engine) as session:
            experiment = session.scalars(select(Experiment).order_by(Experiment.id)).first()
            column = queries.loop_score(experiment)  # P: the score the run's loop read
            scores = sorted(queries.history(session, experiment.id), key=lambda entry: (entry["stage"], entry["k"]))
            spent = queries.test_set_render_seconds(session, experiment.id)
            final = session.get(Model, experiment.final_model_id) if experiment.final_model_id else None
            checkpoint = final.checkpoint_path if final is not None else None
            reasons = Counter(
                drawn_for.get("sampling")
                for drawn_for in session.scalars(
                    select(ParameterSet.drawn_for).where(
                        ParameterSet.experiment_id == experiment.id, ParameterSet.drawn_for.is_not(None)
                    )
                )
            )
            status = experiment.status.value
    finally:
        engine.dispose()
    curve = []
    for entry in scores:
        spent += sum(entry[key] or 0.0 for key in ("train_seconds", "eval_seconds", "render_seconds"))
        curve.append(
            {
                "model_id": entry["model_id"],
                "stage": f"{entry['condition']}/{entry['difficulty']}",
                "k": entry["k"],
                "cpu_seconds": spent,
                "p": entry[column],
            }
        )
    return {
        "status": status,
        "loop_score": column,
        "curve": curve,
        "cpu_seconds": spent,
        "final_p": curve[-1]["p"] if curve else None,
        "best_p": max((point["p"] for point in curve if point["p"] is not None), default=None),
        "theta_drawn": dict(reasons),
        "checkpoint": str(data_dir / checkpoint) if checkpoint else None,
    }


def seconds_to(curve: list[dict], target: float) -> float | None:
    """CPU seconds until P first reached ``target`` (None: never)."""
    return next((point["cpu_seconds"] for point in curve if point["p"] is not None and point["p"] >= target), None)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs/quick.yaml")
    parser.add_argument("--increments", type=int, default=3, help="increments of every stage, both rules alike")
    parser.add_argument("--failure-share", type=float, default=0.5, help="curriculum.mixed.failure_share")
    parser.add_argument("--target", type=float, default=None, help="P whose CPU time to reach is compared")
    parser.add_argument("--n-ood", type=int, default=100, help="images of the default out-of-domain set")
    parser.add_argument("--n-ood-apart", type=int, default=100, help="images of the held-apart set (0: none)")
    parser.add_argument("--work-dir", type=Path, default=ROOT / "var/bench/sampling")
    parser.add_argument("--reuse", action="store_true", help="score runs already in --work-dir")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    base = yaml.safe_load(args.config.read_text())
    runs: dict[str, dict] = {}
    processes = {}
    started = time.perf_counter()
    for rule in RULES:
        data_dir = args.work_dir / rule
        if args.reuse and (data_dir / "foldwise.db").exists():
            continue
        if data_dir.exists():
            subprocess.run(["rm", "-rf", str(data_dir)], check=True)
        data_dir.mkdir(parents=True)
        config_path = data_dir / "config.yaml"
        config_path.write_text(yaml.safe_dump(rule_config(base, rule, args.increments, args.failure_share)))
        env = {**os.environ, "FOLDWISE_DATA_DIR": str(data_dir), "OMP_NUM_THREADS": "1"}
        env.pop("FOLDWISE_DATABASE_URL", None)
        log = (data_dir / "run.log").open("w")
        processes[rule] = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "run", str(config_path)],
            cwd=ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    for rule, process in processes.items():
        if process.wait() != 0:
            raise SystemExit(f"bench/sampling.py: the {rule} run failed; see {args.work_dir / rule / 'run.log'}")
    wall = time.perf_counter() - started
    for rule in RULES:
        runs[rule] = read_run(args.work_dir / rule)

    finals = [runs[rule]["final_p"] for rule in RULES if runs[rule]["final_p"] is not None]
    target = args.target if args.target is not None else (0.95 * min(finals) if finals else None)
    for rule in RULES:
        runs[rule]["seconds_to_target"] = seconds_to(runs[rule]["curve"], target) if target is not None else None

    sets = ood_sets(args.config, {"default": args.n_ood, "apart": args.n_ood_apart})
    threshold = (base.get("evaluation") or {}).get("score_threshold", 0.8)
    for rule in RULES:
        checkpoint = runs[rule]["checkpoint"]
        runs[rule]["out_of_domain"] = {
            name: score_set(checkpoint, folder, threshold) for name, folder in sets.items() if checkpoint
        }

    report = {
        "config": str(args.config),
        "increments_per_stage": args.increments,
        "failure_share": args.failure_share,
        "target_p": target,
        "runs_wall_seconds": wall if processes else None,
        "runs": runs,
        "difference": {
            name: _difference(runs, name) for name in sets if all(name in runs[r]["out_of_domain"] for r in RULES)
        },
        "machine": machine(),
    }
    report["headline"] = headline(report)
    return write_report(report, args.out)


def _difference(runs: dict, name: str) -> float | None:
    failure, uniform = (runs[rule]["out_of_domain"][name]["map"] for rule in ("failure", "uniform"))
    return None if failure is None or uniform is None else failure - uniform


def headline(report: dict) -> str:
    parts = []
    for rule in RULES:
        run = report["runs"][rule]
        sets = ", ".join(f"{name} {scores['map']:.3f}" for name, scores in run["out_of_domain"].items())
        to_target = run["seconds_to_target"]
        parts.append(
            f"{rule}: out of domain {sets}; P {run['final_p']:.3f} after {run['cpu_seconds']:.0f} CPU s"
            + (f", P {report['target_p']:.3f} reached at {to_target:.0f} s" if to_target is not None else "")
        )
    return "; ".join(parts)


if __name__ == "__main__":
    main()
