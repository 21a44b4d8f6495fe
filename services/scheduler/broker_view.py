"""Which task messages someone holds, in the broker's own view: waiting in a Redis queue, or
reserved/running in a live worker (Celery's ``inspect active`` and ``inspect reserved``).

The scheduler asks only about work that was sent and has shown no sign of life for half a
lease (not claimed since it was sent, or a claim that missed two beats of lease/4), and sends
again exactly what nobody holds. Why not Celery's own redelivery alone: with ``task_acks_late`` a message a
dead worker held stays in Redis's ``unacked`` hash until ``visibility_timeout`` (6 h, which must
exceed the longest task), and a Redis restarted empty has nothing to redeliver at all. Why not
worker events (``worker-offline``): a SIGKILLed worker never sends one, and missed heartbeats
take as long as a lease to notice, which the claims already give us. ``inspect`` asks the live
workers directly, and the Redis lists are read without taking anything from them.

On RabbitMQ a message is redelivered as soon as the connection of the worker holding it drops
and durable queues survive a restart, so there the broker itself does this work; its queues
cannot be read without consuming, and the scheduler keeps the age rule (``requeue_after_s``).
"""

from __future__ import annotations

import base64
import json
import logging
from dataclasses import dataclass

log = logging.getLogger(__name__)

# How long the live workers have to answer ``inspect``. A worker's main process answers from
# its event loop, not from the pool, so a busy worker still answers within this.
INSPECT_TIMEOUT_S = 1.0
# kombu's Redis transport keeps priorities 3, 6, 9 in lists of their own beside the queue.
_PRIORITY_SEPARATOR = "\x06\x16"
_PRIORITY_STEPS = (3, 6, 9)


@dataclass(frozen=True)
class Held:
    """The θ ids and model ids in a message that someone holds."""

    render: frozenset[int]
    train: frozenset[int]


def _ids(task_name: str, args) -> tuple[str, list[int]] | None:
    from workers.app import RENDER_TASK, TRAIN_TASK

    if isinstance(args, str):  # older workers report a repr
        import ast

        try:
            args = ast.literal_eval(args)
        except (ValueError, SyntaxError):
            return None
    if not args:
        return None
    if task_name == RENDER_TASK:
        return "render", [int(i) for i in args[0]]
    if task_name == TRAIN_TASK:
        return "train", [int(args[0])]
    return None


def _queued(client, queue: str) -> list[tuple[str, list[int]]]:
    found = []
    for key in (queue, *(f"{queue}{_PRIORITY_SEPARATOR}{step}" for step in _PRIORITY_STEPS)):
        for raw in client.lrange(key, 0, -1):
            try:
                message = json.loads(raw)
                body = message["body"]
                if message.get("properties", {}).get("body_encoding") == "base64":
                    body = base64.b64decode(body)
                args = json.loads(body)[0]
                ids = _ids(message["headers"]["task"], args)
            except (ValueError, KeyError, IndexError, TypeError):
                continue  # not a task message of ours
            if ids:
                found.append(ids)
    return found


def held_messages(app, render_ids: set[int], train_ids: set[int]) -> Held | None:
    """What of ``render_ids`` and ``train_ids`` someone holds; None when the broker cannot be seen
    (not Redis, or unreachable): then nobody can say a message is lost."""
    broker_url = app.conf.broker_url or ""
    if not broker_url.startswith(("redis://", "rediss://")):
        return None
    import redis

    from workers.app import RENDER_QUEUE, TRAIN_QUEUE

    render: set[int] = set()
    train: set[int] = set()

    def add(found: tuple[str, list[int]] | None) -> None:
        if found:
            (render if found[0] == "render" else train).update(found[1])

    # The queues first, then the workers: a message moving from the queue to a worker in
    # between is seen in one or the other, never in neither.
    try:
        client = redis.Redis.from_url(broker_url, socket_timeout=2, socket_connect_timeout=2)
        try:
            for queue in (RENDER_QUEUE, TRAIN_QUEUE):
                for found in _queued(client, queue):
                    add(found)
        finally:
            client.close()
    except redis.RedisError as error:
        log.warning("broker not reachable (%s): no message can be called lost now", error)
        return None
    if render_ids <= render and train_ids <= train:
        return Held(frozenset(render), frozenset(train))
    try:
        inspector = app.control.inspect(timeout=INSPECT_TIMEOUT_S)
        replies = [inspector.active() or {}, inspector.reserved() or {}]
    except Exception as error:  # the broker went away between the two looks
        log.warning("inspect failed (%s): no message can be called lost now", error)
        return None
    for reply in replies:
        for tasks in reply.values():
            for task in tasks or ():
                add(_ids(task.get("name", ""), task.get("args")))
    return Held(frozenset(render), frozenset(train))
