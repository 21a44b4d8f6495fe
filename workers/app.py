"""The Celery app: queues ``render``, ``train`` and ``detect``, and the settings that make them reliable.

``detect`` serves ``POST /models/{id}/detect``: a train-role worker (``foldwise worker detect``)
answers it, so the API never loads torch; it is the one task whose result travels back.

Task modules import bpy or torch only inside the task body, so either worker role can load
this app (and the scheduler can send tasks) without the other role's libraries.
"""

from __future__ import annotations

from celery import Celery
from kombu import Queue

from foldwise.settings import Settings, get_settings

RENDER_QUEUE = "render"
TRAIN_QUEUE = "train"
RENDER_TASK = "foldwise.render_batch"
TRAIN_TASK = "foldwise.train_increment"
DETECT_QUEUE = "detect"
DETECT_TASK = "foldwise.detect"


def result_backend_url(broker_url: str) -> str:
    """Where detect replies travel: the Redis broker itself, else RabbitMQ's reply queues (rpc)."""
    return broker_url if broker_url.startswith(("redis://", "rediss://")) else "rpc://"


def configure(app: Celery, settings: Settings) -> None:
    app.conf.update(
        broker_url=settings.broker_url,
        # Results live in the database, not in the broker; only the detect task (which sets
        # ignore_result=False) replies through the backend, to the API request waiting for it.
        task_ignore_result=True,
        result_backend=result_backend_url(settings.broker_url),
        result_expires=600,
        # Only detect replies travel through it, to a request that waits with a timeout of its own:
        # a lost broker answers a detect with a 503 in about a second, not after the Redis
        # backend's default 20 reconnections a second apart, each holding one of the API's
        # broker threads.
        result_backend_transport_options={
            "retry_policy": {"max_retries": 2, "interval_start": 0, "interval_step": 0.5, "interval_max": 0.5}
        },
        task_queues=(Queue(RENDER_QUEUE), Queue(TRAIN_QUEUE), Queue(DETECT_QUEUE)),
        task_routes={
            RENDER_TASK: {"queue": RENDER_QUEUE},
            TRAIN_TASK: {"queue": TRAIN_QUEUE},
            DETECT_TASK: {"queue": DETECT_QUEUE},
        },
        task_default_queue=RENDER_QUEUE,
        # A typo in a route must fail loudly, not create a queue no worker listens to.
        task_create_missing_queues=False,
        # Ack after the task ran: a worker killed mid-task leaves the message for another worker.
        task_acks_late=True,
        # ...and a worker process that dies (OOM, SIGKILL) gets its message requeued, not acked.
        task_reject_on_worker_lost=True,
        # One message at a time per process: a long training increment never hoards renders.
        worker_prefetch_multiplier=1,
        # Redis redelivers unacked messages after this; it must exceed the longest task or a
        # running increment would be delivered to a second worker.
        broker_transport_options={"visibility_timeout": settings.visibility_timeout_s},
        # The API can tell "started" from "waiting in the queue".
        task_track_started=True,
        task_serializer="json",
        accept_content=["json"],
        worker_hijack_root_logger=False,
        broker_connection_retry_on_startup=True,
        # Embedded mode and tests: run tasks in-process, and let their exceptions surface.
        task_always_eager=settings.eager,
        task_eager_propagates=True,
    )


def create_app(settings: Settings | None = None) -> Celery:
    app = Celery("foldwise", include=["workers.render.tasks", "workers.train.tasks", "workers.train.serving"])
    configure(app, settings or get_settings())
    return app


app = create_app()


def use_eager(eager: bool = True) -> None:
    """Switch this process's app to in-process execution (embedded mode, tests)."""
    app.conf.task_always_eager = eager
