"""Self-describing detector checkpoints ω, and ``detect_object`` (inference; ``detect_ensemble``
for several checkpoints detecting as one).

A checkpoint is one ``torch.save`` file holding plain data only (loadable with
``weights_only=True``)::

    {"format": "foldwise-detector", "format_version": 1,
     "meta": {"family", "backbone", "classes", "input_size", "iterations" (cumulative),
              "config" (the DetectorConfig), "buffers" (e.g. yolo anchors, as lists), ...},
     "state_dict": {...}}

``load_detector(path)`` rebuilds the model from ``meta`` alone. Writes are atomic (a temp file
in the same folder, then rename), so a crash never leaves a half-written ω behind: a writer
killed mid-write leaves only its temporary file (``.<name>.<random>.tmp``, never read), and a
write the volume has no room for (full, over quota, past the file size limit) raises
:class:`NoRoomError` and leaves the file at the path as it was, so that the write can be tried
again once there is room.

An ensemble (``save_ensemble``: the final models of curricula run with other seeds, say) is one
file holding its members' checkpoints whole, so it travels alone::

    {"format": "foldwise-ensemble", "format_version": 1, "members": [<checkpoint>, ...]}

``load_detector`` reads both kinds: an ensemble is a :class:`Detector` whose model runs every
member and merges their detections (:class:`EnsembleModel`), so whatever detects with one
checkpoint (``foldwise detect``, ``foldwise evaluate``, ``bench/wild.py``, ONNX export) detects with
an ensemble.
Training starts from one network, so ``read_checkpoint`` (warm starts, fine-tuning) refuses an
ensemble by name.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import io
import os
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from foldwise.config import DetectorConfig, view_count

CHECKPOINT_FORMAT = "foldwise-detector"
CHECKPOINT_VERSION = 1
ENSEMBLE_FORMAT = "foldwise-ensemble"
ENSEMBLE_VERSION = 1
# DetectorConfig fields that change the network's shape or meaning: a warm start must agree.
ARCHITECTURE_FIELDS = ("family", "backbone")
RCNN_FAMILIES = ("faster_rcnn", "fast_rcnn")


# The errors of a write refused for want of room: the volume is full (ENOSPC), the quota spent
# (EDQUOT), or the file would pass the largest this process may write (EFBIG: the filesystem's
# limit, or RLIMIT_FSIZE; Python ignores SIGXFSZ, so the write fails instead of the process).
NO_ROOM_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
# Checkpoints are serialised in memory, then written in pieces of this size.
WRITE_CHUNK_BYTES = 1 << 20


class CheckpointError(ValueError):
    """A checkpoint that cannot be read, or that does not fit the requested detector."""


class NoRoomError(OSError):
    """A checkpoint or ensemble write refused for want of room on its volume (``errno`` one of
    NO_ROOM_ERRNOS). Nothing of it was kept: the file at its path, if any, is the one written
    before, whole. The same write succeeds once there is room."""


@dataclass(frozen=True)
class Cascade:
    """``detect_object`` in two passes, for a detector with several views and a texture check:
    each image first at one view (upright, at ``size`` px: None, the largest of the model's
    ``test_sizes``) with the check, and at all of its views (checked again, on the keypoints
    already found) only where the texture confirmed none of that view's boxes (nor found a
    sheet), or, with ``unsure``, where a box it did not confirm scores at least that after the
    check. Where the texture confirmed a box, the first pass's detections are the answer.

    On make run's ensemble one view confirmed a box in most images of foldwise's out-of-domain
    sets, and the cascade scored as every view did or above (boxes the texture confirmed at one
    view come without the high-scored clutter twenty views' vote adds); ``unsure`` sent more
    images on for less mAP (bench/README.md, "Detection's speed against its accuracy", and
    bench/results/detect_speed.json). An ONNX export holds every view: the check, and so the
    cascade, runs outside it.
    """

    size: int | None = None
    unsure: float | None = None

    def first_size(self, sizes: Sequence[int]) -> int | None:
        """The first pass's size for a model detecting at ``sizes``."""
        return self.size if self.size is not None else (max(sizes) if sizes else None)

    def again(self, checked: Mapping[str, np.ndarray]) -> bool:
        """Whether checked detections of the first pass call for every view."""
        confirmed = checked["confirmed"]
        if not confirmed.any():
            return True
        return self.unsure is not None and bool(np.any(~confirmed & (checked["scores"] >= self.unsure)))


@dataclass
class Detector:
    """A trained detector ω: the model (eval mode) and its self-description."""

    model: nn.Module
    meta: dict[str, Any]
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    # Grayscale texture per class, where the checkpoint carries them (detector.texture_check).
    textures: dict[str, np.ndarray] | None = None
    # Grayscale sheets of the classes' kind that are none of them, where the checkpoint carries
    # them (``write_lookalikes``): the texture check's matches on them are no evidence.
    lookalikes: dict[str, np.ndarray] | None = None
    # Detection in two passes (``detect_object``): one view first, every view only where it leaves
    # the image unsure. None: every view on every image.
    cascade: Cascade | None = Cascade()
    # Opens the checkpoint's runtime graph (``workers.train.export``), where it has one beside it:
    # ``runtime`` calls it on first use.
    runtime_loader: Callable[[], Any] | None = field(default=None, repr=False)
    _runtime: Any = field(default=None, init=False, repr=False)
    _runtime_lock: Any = field(default_factory=threading.Lock, init=False, repr=False)
    _texture_check: Any = field(default=None, init=False, repr=False)

    @property
    def runtime(self):
        """The network at its own views as an onnxruntime session (``OnnxDetector``), or None:
        ``detect_object`` runs those views through it instead of torch, the same detections in
        about half the time on 2 cores. Opened on first use (about a second, once), so
        a process whose images never need every view does not pay for it."""
        with self._runtime_lock:
            if self.runtime_loader is not None:
                loader, self.runtime_loader = self.runtime_loader, None
                self._runtime = loader()
            return self._runtime

    @runtime.setter
    def runtime(self, value) -> None:
        with self._runtime_lock:
            self.runtime_loader, self._runtime = None, value

    def texture_check(self):
        """The :class:`~workers.train.texture_check.TextureCheck` of this detector's textures
        (built once), or None when its config does not ask for one or it carries no textures."""
        if not self.config.texture_check or not self.textures:
            return None
        if self._texture_check is None:
            from foldwise.settings import get_settings
            from workers.train.texture_check import TextureCheck

            cache = get_settings().cache_dir
            self._texture_check = TextureCheck(
                self.textures,
                self.classes,
                search=self.config.texture_search,
                cache_dir=None if cache is None else cache / "texture-check",
                calibration=self.calibration,
                lookalikes=self.lookalikes,
            )
        return self._texture_check

    def active_cascade(self) -> Cascade | None:
        """The cascade ``detect_object`` runs at this detector's own views: its ``cascade`` where
        its config's ``cascade`` is on, it has a texture check to tell sure from unsure and
        several views; None where it detects in one pass."""
        views = view_count(getattr(self.model, "test_sizes", ()), getattr(self.model, "test_turns", ()))
        if not (self.config.texture_check and self.textures) or not self.config.cascade or views < 2:
            return None
        return self.cascade

    @property
    def calibration(self):
        """The score calibration the checkpoint records (``write_calibration``), or None."""
        from workers.train.calibration import Calibration

        record = self.meta.get("calibration")
        return Calibration.from_dict(record) if record else None

    @property
    def classes(self) -> list[str]:
        return list(self.meta["classes"])

    @property
    def config(self) -> DetectorConfig:
        return DetectorConfig.model_validate(self.meta["config"])


def _named_buffers(model: nn.Module) -> dict[str, list]:
    """Buffers that are not BatchNorm running statistics (e.g. anchors), as JSON-able lists."""
    skip = ("running_mean", "running_var", "num_batches_tracked")
    return {
        name: buffer.detach().cpu().tolist()
        for name, buffer in model.named_buffers()
        if not name.endswith(skip) and buffer.numel() <= 4096
    }


def save_checkpoint(
    model: nn.Module,
    meta: dict[str, Any],
    path: str | Path,
    textures: Mapping[str, np.ndarray] | None = None,
    lookalikes: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write ``model`` and ``meta`` to ``path`` atomically; returns the path. ``textures`` (class
    name to an RGB or grayscale uint8 image) and ``lookalikes`` (sheets that are none of the
    classes, by name) go in grayscale, for the texture check."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(meta)
    meta.setdefault("buffers", _named_buffers(model))
    payload = {
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "meta": meta,
        "state_dict": {name: tensor.detach().cpu() for name, tensor in model.state_dict().items()},
    }
    from workers.train.texture_check import grayscale

    for key, images in (("textures", textures), ("lookalikes", lookalikes)):
        if images:
            payload[key] = {
                str(name): torch.from_numpy(grayscale(np.asarray(image, dtype=np.uint8)).copy())
                for name, image in images.items()
            }
    return _write_atomically(payload, path)


def payload_textures(payload: dict[str, Any], key: str = "textures") -> dict[str, np.ndarray] | None:
    """The grayscale textures a detector's payload carries (texture check), or None; ``key``
    "lookalikes": the lookalike sheets it carries."""
    textures = payload.get(key)
    if not textures:
        return None
    return {str(name): tensor.numpy() for name, tensor in textures.items()}


def _write_atomically(payload: dict[str, Any], path: Path) -> Path:
    """``payload`` to ``path`` through a temporary file beside it, fsynced, then renamed over it."""
    serialised = io.BytesIO()
    # Serialised first: a refused write then fails in os.write, with its errno (torch's own
    # writer turns it into a RuntimeError that no longer says why).
    torch.save(payload, serialised)
    data = serialised.getbuffer()
    temporary = None
    try:
        descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            remaining = data
            while remaining:
                written = os.write(descriptor, remaining[:WRITE_CHUNK_BYTES])
                remaining = remaining[written:]
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        os.chmod(temporary, 0o644)  # mkstemp makes it private; other roles read checkpoints
        os.replace(temporary, path)
    except BaseException as error:
        if temporary is not None and os.path.exists(temporary):
            os.unlink(temporary)
        if isinstance(error, OSError) and error.errno in NO_ROOM_ERRNOS:
            raise NoRoomError(
                error.errno,
                f"no room on the volume for {path} ({len(data) / 1e6:.1f} MB): {error.strerror}; "
                "the file there is as it was",
            ) from error
        raise
    return path


def _load_payload(path: str | Path) -> dict[str, Any]:
    """A checkpoint or ensemble file's payload, checked for format and version."""
    return _read_payload(path, digest=False)[0]


def _read_payload(path: str | Path, digest: bool) -> tuple[dict[str, Any], str | None]:
    """``_load_payload``'s payload and, with ``digest``, the SHA-256 of the very bytes it was read
    from (the file is read once: a runtime graph is matched against the model in memory, not
    against whatever the file holds a moment later)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        data = path.read_bytes()
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 (torch raises many types for a corrupt or foreign file)
        raise CheckpointError(f"checkpoint {path} cannot be read: {type(error).__name__}: {error}") from None
    kind = payload.get("format") if isinstance(payload, dict) else None
    if kind == ENSEMBLE_FORMAT:
        version, expected = payload.get("format_version"), ENSEMBLE_VERSION
        if version != expected:  # before its members: another version may hold them otherwise
            raise CheckpointError(
                f"ensemble {path} has format version {version}; this foldwise reads version {expected}"
            )
        members = payload.get("members")
        if not isinstance(members, list) or not members:
            raise CheckpointError(f"ensemble {path} holds no members")
        for index, member in enumerate(members, start=1):
            _check_detector_payload(member, f"{path} (member {index})")
    else:
        _check_detector_payload(payload, str(path))
    return payload, hashlib.sha256(data).hexdigest() if digest else None


def _check_detector_payload(payload: Any, where: str) -> None:
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{where} is not a foldwise detector checkpoint")
    version = payload.get("format_version")
    if version != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"checkpoint {where} has format version {version}; this foldwise reads version {CHECKPOINT_VERSION}"
        )


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The raw payload of one detector's checkpoint (what training starts from), checked for
    format and version; an ensemble is refused by name."""
    payload = _load_payload(path)
    if payload["format"] == ENSEMBLE_FORMAT:
        raise CheckpointError(
            f"{path} is an ensemble of {len(payload['members'])} detectors: it detects as one, but training "
            "starts from one network; start from one of the checkpoints it was made from"
        )
    return payload


def save_ensemble(checkpoints: Sequence[str | Path], path: str | Path) -> Path:
    """Write the detector checkpoints at ``checkpoints`` (one class list, in one order) as one
    ensemble file at ``path``, atomically; returns the path."""
    members = [read_checkpoint(checkpoint) for checkpoint in checkpoints]
    if not members:
        raise CheckpointError("an ensemble needs at least one checkpoint")
    try:
        _check_one_class_list([member["meta"]["classes"] for member in members], [str(c) for c in checkpoints])
    except ValueError as error:
        raise CheckpointError(str(error)) from None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return _write_atomically({"format": ENSEMBLE_FORMAT, "format_version": ENSEMBLE_VERSION, "members": members}, path)


def write_calibration(source: str | Path, calibration, path: str | Path) -> Path:
    """The checkpoint or ensemble at ``source`` written to ``path`` (atomically; it may be
    ``source``) with ``calibration`` (a :class:`~workers.train.calibration.Calibration`)
    recorded in it: in its meta, or every member's, so that the detector it loads as scores by it."""
    from workers.train.export import carry_runtime_graph, matching_runtime_graph

    payload = _load_payload(source)
    graph = matching_runtime_graph(source)  # the network is unchanged: its runtime graph comes along
    members = payload["members"] if payload["format"] == ENSEMBLE_FORMAT else [payload]
    for member in members:
        member["meta"] = {**member["meta"], "calibration": calibration.to_dict()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    written = _write_atomically(payload, path)
    if graph is not None:
        carry_runtime_graph(graph, written, calibration=calibration.to_dict())
    return written


def write_lookalikes(source: str | Path, lookalikes: Mapping[str, np.ndarray], path: str | Path) -> Path:
    """The checkpoint or ensemble at ``source`` written to ``path`` (atomically; it may be
    ``source``) carrying ``lookalikes`` (name to an RGB or grayscale uint8 image; none: it
    carries none) in grayscale, for its texture check."""
    from workers.train.export import carry_runtime_graph, matching_runtime_graph
    from workers.train.texture_check import grayscale

    payload = _load_payload(source)
    graph = matching_runtime_graph(source)  # the network is unchanged: its runtime graph comes along
    members = payload["members"] if payload["format"] == ENSEMBLE_FORMAT else [payload]
    stored = {
        str(name): torch.from_numpy(grayscale(np.asarray(image, dtype=np.uint8)).copy())
        for name, image in lookalikes.items()
    }
    for member in members:
        if stored:
            member["lookalikes"] = stored
        else:
            member.pop("lookalikes", None)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    written = _write_atomically(payload, path)
    if graph is not None:
        carry_runtime_graph(graph, written)
    return written


def check_compatible(meta: dict[str, Any], config: DetectorConfig, classes: Sequence[str], path: str | Path) -> None:
    """Raise CheckpointError when ω_in cannot initialise a detector of ``config`` for ``classes``."""
    problems = []
    for key in ARCHITECTURE_FIELDS:
        if meta.get(key) != getattr(config, key):
            problems.append(f"{key}: checkpoint has {meta.get(key)!r}, config asks for {getattr(config, key)!r}")
    built_with = meta.get("config", {}).get("pretrained")
    if config.family in RCNN_FAMILIES and built_with != config.pretrained:
        # ImageNet-initialised R-CNN backbones freeze BatchNorm; random ones train it: other layers.
        problems.append(f"pretrained: checkpoint was built with {built_with!r}, config asks for {config.pretrained!r}")
    if list(meta.get("classes", [])) != list(classes):
        problems.append(f"classes: checkpoint has {list(meta.get('classes', []))}, training set has {list(classes)}")
    if problems:
        raise CheckpointError(f"cannot warm-start from {path}: " + "; ".join(problems))


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run with ``count`` torch intra-op threads (0: leave torch's choice), then restore.

    On a shared, oversubscribed CPU, more threads than free cores makes torch several times
    slower (its OpenMP workers spin), so the config's thread count matters in inference too.
    """
    from foldwise.settings import get_settings

    cap = get_settings().threads  # this process's share of a machine it shares (FOLDWISE_THREADS)
    if cap > 0:
        count = min(count, cap) if count > 0 else cap
    previous = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``auto``/None: CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("detector.device is 'cuda' but torch sees no CUDA device")
    return device


def model_from_meta(meta: dict[str, Any], config: DetectorConfig | None = None) -> nn.Module:
    """An untrained model with the architecture described by ``meta`` (or ``config``)."""
    from workers.train.detectors import build_detector

    config = config or DetectorConfig.model_validate(meta["config"])
    # The state dict brings the weights: no ImageNet file needed.
    return build_detector(config, len(meta["classes"]), load_pretrained=False)


def load_state(model: nn.Module, state_dict: dict[str, torch.Tensor], path: str | Path) -> None:
    try:
        model.load_state_dict(state_dict)
    except RuntimeError as error:
        raise CheckpointError(f"checkpoint {path} does not fit the detector it describes: {error}") from None


def load_detector(path: str | Path, device: str | torch.device | None = None) -> Detector:
    """Rebuild the detector stored at ``path`` from its metadata alone, in eval mode; an
    ensemble file gives its members as one detector (:func:`combine_detectors`)."""
    from workers.train.export import load_runtime_graph, runtime_graph_path

    target = resolve_device(device)
    with_graph = target.type == "cpu" and runtime_graph_path(path).is_file()
    payload, sha256 = _read_payload(path, digest=with_graph)
    members = payload["members"] if payload["format"] == ENSEMBLE_FORMAT else [payload]
    detectors = []
    for member in members:
        model = model_from_meta(member["meta"])
        load_state(model, member["state_dict"], path)
        model.to(target).eval()
        detectors.append(
            Detector(
                model=model,
                meta=member["meta"],
                device=target,
                textures=payload_textures(member),
                lookalikes=payload_textures(member, "lookalikes"),
            )
        )
    try:
        detector = detectors[0] if payload["format"] == CHECKPOINT_FORMAT else combine_detectors(detectors)
    except ValueError as error:
        raise CheckpointError(f"ensemble {path}: {error}") from None
    if with_graph:
        threads = int(detector.meta.get("config", {}).get("num_threads", 0))
        # The digest of the bytes the model was read from: a graph of a later rewrite is no graph of it.
        detector.runtime_loader = functools.partial(
            load_runtime_graph, path, detector.classes, threads=threads, sha256=sha256
        )
    return detector


class EnsembleModel(nn.Module):
    """Several detectors' models as one (eval only): each detects at its own views, and their
    detections merge per image as a detector's views do (per-class NMS at ``iou``, the best
    ``limit`` kept). Members whose views vote (``view_vote``) combine their voted scores by the
    same rule at a vote of 1, so the ensemble scores as if one detector's views had all voted
    together. Setting ``test_sizes`` or ``test_turns`` sets every member's."""

    def __init__(self, members: Sequence[nn.Module], iou: float, limit: int, vote: float | None = None) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        self.iou, self.limit, self.vote = float(iou), int(limit), vote

    def forward(self, images):
        from workers.train.detectors.views import merge_detections

        if self.training:
            raise RuntimeError("an ensemble only detects: train each member")
        members = list(self.members)
        if _views_alike(members):
            # Each member's views, as member(images) gives them, with the views' resizing (and the
            # trunk, where the members share one) done once per view for all of them.
            from workers.train.detectors.views import ensemble_detect, view_runs

            sizes, turns = members[0].test_sizes, members[0].test_turns
            views = view_runs(members, ensemble_detect(members), images, sizes, turns)
            if sizes or turns:
                runs = [
                    [
                        merge_detections(outputs, m.roi_heads.nms_thresh, m.roi_heads.detections_per_img, m.view_vote)
                        for outputs in zip(*member_views)
                    ]
                    for m, member_views in zip(members, views)
                ]
            else:
                runs = [member_views[0] for member_views in views]
        else:
            runs = [member(images) for member in members]
        return [merge_detections(outputs, self.iou, self.limit, self.vote) for outputs in zip(*runs)]

    def _views(name: str):  # noqa: N805 (a property factory, not a method)
        def get(self):
            return getattr(self.members[0], name)

        def set_(self, value) -> None:
            for member in self.members:
                setattr(member, name, value)

        return property(get, set_)

    test_sizes = _views("test_sizes")
    test_turns = _views("test_turns")
    del _views


def _views_alike(members: Sequence[nn.Module]) -> bool:
    """Whether the members are Faster R-CNNs detecting at the same views (they then run their
    views together: ``EnsembleModel.forward``)."""
    from workers.train.detectors.faster_rcnn import FasterRCNN

    first = members[0]
    return all(
        isinstance(member, FasterRCNN)
        and (member.test_sizes, member.test_turns) == (first.test_sizes, first.test_turns)
        for member in members
    )


def combine_detectors(detectors: Sequence[Detector]) -> Detector:
    """Several detectors of one class list, on one device, as one :class:`Detector` (one
    detector: itself). Its ``meta`` is the first member's, with every member's in ``members``;
    its detections are the members' merged at the first member's NMS IoU and detection cap (by
    vote where the first member's views vote: :class:`EnsembleModel`)."""
    if not detectors:
        raise ValueError("an ensemble needs at least one detector")
    if len(detectors) == 1:
        return detectors[0]
    first = detectors[0]
    _check_one_class_list([d.classes for d in detectors], [f"detector {i}" for i in range(1, len(detectors) + 1)])
    for index, detector in enumerate(detectors[1:], start=2):
        if detector.device != first.device:
            raise ValueError(f"detector {index} is on {detector.device}, detector 1 on {first.device}")
    heads = getattr(first.model, "roi_heads", None)  # yolo has none: torchvision's NMS IoU, the config's cap
    iou, limit = (
        (heads.nms_thresh, heads.detections_per_img) if heads is not None else (0.5, first.config.detections_per_image)
    )
    meta = {**first.meta, "members": [detector.meta for detector in detectors]}
    # One class list, so one set of textures checks the merged detections (the first member's).
    textures = next((d.textures for d in detectors if d.textures), None)
    lookalikes = next((d.lookalikes for d in detectors if d.lookalikes), None)
    return Detector(
        model=EnsembleModel([d.model for d in detectors], iou, limit, vote=1.0 if first.config.view_vote else None),
        meta=meta,
        device=first.device,
        textures=textures,
        lookalikes=lookalikes,
    )


def _check_one_class_list(class_lists: Sequence[Sequence[str]], names: Sequence[str]) -> None:
    """ValueError naming the first member whose classes differ from the first's (names, order)."""
    first = list(class_lists[0])
    for name, classes in zip(names[1:], class_lists[1:]):
        if list(classes) != first:
            raise ValueError(
                f"{name} has the classes {list(classes)}, {names[0]} {first}: an ensemble needs one class list, in one order"
            )


def member_families(detector: Detector) -> list[str]:
    """The detector family of each member (one detector: its own)."""
    return [meta["family"] for meta in detector.meta.get("members", [detector.meta])]


def _image_array(image: np.ndarray | str | Path, index: int) -> tuple[np.ndarray, Path | None]:
    from workers.train.data import as_rgb_uint8, read_image_rgb

    if isinstance(image, (str, Path)):
        return read_image_rgb(image), Path(image)
    return as_rgb_uint8(image, where=f"images[{index}]"), None


@contextmanager
def _test_views(model: nn.Module, sizes: Sequence[int] | None, turns: Sequence[int] | None) -> Iterator[None]:
    """The model detects at ``sizes`` and ``turns`` inside the block (None: as built), as before after it."""
    overrides = {
        name: tuple(value) for name, value in (("test_sizes", sizes), ("test_turns", turns)) if value is not None
    }
    saved = {name: getattr(model, name) for name in overrides}
    try:
        for name, value in overrides.items():
            setattr(model, name, value)
        yield
    finally:
        for name, value in saved.items():
            setattr(model, name, value)


def detect_object(
    detector: Detector,
    images: Sequence[np.ndarray | str | Path],
    batch_size: int = 8,
    on_batch: Callable[[int], None] | None = None,
    test_sizes: Sequence[int] | None = None,
    test_turns: Sequence[int] | None = None,
    texture_check: bool = True,
    every_view: bool = False,
    with_evidence: bool = False,
) -> list[dict[str, np.ndarray]]:
    """Detections per image: ``boxes`` (n, 4) float32 xyxy in that image's pixels, ``scores``
    (n,) float32, ``labels`` (n,) int64 0-based class indices, best score first.

    Images are RGB uint8 arrays or paths (read with OpenCV); any size (the model resizes to
    its input size and maps boxes back). Runs with the detector config's ``num_threads``.
    ``on_batch(images_done)`` is called after every batch (progress display). ``test_sizes``
    overrides the detector config's input sizes to detect at (R-CNN families; ``()``: its
    input size alone), ``test_turns`` its quarter turns (``()``: the images as they are).
    The detector's texture check (``detector.texture_check``, where the checkpoint carries the
    textures) runs on every image's detections, which then also hold ``confirmed`` (n,) bool, the
    boxes the texture confirmed; ``texture_check=False`` gives the network's alone.
    ``with_evidence``: each image's detections also hold the check's ``evidence`` (what a
    calibration reads, ``TextureCheck.apply``).

    A detector with several views and a texture check detects in two passes where its
    ``cascade`` says so (:class:`Cascade`) and its config's ``cascade`` is on: every view only for
    the images one view leaves unsure. ``test_sizes`` or ``test_turns`` given, ``every_view``, the
    config's ``cascade`` off, or ``detector.cascade`` None: the views asked for, in one pass.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be at least 1, got {batch_size}")
    others = sorted(set(member_families(detector)) - set(RCNN_FAMILIES))
    if test_sizes is not None and others:
        raise ValueError(f"test_sizes: only the R-CNN families detect at several sizes, not {', '.join(others)}")
    if test_turns is not None and others:
        raise ValueError(f"test_turns: only the R-CNN families detect on turned views, not {', '.join(others)}")
    model = detector.model
    model.eval()
    checker = detector.texture_check() if texture_check else None
    sizes = tuple(getattr(model, "test_sizes", ()))
    # Views asked for, every view, or no check to tell sure from unsure: one pass.
    asked = checker is None or every_view or test_sizes is not None or test_turns is not None
    cascade = None if asked else detector.active_cascade()
    # The model's own views run through the runtime graph where the detector has one (the same
    # detections as torch's), opened only once they are needed; views asked for, and the
    # cascade's first view, run in torch.
    own_views = test_sizes is None and test_turns is None

    def at_own_views(arrays: list[np.ndarray], tensors: list[torch.Tensor]) -> list[dict[str, np.ndarray]]:
        runtime = detector.runtime if own_views else None
        if runtime is not None:
            return [runtime.detect(array) for array in arrays]
        return [_found(output) for output in _by_shape(model, tensors)]

    results: list[dict[str, np.ndarray]] = []
    threads = int(detector.meta.get("config", {}).get("num_threads", 0))
    with torch.no_grad(), torch_threads(threads), _test_views(model, test_sizes, test_turns):
        for start in range(0, len(images), batch_size):
            arrays = [_image_array(image, start + i) for i, image in enumerate(images[start : start + batch_size])]
            cache = getattr(model, "proposal_cache", None)
            if cache is not None:
                # Fast R-CNN: fill the proposal cache from files beside the images when present.
                for array, path in arrays:
                    cache.proposals(array, path)
            tensors = [
                torch.from_numpy(array).to(detector.device).permute(2, 0, 1).float().div_(255) for array, _ in arrays
            ]
            if cascade is None:
                for (array, _), found in zip(arrays, at_own_views([array for array, _ in arrays], tensors)):
                    results.append(
                        checker.apply(array, found, with_evidence=with_evidence) if checker is not None else found
                    )
            else:
                first_size = cascade.first_size(sizes)
                # The image's keypoints are found on a thread of their own while one view runs:
                # neither keeps 2 cores busy alone (bench/README.md, "Detection's speed against its accuracy").
                with ThreadPoolExecutor(1) as keypoints:
                    pending = [keypoints.submit(checker.matches, array) for array, _ in arrays]
                    with _test_views(model, () if first_size is None else (first_size,), ()):
                        first = _by_shape(model, tensors)
                    matches = [found.result() for found in pending]
                checked = [
                    checker.apply(array, _found(output), with_evidence=with_evidence, matches=found)
                    for (array, _), output, found in zip(arrays, first, matches)
                ]
                again = [index for index, found in enumerate(checked) if cascade.again(found)]
                if again:
                    found_again = at_own_views(
                        [arrays[index][0] for index in again], [tensors[index] for index in again]
                    )
                    for index, found in zip(again, found_again):
                        checked[index] = checker.apply(
                            arrays[index][0], found, with_evidence=with_evidence, matches=matches[index]
                        )
                results.extend(checked)
            if on_batch is not None:
                on_batch(len(results))
    return results


def _by_shape(model: nn.Module, tensors: list[torch.Tensor]) -> list[Mapping[str, torch.Tensor]]:
    """``model(tensors)``, one forward pass per image shape, outputs in the tensors' order.

    torchvision pads a batch to its largest image, and the padding moves the features near an
    image's edges: an image batched beside one of another size would get other boxes and scores
    than alone. Images of one shape are padded alike, so each image's detections depend on it alone.
    """
    groups: dict[tuple[int, ...], list[int]] = {}
    for index, tensor in enumerate(tensors):
        groups.setdefault(tuple(tensor.shape), []).append(index)
    outputs: list[Mapping[str, torch.Tensor]] = [{} for _ in tensors]
    for indices in groups.values():
        for index, output in zip(indices, model([tensors[index] for index in indices])):
            outputs[index] = output
    return outputs


def _found(output: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """A model's detections on one image as ``detect_object`` gives them (numpy, 0-based labels)."""
    return {
        "boxes": output["boxes"].detach().cpu().numpy().astype(np.float32).reshape(-1, 4),
        "scores": output["scores"].detach().cpu().numpy().astype(np.float32),
        "labels": output["labels"].detach().cpu().numpy().astype(np.int64) - 1,
    }


def detection_records(
    found: dict[str, np.ndarray], classes: Sequence[str], score_threshold: float = 0.0
) -> list[dict[str, Any]]:
    """One image's detections at or above ``score_threshold`` as JSON-able records, best first:
    ``box`` [x0, y0, x1, y1] in the image's pixels (2 decimals), ``class``, ``label`` (its index),
    ``score`` and ``confirmed`` (whether the texture check confirmed it; None without a check)."""
    confirmed = found.get("confirmed")
    return [
        {
            "box": [round(float(v), 2) for v in found["boxes"][i]],
            "class": str(classes[int(found["labels"][i])]) if 0 <= int(found["labels"][i]) < len(classes) else None,
            "label": int(found["labels"][i]),
            "score": float(found["scores"][i]),
            "confirmed": None if confirmed is None else bool(confirmed[i]),
        }
        for i in np.flatnonzero(found["scores"] >= score_threshold)
    ]


def detect_ensemble(
    detectors: Sequence[Detector],
    images: Sequence[np.ndarray | str | Path],
    on_batch: Callable[[int], None] | None = None,
    **options: Any,
) -> list[dict[str, np.ndarray]]:
    """Several detectors of one class list detecting as one (an ensemble, e.g. the final models of
    two runs with other seeds): ``detect_object`` (with ``options``: batch_size, test_sizes,
    test_turns) on :func:`combine_detectors`. Two runs of ``quick.yaml`` (seeds 0 and 1) merged
    scored 0.01-0.06 more on each out-of-domain set than either alone (bench/README.md,
    "... and seed ensembles")."""
    return detect_object(combine_detectors(detectors), images, on_batch=on_batch, **options)
