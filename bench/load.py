"""The API under load, on loopback (JSON out): 50 clients mixing status reads, figure reads and
detects against one API process and one detect worker.

Everything is the bench's own and is removed afterwards: a temporary data folder and SQLite
database, a redis-server on a free port without persistence, the API as compose runs it
(``foldwise api``: one uvicorn process on uvloop and httptools, access log on) and
``foldwise worker detect --concurrency 1``. A 64-px YOLO is trained on eight renders first
(about 10 s) so that the worker runs a real network, and each figure is fetched once (drawn,
then served from the API's cache while the record does not change). Then, for ``--duration`` seconds, each client sends
requests one after another:

- status clients: ``/health`` and ``/experiments/{id}``, ``/stages``, ``/history``, waiting
  ``--think`` seconds after each answer (a dashboard polling);
- figure clients: ``report.png`` and ``figures/fig4.png``, ``fig6.png``, waiting ``--think``
  seconds after each answer;
- detect clients: ``POST /models/{id}/detect`` with a rendered image, the next one as soon as
  the last is answered (after ``Retry-After`` when refused).

All clients run in this one process on one asyncio loop, each on a keep-alive connection of its
own spoken with asyncio's streams (:class:`Connection`): the load costs the machine one process
beside the API's and the worker's, and as little CPU per request as an HTTP client can.

It reports the p50/p99 latency of each group while detects queue (the ``detect`` queue's depth
is sampled), and what became of every detect: answered, refused cleanly (503 with
``Retry-After``, the queue being full), timed out (504), or lost (anything else: a 500, a
dropped connection, no answer within the client's timeout). Goals: p99 of the status routes at
most 200 ms; no detect lost.

    python bench/load.py --out bench/results/load.json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import secrets
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STATUS_GOAL_P99_S = 0.2
CLIENT_TIMEOUT_S = 45.0  # longer than the API's 30 s detect wait: a 504 is an answer, silence is a loss


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def percentile(values: list[float], share: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(share * (len(ordered) - 1)))]


def summary(latencies: list[float]) -> dict:
    return {
        "count": len(latencies),
        "p50_ms": None if not latencies else round(1000 * percentile(latencies, 0.50), 1),
        "p99_ms": None if not latencies else round(1000 * percentile(latencies, 0.99), 1),
        "max_ms": None if not latencies else round(1000 * max(latencies), 1),
        "mean_ms": None if not latencies else round(1000 * statistics.fmean(latencies), 1),
    }


# --------------------------------------------------------------------------- the stack


def start_redis(port: int) -> subprocess.Popen:
    server = shutil.which("redis-server")
    if server is None:
        sys.exit("bench/load.py needs redis-server (apt-get install redis-server)")
    process = subprocess.Popen(
        [server, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    import redis

    client = redis.Redis(port=port)
    for _ in range(400):
        try:
            client.ping()
            return process
        except redis.ConnectionError:
            time.sleep(0.025)
    sys.exit("redis-server did not start")


def train_and_seed(data_dir: Path, url: str) -> dict:
    """A trained 64-px YOLO as the evaluated model of a running experiment with a history."""
    from datetime import timedelta

    import torch

    from db.migrate import upgrade
    from db.models import Evaluation, Experiment, ExperimentStatus, Model, ModelStatus, Stage, StageStatus
    from db.session import get_sessionmaker
    from foldwise import store
    from foldwise.config import AssetsConfig, DetectorConfig, ExperimentConfig
    from workers.render.assets import load_assets
    from workers.render.cli import render_dataset
    from workers.train.data import load_coco_dataset
    from workers.train.training import train_detector

    renders = data_dir / "renders"
    assets = load_assets(AssetsConfig(n_objects=2))
    render_dataset(
        renders, ["fb"], ["easy"], 8, seed=5, image_size=64, backend="raster", assets=assets, echo=lambda _: None
    )
    samples, classes = load_coco_dataset(renders)
    detector = DetectorConfig(
        family="yolo", backbone="mobilenet_v3_large_fpn", input_size=64, batch_size=4, num_threads=1
    )
    torch.set_num_threads(1)
    train_detector(samples, None, 150, detector, classes, renders / "model.pt", seed=0)

    upgrade(url)
    config = ExperimentConfig(name="load", curriculum={"conditions": ["fb"], "difficulties": ["easy", "medium"]})
    start = datetime.now(UTC) - timedelta(minutes=10)
    with get_sessionmaker(url)() as session:
        experiment = Experiment(
            name="load", config=config.model_dump(mode="json"), seed=0, classes=classes,
            status=ExperimentStatus.running, started_at=start,
        )  # fmt: skip
        session.add(experiment)
        session.flush()
        stages = [
            Stage(experiment_id=experiment.id, order=order, condition="fb", difficulty=difficulty,
                  status=StageStatus.running, started_at=start)
            for order, difficulty in enumerate(("easy", "medium"))
        ]  # fmt: skip
        session.add_all(stages)
        session.flush()
        models = []
        for index, (stage, k, score) in enumerate([(0, 1, 0.4), (0, 2, 0.6), (1, 1, 0.55), (1, 2, 0.7)]):
            model = Model(
                experiment_id=experiment.id, stage_id=stages[stage].id, increment=k, detector="yolo",
                status=ModelStatus.evaluated, iterations=150, train_seconds=5.0, attempts=1,
            )  # fmt: skip
            session.add(model)
            session.flush()
            model.checkpoint_path = store.checkpoint_path(experiment.id, model.id)
            session.add(
                Evaluation(
                    model_id=model.id, map=score, map_unthresholded=score, details={"fb": {"easy": score}},
                    eval_seconds=1.0, created_at=start + timedelta(seconds=30 * (index + 1)),
                )
            )  # fmt: skip
            models.append(model)
        session.commit()
        served = models[-1]
        target = store.resolve(served.checkpoint_path)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(renders / "model.pt", target)
        return {
            "experiment": experiment.id,
            "model": served.id,
            "image": Path(samples[0].image_path).read_bytes(),
        }


def wait_until_up(base: str, deadline_s: float = 60.0) -> None:
    import httpx

    started = time.monotonic()
    while time.monotonic() - started < deadline_s:
        try:
            if httpx.get(f"{base}/health", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"the API at {base} did not answer /health within {deadline_s:g} s")


def wait_for_worker(env: dict, deadline_s: float = 60.0) -> None:
    from foldwise.settings import Settings
    from workers.app import create_app

    celery = create_app(Settings(broker_url=env["FOLDWISE_BROKER_URL"]))
    started = time.monotonic()
    try:
        while time.monotonic() - started < deadline_s:
            if celery.control.ping(timeout=0.5):
                return
        raise RuntimeError(f"the detect worker did not answer a ping within {deadline_s:g} s")
    finally:
        celery.close()


# --------------------------------------------------------------------------- the load


class NoAnswer(ConnectionError):
    """The server closed the connection before a byte of the answer came."""


class Connection:
    """One keep-alive HTTP/1.1 connection to the API, one request at a time (a browser tab's).

    Written on asyncio's streams rather than with an HTTP client library: the clients share
    the machine with the API they measure, and per request this costs a fraction of httpx's
    CPU time. It speaks only what the API answers: ``Content-Length`` or chunked bodies."""

    # Under uvicorn's keep-alive timeout (5 s): a connection idle longer is opened anew.
    IDLE_S = 4.0

    def __init__(self, host: str, port: int, timeout_s: float = CLIENT_TIMEOUT_S) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.last_used = 0.0

    async def _open(self) -> None:
        self.close()
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None

    async def request(
        self, method: str, path: str, body: bytes = b"", headers: dict[str, str] | None = None
    ) -> tuple[int, dict[str, str], bytes]:
        """(status, headers with lower-case names, body). Raises OSError (``ConnectionError``
        included) or ``TimeoutError`` when no whole answer comes within ``timeout_s``."""
        lines = [f"{method} {path} HTTP/1.1", f"Host: {self.host}:{self.port}", f"Content-Length: {len(body)}"]
        lines += [f"{name}: {value}" for name, value in (headers or {}).items()]
        message = ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body
        reused = not (self.writer is None or time.monotonic() - self.last_used > self.IDLE_S or self.reader.at_eof())
        try:
            if not reused:
                await self._open()
            try:
                return await asyncio.wait_for(self._exchange(message), self.timeout_s)
            except (NoAnswer, ConnectionResetError, BrokenPipeError):
                if not reused:
                    raise
                # The server closed the kept-alive connection before reading this request (it
                # answered nothing): the request never arrived, and goes again on a new one.
                await self._open()
                return await asyncio.wait_for(self._exchange(message), self.timeout_s)
        except BaseException:
            self.close()  # the connection is somewhere in the middle of an answer
            raise
        finally:
            self.last_used = time.monotonic()

    async def _exchange(self, message: bytes) -> tuple[int, dict[str, str], bytes]:
        assert self.reader is not None and self.writer is not None
        self.writer.write(message)
        await self.writer.drain()
        status_line = await self.reader.readline()
        if not status_line:
            raise NoAnswer("the server closed the connection")
        headers = {}
        while (line := await self.reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.decode("latin-1").partition(":")
            headers[name.strip().lower()] = value.strip()
        if headers.get("transfer-encoding", "").lower() == "chunked":
            body = bytearray()
            while size := int((await self.reader.readline()).split(b";")[0], 16):
                body += await self.reader.readexactly(size + 2)
                del body[-2:]
            await self.reader.readline()  # the blank line after the last chunk
        else:
            body = await self.reader.readexactly(int(headers.get("content-length", "0")))
        if headers.get("connection", "").lower() == "close":
            self.close()
        return int(status_line.split()[1]), headers, bytes(body)


async def run_load(
    base: str,
    token: str,
    seeded: dict,
    clients: int,
    duration_s: float,
    per_client: int,
    redis_port: int,
    think_s: float,
) -> dict:
    from urllib.parse import urlsplit

    import redis.asyncio

    where = urlsplit(base)
    experiment, model = seeded["experiment"], seeded["model"]
    status_paths = [
        "/health",
        f"/experiments/{experiment}",
        f"/experiments/{experiment}/stages",
        f"/experiments/{experiment}/history",
    ]
    figure_paths = [
        f"/experiments/{experiment}/report.png",
        f"/experiments/{experiment}/figures/fig4.png",
        f"/experiments/{experiment}/figures/fig6.png",
    ]
    latencies: dict[str, list[float]] = {"health": [], "status": [], "figures": [], "detect_answered": []}
    detects = {"sent": 0, "answered": 0, "refused_503": 0, "timed_out_504": 0, "lost": 0}
    lost_examples: list[str] = []
    other_errors: dict[str, int] = {}
    depths: list[int] = []
    stop_at = time.monotonic() + duration_s
    detect_headers = {"Authorization": f"Bearer {token}", "Content-Type": "image/png"}

    def connection() -> Connection:
        return Connection(where.hostname, where.port)

    async def read_in_turn(index: int, paths: list[str], group, named) -> None:
        """GET ``paths`` in turn from ``index`` on, ``think_s`` apart: each latency under
        ``group(path)``, each answer but a 200 counted under ``named(path)`` and its code."""
        client = connection()
        try:
            for n in range(per_client):
                if time.monotonic() > stop_at:
                    return
                path = paths[(index + n) % len(paths)]
                began = time.perf_counter()
                code, _, _ = await client.request("GET", path)
                latencies[group(path)].append(time.perf_counter() - began)
                if code != 200:
                    key = f"GET {named(path)} {code}"
                    other_errors[key] = other_errors.get(key, 0) + 1
                await asyncio.sleep(think_s)
        finally:
            client.close()

    async def status_client(index: int) -> None:
        await read_in_turn(index, status_paths, lambda path: "health" if path == "/health" else "status", str)

    async def figure_client(index: int) -> None:
        await read_in_turn(index, figure_paths, lambda path: "figures", lambda path: path.rsplit("/", 1)[-1])

    async def detect_client(index: int) -> None:
        client = connection()
        try:
            for _ in range(per_client):
                if time.monotonic() > stop_at:
                    return
                detects["sent"] += 1
                began = time.perf_counter()
                try:
                    code, answer_headers, body = await client.request(
                        "POST", f"/models/{model}/detect", seeded["image"], detect_headers
                    )
                except (OSError, TimeoutError, asyncio.IncompleteReadError) as error:
                    detects["lost"] += 1
                    lost_examples.append(f"{type(error).__name__}: {error}"[:200])
                    continue
                if code == 200:
                    detects["answered"] += 1
                    latencies["detect_answered"].append(time.perf_counter() - began)
                elif code == 503 and answer_headers.get("retry-after"):
                    detects["refused_503"] += 1
                    # A polite client waits as told, but no longer than the run has left.
                    pause = min(float(answer_headers["retry-after"]), max(0.0, stop_at - time.monotonic()))
                    await asyncio.sleep(pause)
                elif code == 504:
                    detects["timed_out_504"] += 1
                else:
                    detects["lost"] += 1
                    lost_examples.append(f"{code}: {body[:200].decode('utf-8', 'replace')}")
        finally:
            client.close()

    async def sample_depth() -> None:
        queue = redis.asyncio.Redis(port=redis_port)
        try:
            while time.monotonic() < stop_at:
                depths.append(await queue.llen("detect"))
                await asyncio.sleep(0.25)
        finally:
            await queue.aclose()

    roles = [status_client, status_client, figure_client, detect_client, detect_client]
    # Each figure is drawn once for the record as it stands (services/api/drawings.py); the
    # first draws (matplotlib's import included) are timed apart, before the load.
    first = connection()
    began = time.monotonic()
    try:
        for path in figure_paths:
            assert (await first.request("GET", path))[0] == 200, path
    finally:
        first.close()
    first_draws_s = time.monotonic() - began
    stop_at = time.monotonic() + duration_s
    started = time.monotonic()
    tasks = [asyncio.create_task(roles[i % len(roles)](i)) for i in range(clients)]
    sampler = asyncio.create_task(sample_depth())
    await asyncio.gather(*tasks)
    await sampler
    took = time.monotonic() - started
    role_counts = {
        role.__name__: sum(1 for i in range(clients) if roles[i % len(roles)] is role) for role in set(roles)
    }
    return {
        "seconds": round(took, 1),
        "first_figure_draws_s": round(first_draws_s, 1),
        "clients": role_counts,
        "health": summary(latencies["health"]),
        "status_routes": summary(latencies["status"]),
        "figures": summary(latencies["figures"]),
        "detects": {
            **detects,
            "answered_latency": summary(latencies["detect_answered"]),
            "lost_examples": lost_examples[:5],
        },
        "detect_queue_depth": {
            "max": max(depths, default=0),
            "mean": round(statistics.fmean(depths), 1) if depths else 0,
        },
        "other_errors": other_errors,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--duration", type=float, default=20.0, help="seconds of load (each client stops after it)")
    parser.add_argument("--per-client", type=int, default=500, help="requests per client at most")
    parser.add_argument(
        "--think",
        type=float,
        default=0.5,
        help="seconds a status or figure client waits between its requests (a dashboard polls every 3 s; 0: a flood)",
    )
    parser.add_argument("--out", type=Path, default=None, help="write the JSON here too")
    args = parser.parse_args()
    if not (
        1 <= args.clients <= 200
        and 1 <= args.duration <= 300
        and 1 <= args.per_client <= 10_000
        and 0 <= args.think <= 60
    ):
        sys.exit(
            "--clients 1..200, --duration 1..300 s, --per-client 1..10000, --think 0..60 s: the bench stays bounded"
        )

    work = Path(tempfile.mkdtemp(prefix="foldwise-load-"))
    redis_port, api_port = free_port(), free_port()
    token = secrets.token_hex(16)
    env = {
        **os.environ,
        "FOLDWISE_DATA_DIR": str(work / "data"),
        "FOLDWISE_DATABASE_URL": f"sqlite:///{work / 'load.db'}",
        "FOLDWISE_BROKER_URL": f"redis://127.0.0.1:{redis_port}/0",
        "FOLDWISE_API_TOKEN": token,
        "FOLDWISE_CACHE_DIR": str(work / "cache"),
    }
    env.pop("FOLDWISE_EAGER", None)
    os.environ.update({key: env[key] for key in ("FOLDWISE_DATA_DIR", "FOLDWISE_DATABASE_URL", "FOLDWISE_BROKER_URL")})
    processes: list[subprocess.Popen] = []
    groups: list[subprocess.Popen] = []  # started in a session of their own: the worker and its pool
    try:
        processes.append(start_redis(redis_port))
        began = time.monotonic()
        seeded = train_and_seed(work / "data", env["FOLDWISE_DATABASE_URL"])
        setup_s = time.monotonic() - began
        logs = work / "logs"
        logs.mkdir()
        # As compose.yaml's api service runs it: `foldwise api`, one uvicorn process.
        api = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "api", "--host", "127.0.0.1", "--port", str(api_port)],
            cwd=ROOT, env=env, stdout=open(logs / "api.log", "w"), stderr=subprocess.STDOUT,
        )  # fmt: skip
        processes.append(api)
        worker = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "worker", "detect", "--concurrency", "1", "--loglevel", "warning"],
            cwd=ROOT, env=env, stdout=open(logs / "worker.log", "w"), stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        groups.append(worker)
        base = f"http://127.0.0.1:{api_port}"
        wait_until_up(base)
        wait_for_worker(env)
        # Other work on the machine shows in the latencies: the load average says how much there was.
        load_average = [round(value, 2) for value in os.getloadavg()]
        results = asyncio.run(
            run_load(base, token, seeded, args.clients, args.duration, args.per_client, redis_port, args.think)
        )
        from services.api.routes.detect import MAX_IN_FLIGHT, REPLY_TIMEOUT_S

        p99 = max(results["health"]["p99_ms"] or 0, results["status_routes"]["p99_ms"] or 0)
        met = p99 <= 1000 * STATUS_GOAL_P99_S
        detects = results["detects"]
        headline = (
            f"/health p50 {results['health']['p50_ms']} ms, p99 {results['health']['p99_ms']} ms; status routes "
            f"p50 {results['status_routes']['p50_ms']} ms, p99 {results['status_routes']['p99_ms']} ms "
            f"(goal p99 at most {1000 * STATUS_GOAL_P99_S:g} ms: {'met' if met else 'missed'}); detects "
            f"{detects['answered']} answered, {detects['refused_503']} refused (503), "
            f"{detects['timed_out_504']} timed out, {detects['lost']} lost; {args.clients} clients, "
            f"{args.duration:g} s, think {args.think:g} s"
        )
        report = {
            "bench": "load",
            "headline": headline,
            "date": datetime.now(UTC).isoformat(timespec="seconds"),
            "commit": commit(),
            "machine": {
                "cpu": cpu_model(),
                "cores": os.cpu_count(),
                "python": platform.python_version(),
                "load_average_before_load": load_average,  # 1, 5 and 15 minutes, with the stack started
            },
            "setup": {
                "api": "foldwise api (as compose.yaml runs it: one uvicorn process on uvloop and httptools, access "
                "log on), SQLite, loopback",
                "detect_worker": "foldwise worker detect --concurrency 1 (64-px YOLO, CPU)",
                "broker": "a redis-server of the bench's own",
                "max_detects_in_flight": MAX_IN_FLIGHT,
                "reply_timeout_s": REPLY_TIMEOUT_S,
                "duration_s": args.duration,
                "think_s": args.think,
                "train_and_seed_s": round(setup_s, 1),
            },
            "results": results,
            "goals": {
                "status_p99_ms_at_most": 1000 * STATUS_GOAL_P99_S,
                "status_p99_ms": p99,
                "status_p99_met": met,
                "no_detect_lost": results["detects"]["lost"] == 0,
            },
        }
        text = json.dumps(report, indent=2)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text + "\n")
        print(text)
    finally:
        for process in groups:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
        for process in reversed(processes):
            if process.poll() is None:
                process.terminate()
        for process in groups + processes:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
