"""POST /models/{id}/detect: a trained ω run on one uploaded image; POST /studies/{study}/detect:
the ensemble a study handed over (``foldwise run --members``, or ``foldwise ensemble --out``
into ``studies/<study>/ensemble.pt`` of the artifact store), the same way.

The API imports no torch: the image goes to a ``foldwise worker detect`` over the ``detect``
queue (:mod:`workers.train.serving`) and this request waits for the reply. With eager Celery
(embedded mode, tests) the task runs in this process instead.

The image's header is read before anything else is done with it: a few bytes can claim
50000x50000 pixels, which no decoder should be asked to allocate. The wait for the worker holds
no thread: every reply waited for is looked for together, by one poller on the event loop that
asks the result backend about all of them in one round trip (:class:`Replies`). Every call to
the broker runs on a few threads of its own (BROKER_THREADS): Celery keeps a result backend per
thread, and making one (entry points scanned, connections opened) costs far more than the call.
At most MAX_IN_FLIGHT detects wait at once; past that the answer is a 503 with ``Retry-After``,
so a crowd of detects with no (or slow) workers neither exhausts a thread pool nor delays the
other routes.
"""

import asyncio
import base64
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Annotated, Any, NamedTuple

from fastapi import APIRouter, HTTPException, Path, Query, Request, status
from pydantic import BaseModel, Field
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

# The Celery app (celery and kombu; neither torch nor bpy) is loaded with the API: imported by
# the first detect instead, it would hold the event loop, and every request waiting on it, for
# a few hundred milliseconds. Routes read ``workers.app.app`` when called (tests replace it).
import workers.app  # noqa: F401
from db.models import Model, ModelStatus
from foldwise import store
from foldwise.images import ImageError, image_size
from services.api.deps import ModelId, SessionDep, TokenRequired
from services.api.schemas import NOT_FOUND, WRITE_ERRORS, ErrorDetail, InvalidInput

# A rendered or photographed picture of one sheet is well under this.
MAX_IMAGE_BYTES = 8 << 20
# The pixels a detect worker decodes at most (workers.train.serving.MAX_PIXELS, checked there too).
MAX_IMAGE_PIXELS = 4096 * 4096
# How long a request waits for a detect worker before answering 504; the message expires then
# too, so that a worker that comes later drops it instead of answering no one.
REPLY_TIMEOUT_S = 30.0
# Detects waiting for a worker at once, per API process; more are refused with a 503.
MAX_IN_FLIGHT = 16
RETRY_AFTER_S = 5
# Replies are looked for FIRST_POLL_S after a detect is sent or a reply comes, then ever less
# often while none comes, up to every MAX_POLL_S.
FIRST_POLL_S = 0.02
MAX_POLL_S = 0.25
# Threads that talk to the broker (send a detect, look for replies, forget one), shared by every
# app of the process: each holds a Celery result backend of its own for the process's life.
BROKER_THREADS = 4
_broker = ThreadPoolExecutor(max_workers=BROKER_THREADS, thread_name_prefix="foldwise-broker")
IMAGE_TYPES = frozenset({"image/png", "image/jpeg", "application/octet-stream"})
# What the first bytes of a PNG and a JPEG are; anything else is refused before a worker sees it.
SIGNATURES = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff")

router = APIRouter(prefix="/models", tags=["models"])
study_router = APIRouter(prefix="/studies", tags=["studies"])
# A study's name as it names a folder of the artifact store: printable, no path separator.
STUDY_FOLDER = dict(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069/\\]+$")


class Detection(BaseModel):
    box: list[float] = Field(description="x0, y0, x1, y1 in the image's pixels")
    class_name: str = Field(alias="class", description="the object class")
    label: int = Field(description="index of the class in `classes`")
    score: float
    confirmed: bool | None = Field(
        default=None,
        description="whether the detector's texture check confirmed this box (its class's texture mapped onto it); "
        "null where the detector has no texture check",
    )


IMAGE_BODY = {
    "requestBody": {
        "required": True,
        "description": "The image file itself (PNG or JPEG), at most 8 MiB.",
        "content": {t: {"schema": {"type": "string", "format": "binary"}} for t in ("image/png", "image/jpeg")},
    }
}

# What both detect routes may answer about the image and the worker.
IMAGE_ERRORS = {
    413: {"model": ErrorDetail, "description": "the image is larger than 8 MiB"},
    415: {"model": ErrorDetail, "description": "not image/png, image/jpeg or application/octet-stream"},
    502: {"model": ErrorDetail, "description": "the detect worker failed on the image"},
    503: {
        "model": ErrorDetail,
        "description": f"{MAX_IN_FLIGHT} detects are already waiting for a worker (retry after `Retry-After` seconds), "
        "or the broker is unreachable",
    },
    504: {"model": ErrorDetail, "description": "no detect worker answered in time"},
}


class ImageSize(BaseModel):
    width: int
    height: int


class Detections(BaseModel):
    image: ImageSize
    classes: list[str]
    detections: list[Detection] = Field(description="best score first, at or above `threshold`")
    threshold: float
    seconds: float = Field(description="time the worker took (decoding included)")
    texture_check: bool = Field(
        default=False,
        description="whether the detector's texture check ran on the network's detections (detector.texture_check)",
    )
    texture_search: bool = Field(
        default=False,
        description="whether the texture also searched the whole image for sheets the network missed (detector.texture_search)",
    )
    calibrated: bool = Field(
        default=False,
        description="whether the scores are calibrated (`foldwise calibrate`, or the default calibration): "
        "each is the chance its box is true",
    )


class DetectResult(Detections):
    model_id: int


class StudyDetectResult(Detections):
    study: str
    members: int = Field(description="the detectors of the ensemble, detecting as one")


@router.post(
    "/{model_id}/detect",
    response_model=DetectResult,
    response_model_by_alias=True,
    dependencies=[TokenRequired],
    openapi_extra=IMAGE_BODY,
    responses={
        **WRITE_ERRORS,
        **NOT_FOUND,
        **IMAGE_ERRORS,
        409: {"model": ErrorDetail, "description": "the model has no checkpoint (not trained, or failed)"},
        422: {
            "model": InvalidInput,
            "description": f"the body is not a PNG or JPEG image that decodes, or its header claims more than "
            f"{MAX_IMAGE_PIXELS:,} pixels (the message names its size)",
        },
    },
)
async def detect(
    model_id: ModelId,
    request: Request,
    session: SessionDep,
    threshold: Annotated[float, Query(ge=0.0, le=1.0, description="keep detections scoring at least this")] = 0.5,
) -> dict[str, Any]:
    """Run ω ``model_id`` on the image in the body; boxes, classes and scores as JSON."""
    with _slot(request):
        image = await _read_image(request)
        # The model's row is read on the thread that sends the message (404, 409 from there).
        reply = await _ask_worker(lambda: _checkpoint_of(session, model_id), image, threshold)
    if "error" in reply:
        code = status.HTTP_409_CONFLICT if reply.get("missing") else status.HTTP_422_UNPROCESSABLE_CONTENT
        raise HTTPException(code, reply["error"])
    reply.pop("members", None)  # a recorded model is one detector
    return {"model_id": model_id, "threshold": threshold, **reply}


def _checkpoint_of(session, model_id: int) -> str:
    # Two columns, not the row: its training statistics are a document decoded for nothing here.
    row = session.execute(select(Model.status, Model.checkpoint_path).where(Model.id == model_id)).first()
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"model {model_id} does not exist")
    model_status, checkpoint = row
    if model_status != ModelStatus.evaluated or not checkpoint:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"model {model_id} is {model_status.value}: only a trained and evaluated model can detect",
        )
    session.close()  # the reply may take a while; hold no connection meanwhile
    return checkpoint


@contextmanager
def _slot(request: Request) -> Iterator[None]:
    """One of MAX_IN_FLIGHT places for a detect, or a 503 with Retry-After. The count lives on
    the app and changes only on its event loop, between awaits: no lock is needed."""
    state = request.app.state
    waiting = getattr(state, "detects_in_flight", 0)
    limit = getattr(state, "max_detects_in_flight", MAX_IN_FLIGHT)
    if waiting >= limit:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            f"{waiting} detects are already waiting for a worker: retry in {RETRY_AFTER_S} s",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        )
    state.detects_in_flight = waiting + 1
    try:
        yield
    finally:
        state.detects_in_flight -= 1


async def _ask_worker(checkpoint: Callable[[], str], image: bytes, threshold: float) -> dict[str, Any]:
    """The detect worker's reply, waited for without holding a thread.

    Where the detector is (``checkpoint()``, which may read the database) is found on the
    broker thread that publishes the message; the reply is then waited for with every other
    (:class:`Replies`), and fetched and forgotten by the look that finds it come."""
    from workers.app import app

    encoded = base64.b64encode(image).decode("ascii")

    def arguments() -> list:
        return [checkpoint(), encoded, threshold]

    if app.conf.task_always_eager:
        return await run_in_threadpool(lambda: _run_here(arguments()))
    loop = asyncio.get_running_loop()
    reply = await loop.run_in_executor(_broker, lambda: _publish(arguments()))
    collected = False
    try:
        outcome = await asyncio.wait_for(Replies.of(loop).wait(reply), REPLY_TIMEOUT_S)
        collected = True  # and forgotten by the look that found it
    except TimeoutError:
        raise HTTPException(
            status.HTTP_504_GATEWAY_TIMEOUT,
            f"no detect worker answered within {REPLY_TIMEOUT_S:g} s: start one with `foldwise worker detect`",
        ) from None
    finally:
        if not collected:
            await loop.run_in_executor(_broker, _forget, reply)
    if isinstance(outcome, Failed):  # the task raised in the worker: its failure, not the client's
        error = outcome.error
        raise HTTPException(status.HTTP_502_BAD_GATEWAY, f"the detect worker failed: {type(error).__name__}: {error}")
    return outcome


async def prepare_broker() -> None:
    """Load what the first detect would load on a broker thread, so that the first detects
    after the API starts do not wait for it: the result backend's module and classes, found
    through Celery's entry points (tens of milliseconds, the GIL held throughout). Nothing
    connects; whatever fails here fails again, and is answered, in the detect that needs it."""

    def prepare() -> None:
        from workers.app import app

        try:
            if not app.conf.task_always_eager:
                app.backend  # noqa: B018  (made on first use, per thread)
                app.connection_for_write().get_transport_cls()  # the transport's module, imported
        except Exception:
            pass

    await asyncio.get_running_loop().run_in_executor(_broker, prepare)


class Failed(NamedTuple):
    """The outcome of a task that raised in the worker."""

    error: Exception


class Replies:
    """The replies waited for on one event loop, looked for together.

    One poller task runs while any reply is waited for: each look is one hand-over to a broker
    thread that asks about every waiting reply at once (:func:`_collect`), so a crowd of waiting
    detects costs the event loop one hand-over per look, not one per detect."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.waiting: dict[Any, asyncio.Future] = {}
        self.pause = FIRST_POLL_S
        self.poller: asyncio.Task | None = None

    @classmethod
    def of(cls, loop: asyncio.AbstractEventLoop) -> "Replies":
        """The replies of ``loop`` (a test client may start a loop per request)."""
        replies = _replies.get(id(loop))
        if replies is None or replies.loop is not loop:
            _replies.clear()  # one loop serves the process at a time
            replies = _replies[id(loop)] = cls(loop)
        return replies

    async def wait(self, reply) -> Any:
        """The reply's result, or Failed; an HTTPException (503) when the broker stops answering."""
        future = self.loop.create_future()
        self.waiting[reply] = future
        self.pause = FIRST_POLL_S
        if self.poller is None or self.poller.done():
            self.poller = self.loop.create_task(self._poll())
        try:
            return await future
        finally:
            self.waiting.pop(reply, None)

    async def _poll(self) -> None:
        while self.waiting:
            await asyncio.sleep(self.pause)
            waiting = {reply: future for reply, future in self.waiting.items() if not future.done()}
            if not waiting:
                continue
            try:
                outcomes = await self.loop.run_in_executor(_broker, _collect, list(waiting))
            except Exception as error:  # the broker lost (a 503), or anything unforeseen: each waiter gets it
                for future in waiting.values():
                    if not future.done():
                        future.set_exception(error)
                continue
            self.pause = FIRST_POLL_S if outcomes else min(self.pause * 1.5, MAX_POLL_S)
            for reply, outcome in outcomes.items():
                if not waiting[reply].done():
                    waiting[reply].set_result(outcome)


_replies: dict[int, Replies] = {}


def _collect(replies: list) -> dict[Any, Any]:
    """On a broker thread: the outcome (result or Failed) of each reply that has come, each
    forgotten then. Celery results of a key-value backend (Redis) are read with one MGET;
    anything else is asked reply by reply. A 503 when the result backend stops answering."""
    from celery.result import AsyncResult

    outcomes: dict[Any, Any] = {}
    batched: dict[Any, list] = {}
    single = []
    for reply in replies:
        if isinstance(reply, AsyncResult) and hasattr(reply.backend, "mget"):
            batched.setdefault(reply.backend, []).append(reply)
        else:
            single.append(reply)
    for backend, group in batched.items():
        by_id = {reply.id: reply for reply in group}
        try:
            found = dict(backend.get_many(list(by_id), interval=0, max_iterations=1))
        except NotImplementedError:  # a key-value backend without MGET
            single += group
            continue
        except Exception as error:
            raise _broker_lost(error) from None
        for task_id, meta in found.items():
            result = meta["result"]  # a failed task's exception is already rebuilt (meta_from_decoded)
            outcomes[by_id[task_id]] = result if meta["status"] == "SUCCESS" else Failed(_as_exception(result))
    for reply in single:
        if _ready(reply):
            try:
                outcomes[reply] = reply.get(timeout=REPLY_TIMEOUT_S)
            except Exception as error:
                outcomes[reply] = Failed(error)
    for reply in outcomes:
        _forget(reply)
    return outcomes


def _as_exception(result: Any) -> Exception:
    return result if isinstance(result, Exception) else RuntimeError(str(result))


def _forget(reply) -> None:
    try:
        reply.forget()
    except Exception:  # a lost broker keeps the reply until result_expires: nothing to answer for
        pass


def _broker_lost(error: Exception) -> HTTPException:
    return HTTPException(
        status.HTTP_503_SERVICE_UNAVAILABLE,
        f"the broker stopped answering while the detect waited: {' '.join(str(error).split())[:300]}",
    )


def _ready(reply) -> bool:
    """Whether the reply has come; a 503 when the result backend (the broker) stops answering."""
    try:
        return reply.ready()
    except Exception as error:
        raise _broker_lost(error) from None


def _run_here(args: list) -> dict[str, Any]:
    """The detect task in this process (eager Celery: embedded mode, tests)."""
    import workers.train.serving  # noqa: F401  (registers the task)
    from workers.app import DETECT_TASK, app

    # send_task ignores task_always_eager: run the registered task here.
    return app.tasks[DETECT_TASK].apply(args=args, throw=True).get()


def _publish(args: list):
    """Send the detect message; it expires when the request stops waiting for it."""
    from workers.app import DETECT_QUEUE, DETECT_TASK, app

    try:
        return app.send_task(DETECT_TASK, args=args, queue=DETECT_QUEUE, expires=REPLY_TIMEOUT_S)
    except Exception as error:  # kombu's OperationalError and the socket errors under it
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE, f"the broker is unreachable: {' '.join(str(error).split())[:300]}"
        ) from None


async def _read_image(request: Request) -> bytes:
    """The body as a PNG or JPEG of at most MAX_IMAGE_BYTES and MAX_IMAGE_PIXELS (read from its
    header, nothing decoded), or the HTTP error that says why not."""
    media_type = (request.headers.get("content-type") or "").split(";", 1)[0].strip().lower()
    if media_type not in IMAGE_TYPES:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            f"unsupported content type {media_type or '(none)'}: send the image as image/png or image/jpeg",
        )
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > MAX_IMAGE_BYTES:
        raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"image larger than {MAX_IMAGE_BYTES} bytes")
    image = bytearray()
    async for chunk in request.stream():
        image += chunk
        if len(image) > MAX_IMAGE_BYTES:
            raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"image larger than {MAX_IMAGE_BYTES} bytes")
    if not image:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "empty body: send a PNG or JPEG image")
    if not bytes(image[:8]).startswith(SIGNATURES):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "the body is not a PNG or JPEG image")
    image = bytes(image)
    try:
        image_size(image, max_pixels=MAX_IMAGE_PIXELS)  # the header only: microseconds
    except ImageError as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(error)) from None
    return image


@study_router.post(
    "/{study}/detect",
    response_model=StudyDetectResult,
    response_model_by_alias=True,
    dependencies=[TokenRequired],
    openapi_extra=IMAGE_BODY,
    responses={
        **WRITE_ERRORS,
        **IMAGE_ERRORS,
        404: {"model": ErrorDetail, "description": "the study has no ensemble file in the artifact store"},
        422: {
            "model": InvalidInput,
            "description": f"a study name that is no folder name, a body that is not an image, or an image of more "
            f"than {MAX_IMAGE_PIXELS:,} pixels",
        },
    },
)
async def detect_with_study(
    study: Annotated[str, Path(**STUDY_FOLDER, description="the study whose ensemble detects")],
    request: Request,
    threshold: Annotated[float, Query(ge=0.0, le=1.0, description="keep detections scoring at least this")] = 0.5,
) -> dict[str, Any]:
    """Run the ensemble study ``study`` handed over on the image in the body: every member
    detects and their detections merge, as ``foldwise detect --model ENSEMBLE`` does."""
    if study in (".", ".."):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"study {study!r} names no folder")
    with _slot(request):
        image = await _read_image(request)
        reply = await _ask_worker(lambda: store.ensemble_path(study), image, threshold)
    if "error" in reply:
        if reply.get("missing"):
            raise HTTPException(
                status.HTTP_404_NOT_FOUND,
                f"study {study!r} has no ensemble ({store.ensemble_path(study)} in the artifact store): "
                "`foldwise run CONFIG --members N` writes one, `foldwise ensemble --model A --model B --out "
                "DATA_DIR/studies/NAME/ensemble.pt` joins recorded models into one",
            )
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, reply["error"])
    members = reply.pop("members", 1)
    return {"study": study, "members": members, "threshold": threshold, **reply}
