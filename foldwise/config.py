"""The experiment configuration: one YAML file, validated before any work starts.

Every section forbids unknown keys, so a typo fails with the key's dotted path instead of
being ignored. ``load_config`` raises :class:`ConfigError` naming the offending key.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from foldwise.conditions import load_condition_table
from foldwise.documents import DocumentError, check_nesting, load_yaml


class ConfigError(ValueError):
    """An experiment configuration that cannot run; the message names the bad key."""


# Upper bounds on what a config may ask for: a config is a request for work, and a slip of the
# keyboard (10**9 images per increment) must be an error at once, not a job that never ends.
MAX_IMAGES_PER_INCREMENT = 100_000
MAX_ITERATIONS = 1_000_000
MAX_WINDOW = 1_000
MAX_INCREMENTS = 10_000
MAX_TEST_IMAGES_PER_STAGE = 100_000
MAX_BATCH = 4_096
# Past these a run only diverges or does nothing: SGD at a learning rate above 10, a weight
# decay above 1 (shrinking weights by more than the step), a gradient clip that clips nothing.
MAX_LEARNING_RATE = 10.0
MAX_WEIGHT_DECAY = 1.0
MAX_GRAD_CLIP_NORM = 1e6
# Conditions one mixed image draws at once (foldwise.sampling); more is a clutter of effects.
MAX_CONDITIONS_PER_IMAGE = 9
# Control characters (NUL above all) in a text field: PostgreSQL refuses NUL in text, and
# no name or path needs any of them; nor the C1 controls, nor the bidirectional overrides and
# isolates, which make a name display as another (U+202E turns "gpj.exe" around).
CONTROL_CHARACTERS = re.compile(r"[\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]")
# JSON's "\ud800" decodes to half a UTF-16 pair, which no file system or database can store.
LONE_SURROGATES = re.compile(r"[\ud800-\udfff]")


class _Section(BaseModel):
    # inf/nan have no place in a config, and PostgreSQL's JSON columns cannot store them.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _strict_numbers_and_clean_text(cls, value: Any, info: ValidationInfo) -> Any:
        """Numbers are numbers: pydantic would read `true` as 1, "50" as 50 and 50.0 as a count
        of 50. Text holds no control characters."""
        annotation = cls.model_fields[info.field_name].annotation
        if get_origin(annotation) in (tuple, list) and isinstance(value, (list, tuple)):
            element_types = {t for argument in get_args(annotation) for t in _scalar_types(argument)}
            for index, element in enumerate(value):
                _check_number(element, element_types, f"[{index}]: ")
        else:
            _check_number(value, _scalar_types(annotation), "")
        if isinstance(value, str) and CONTROL_CHARACTERS.search(value):
            raise ValueError(f"control character {CONTROL_CHARACTERS.search(value).group()!r} in text")
        if isinstance(value, str) and LONE_SURROGATES.search(value):
            raise ValueError(f"text is not valid Unicode (lone surrogate {LONE_SURROGATES.search(value).group()!r})")
        return value


def _scalar_types(annotation: Any) -> set[Any]:
    """The types an annotation admits at its top level (int | None -> {int, NoneType})."""
    arguments = get_args(annotation)
    if get_origin(annotation) is Annotated:
        return _scalar_types(arguments[0])
    if get_origin(annotation) in (Union, UnionType):
        return {t for argument in arguments for t in _scalar_types(argument)}
    return {annotation}


def _check_number(value: Any, types: set[Any], where: str) -> None:
    """Refuse a value of the wrong kind for a field that takes numbers (and no text)."""
    if not types & {int, float} or types & {str, Path}:
        return
    if isinstance(value, bool) and bool not in types:
        raise ValueError(f"{where}expected a number, got a boolean")
    if isinstance(value, str):
        raise ValueError(f"{where}expected a number, got the text {value!r}")
    if isinstance(value, float) and float not in types:
        raise ValueError(f"{where}expected a whole number, got {value!r}")


class AssetsConfig(_Section):
    """Where object textures, backgrounds and occluders come from (None: built-in defaults)."""

    objects: Path | None = None
    backgrounds: Path | None = None
    occluders: Path | None = None
    # Printed sheets of the objects' kind that are none of them (the user's other forms or
    # covers): one or two lie beside the targets in every render, and the detector's texture
    # check carries them, so neither the network nor the check takes them for an object.
    lookalikes: Path | None = None
    # How many of the built-in object textures to use as classes (the paper uses 5).
    n_objects: int = Field(default=5, ge=1, le=5)


class RenderConfig(_Section):
    backend: Literal["raster", "blender"] = "raster"
    # Interpolated rulings per guiding ruling: 1 gives the paper's sharp creases (2 rulings,
    # 3 regions), 3 smooth bends (7 regions); None: the condition table's canonical value.
    smooth_steps: int | None = Field(default=None, ge=1, le=16)
    image_size: int = Field(default=128, ge=32, le=2048)
    # Cycles samples per pixel and device for the blender backend.
    samples: int = Field(default=16, ge=1, le=4096)
    device: Literal["CPU", "GPU"] = "CPU"
    # How many times a rejected θ (self-intersecting sheet, invisible target) is redrawn.
    max_resamples: int = Field(default=20, ge=0, le=1000)
    # θ per render task: larger batches amortise task overhead, smaller ones spread better.
    batch_size: int = Field(default=8, ge=1, le=1000)
    # A run that lost more than this share of its images (every resample rejected, or the
    # worker raised) fails instead of reporting `finished` on what was left.
    max_failed_share: float = Field(
        default=0.1, ge=0.0, le=1.0, description="share of failed images above which the experiment fails"
    )


class StageOverrides(_Section):
    """Active-learning settings a mixed stage uses instead of the experiment's own."""

    m: int | None = Field(default=None, ge=1, le=MAX_IMAGES_PER_INCREMENT)
    t: int | None = Field(default=None, ge=1, le=MAX_ITERATIONS)
    M: int | None = Field(default=None, ge=1, le=MAX_WINDOW)
    N: int | None = Field(default=None, ge=1, le=MAX_WINDOW)
    tau: float | None = Field(default=None, ge=0.0, le=1.0)
    max_increments: int | None = Field(default=None, ge=1, le=MAX_INCREMENTS)
    training_set: Literal["reset", "grow"] | None = None


ConditionsPerImage = Annotated[int, Field(ge=1, le=MAX_CONDITIONS_PER_IMAGE)]


class MixedStageConfig(_Section):
    """The mixed stage(s) that end a curriculum: each image draws several conditions at
    random difficulties up to the stage's (the paper's future work; foldwise.sampling)."""

    # One mixed stage per difficulty listed, in this order, after every single-condition stage.
    difficulties: list[str] = Field(default_factory=lambda: ["hard"], min_length=1)
    # How many conditions each image draws: [low, high], inclusive.
    conditions_per_image: tuple[ConditionsPerImage, ConditionsPerImage] = (2, 4)
    # Which conditions it draws from (empty: every condition of the table).
    draw_from: list[str] = Field(default_factory=list)
    # Conditions every image holds, at a random difficulty, besides the conditions_per_image
    # drawn from the rest: the nuisances a photograph always has (a camera roll, a tilt), which
    # a draw of 2-4 among the whole table gives to one image in six only.
    always: list[str] = Field(default_factory=list)
    # The share of its images that show no object at all.
    negatives: float = Field(default=0.1, ge=0.0, le=0.9)
    # How an increment's images draw their (condition, difficulty) cells: "uniform", every cell
    # alike; "failure", part of the draw (failure_share) in proportion to 1 − AP of the latest
    # scored model on each cell of the standard test set (foldwise.sampling.cell_probabilities).
    sampling: Literal["uniform", "failure"] = "uniform"
    failure_share: float = Field(default=0.5, ge=0.0, le=1.0)
    # m, t, M, N, tau, max_increments for the mixed stages (unset: the experiment's).
    active_learning: StageOverrides = StageOverrides()

    @model_validator(mode="after")
    def _known(self) -> MixedStageConfig:
        table = load_condition_table()
        low, high = self.conditions_per_image
        if not 1 <= low <= high:
            raise ValueError(f"conditions_per_image: needs 1 <= low <= high, got {list(self.conditions_per_image)}")
        pool = self.draw_from or list(table.codes)
        for i, code in enumerate(self.draw_from):
            if code not in table.conditions:
                raise ValueError(f"draw_from[{i}]: unknown condition {code!r}; known: {', '.join(table.codes)}")
        if len(set(self.draw_from)) != len(self.draw_from):
            # An image draws distinct entries: a condition listed twice could appear twice in one image.
            raise ValueError("draw_from: a condition is listed twice")
        for i, code in enumerate(self.always):
            if code not in table.conditions:
                raise ValueError(f"always[{i}]: unknown condition {code!r}; known: {', '.join(table.codes)}")
        if len(set(self.always)) != len(self.always):
            raise ValueError("always: a condition is listed twice")
        if self.draw_from and set(self.always) - set(self.draw_from):
            # draw_from names what a mixed image may show; a held condition outside it contradicts it.
            outside = sorted(set(self.always) - set(self.draw_from))
            raise ValueError(f"always: {outside} not in draw_from ({', '.join(self.draw_from)})")
        pool = [code for code in pool if code not in self.always]
        if high > len(pool):
            raise ValueError(
                f"conditions_per_image: {high} conditions per image, but only {len(pool)} to draw from"
                + (f" besides always ({', '.join(self.always)})" if self.always else "")
            )
        if len(set(self.difficulties)) != len(self.difficulties):
            # Two mixed stages of one difficulty would draw the same test set twice.
            raise ValueError("difficulties: a difficulty is listed twice")
        for i, difficulty in enumerate(self.difficulties):
            if difficulty not in table.difficulties:
                raise ValueError(
                    f"difficulties[{i}]: unknown difficulty {difficulty!r}; known: {', '.join(table.difficulties)}"
                )
        return self

    def draw(self):
        from foldwise.sampling import MixedDraw

        return MixedDraw(
            tuple(self.conditions_per_image),
            tuple(self.draw_from),
            self.negatives,
            tuple(self.always),
            failure_share=self.failure_share,
        )


class CurriculumConfig(_Section):
    conditions: list[str] = Field(default_factory=lambda: ["fb", "mb", "po", "de", "eo", "sc", "li"], min_length=1)
    difficulties: list[str] = Field(default_factory=lambda: ["easy", "medium", "hard"], min_length=1)
    # Stages of several conditions at once after the single-condition ones (None: none).
    mixed: MixedStageConfig | None = None
    # One stage per (condition, difficulty) before the mixed stages, as the paper's Algorithm 1.
    # false: the mixed stages alone train (they need curriculum.mixed); conditions × difficulties
    # still make the standard test set, so P keeps measuring every condition.
    single_condition_stages: bool = True

    @model_validator(mode="after")
    def _known(self) -> CurriculumConfig:
        table = load_condition_table()
        for i, code in enumerate(self.conditions):
            if code not in table.conditions:
                raise ValueError(f"conditions[{i}]: unknown condition {code!r}; known: {', '.join(table.codes)}")
        for i, difficulty in enumerate(self.difficulties):
            if difficulty not in table.difficulties:
                raise ValueError(
                    f"difficulties[{i}]: unknown difficulty {difficulty!r}; known: {', '.join(table.difficulties)}"
                )
        if len(set(self.conditions)) != len(self.conditions):
            raise ValueError("conditions: a condition is listed twice")
        if len(set(self.difficulties)) != len(self.difficulties):
            raise ValueError("difficulties: a difficulty is listed twice")
        if not self.single_condition_stages and self.mixed is None:
            raise ValueError("single_condition_stages: false leaves no stage to train without curriculum.mixed")
        return self


class TestSetConfig(_Section):
    # n: standard test images per (condition, difficulty); the paper has 30 per object.
    per_stage: int = Field(default=150, ge=1, le=MAX_TEST_IMAGES_PER_STAGE)
    # Which (condition, difficulty) pairs the standard test set covers: the paper's Table 3
    # ("table3", its 7 conditions), every condition of the table ("all"), or only the
    # curriculum's stages ("curriculum", mixed stages included; for kind: canonical_baseline,
    # the curriculum's conditions × difficulties).
    covers: Literal["table3", "all", "curriculum"] = "curriculum"
    # The user's labelled photographs (a COCO or Pascal VOC export, as `foldwise evaluate` reads;
    # the detector's classes named as the objects' files): every increment is scored on them too.
    photographs: Path | None = None
    # "beside": P stays the renders' score and the photographs' is recorded next to it
    # (evaluations.details.photographs); "standard": the photographs are the standard test set,
    # so P, the stopping rule and each stage's best model read them.
    photographs_role: Literal["beside", "standard"] = "beside"

    @model_validator(mode="after")
    def _role_needs_photographs(self) -> TestSetConfig:
        if self.photographs is None and self.photographs_role != "beside":
            raise ValueError("photographs_role: standard needs test_set.photographs, a folder of labelled photographs")
        return self


class ActiveLearningConfig(_Section):
    m: int = Field(default=50, ge=1, le=MAX_IMAGES_PER_INCREMENT, description="training images per increment")
    t: int = Field(default=1000, ge=1, le=MAX_ITERATIONS, description="training iterations per increment")
    M: int = Field(default=3, ge=1, le=MAX_WINDOW, description="recent window of the stopping rule")
    N: int = Field(default=8, ge=1, le=MAX_WINDOW, description="earlier window of the stopping rule")
    tau: float = Field(default=0.02, ge=0.0, le=1.0, description="plateau threshold on |P_M - P_N|")
    max_increments: int = Field(default=40, ge=1, le=MAX_INCREMENTS, description="cap on increments per stage")
    training_set: Literal["reset", "grow"] = "reset"


class LearnabilityConfig(_Section):
    """Algorithm 2 (paper §4.3, §5.2): how well each condition can be learned.

    Every (condition, difficulty) trains exactly ``kappa`` increments, with no stopping rule, so
    that every difficulty of every condition gets the same κ·t iterations (a fair comparison).
    Each model is scored on its own condition's test set (its n images per difficulty), and a
    difficulty starts from the LAST model ω_κ of the difficulty before it, not the best.

    Which model each condition's FIRST difficulty starts from (``start``); either way every
    condition starts from the same model, as in §5.2, where every detector "was initialized
    with the pre-trained models available for them": the conditions are then independent, and
    neither their order in the curriculum nor a condition trained before them changes their
    scores. (Algorithm 2's pseudo-code never resets ω_in between conditions; followed
    literally, each condition would inherit every earlier one's training and the order of C
    would bias the comparison that the algorithm exists to make.)

    * ``initial`` (the default): the detector's initial weights (ImageNet when
      ``detector.pretrained: imagenet``, else random).
    * ``canonical``: the last model of one shared canonical stage, trained first (condition
      and difficulty ``canonical``, as the canonical_baseline kind's one stage) for
      ``canonical_increments`` increments and scored on the whole test set. The paper's
      detectors already see objects when a condition's first stage begins (ImageNet
      pretraining); from random weights every easy stage instead spends its κ increments
      learning the objects themselves and scores near 0, so only the medium and hard stages
      tell the conditions apart. A detector that already knows the objects on canonical images
      is the offline analogue of that pretrained start: each condition then measures how the
      condition itself is learned. The canonical stage is not a condition: it has no place in
      the learnability order.

    An increment's m, t and training_set come from ``active_learning``, as in Algorithm 1 (the
    canonical stage's too); its stopping-rule keys (M, N, tau, max_increments) have no meaning
    here and are refused.
    """

    kappa: int = Field(default=10, ge=1, le=MAX_INCREMENTS, description="increments per (condition, difficulty): κ")
    start: Literal["initial", "canonical"] = Field(
        default="initial", description="what each condition's first difficulty starts from"
    )
    canonical_increments: int | None = Field(
        default=None, ge=1, le=MAX_INCREMENTS, description="increments of the shared canonical stage (start: canonical)"
    )


class CanonicalBaselineConfig(_Section):
    """The paper's Table 2 (§3.2): one detector trained on canonical images only, then scored on
    every (condition, difficulty) of the test set, which tells the conditions that hurt it.

    One stage of ``increments`` increments on canonical θ (every condition at its canonical
    value), with no stopping rule: the paper trains for a fixed number of iterations (20,000 on
    2,500 images), and choosing the model by its test score would fit the test set. The
    curriculum's conditions and difficulties are not trained: they name what the test set
    covers (``test_set.covers: curriculum``; ``all`` scores every condition of the table, those
    outside the paper's curriculum included, as its Table 2 does), and the table reads the LAST
    model's scores.

    An increment's m, t and training_set come from ``active_learning``, as in Algorithm 1 (with
    ``grow`` the canonical set grows each increment, closest to the paper's one fixed set); its
    stopping-rule keys (M, N, tau, max_increments) have no meaning here and are refused.
    """

    increments: int = Field(default=10, ge=1, le=MAX_INCREMENTS, description="increments of the canonical stage")


# Keys of `active_learning` that only the stopping rule of Algorithm 1 reads.
STOPPING_RULE_KEYS = ("M", "N", "tau", "max_increments")


class AugmentationConfig(_Section):
    """Train-time augmentation (workers/train/augment.py): the probability of each transform
    per image per step. Off by default: the paper trains without augmentation."""

    enabled: bool = False
    quarter_turn: float = Field(
        default=0.0, ge=0.0, le=1.0, description="a turn by 90, 180 or 270 degrees, frame and boxes with it (exact)"
    )
    zoom: float = Field(
        default=0.0,
        ge=0.0,
        le=1.0,
        description="object zoom: one target spans 35-150% of the frame's long side (cut by the frame when larger)",
    )
    crop: float = Field(
        default=0.5, ge=0.0, le=1.0, description="random crop: 35-100% of the area, aspect 9:16 to 16:9, not distorted"
    )
    photometric: float = Field(default=0.5, ge=0.0, le=1.0, description="brightness, contrast, saturation, hue")
    grayscale: float = Field(default=0.05, ge=0.0, le=1.0)
    blur: float = Field(default=0.1, ge=0.0, le=1.0, description="Gaussian blur, sigma 0.3-1.5 px")
    noise: float = Field(default=0.2, ge=0.0, le=1.0, description="Gaussian noise, sigma 3% of full scale")
    jpeg: float = Field(default=0.2, ge=0.0, le=1.0, description="JPEG at quality 20-90")


# Input sizes (longer side, px) detector.test_sizes accepts: the config and the command-line parser.
MIN_TEST_SIZE, MAX_TEST_SIZE = 32, 2048


class DetectorConfig(_Section):
    family: Literal["faster_rcnn", "fast_rcnn", "yolo"] = "faster_rcnn"
    backbone: str = "mobilenet_v3_large_fpn"
    input_size: int = Field(default=128, ge=32, le=2048)
    # none: random initialisation; imagenet: torchvision's classifier from the torch hub cache;
    # coco: the COCO-trained MobileNetV3 that ships with foldwise (backbone mobilenet_v3_large_075_fpn).
    pretrained: Literal["none", "imagenet", "coco"] = "none"
    # Backbone stages that train, counted from the last (torchvision's trainable_backbone_layers):
    # none = 3 with pretrained weights, all from random ones; 0 keeps the whole backbone frozen.
    trainable_backbone_stages: int | None = Field(default=None, ge=0, le=6)
    batch_size: int = Field(default=4, ge=1, le=512)
    learning_rate: float = Field(default=0.01, gt=0, le=MAX_LEARNING_RATE)
    momentum: float = Field(default=0.9, ge=0, lt=1)
    weight_decay: float = Field(default=1e-4, ge=0, le=MAX_WEIGHT_DECAY)
    # Non-finite losses tolerated (each skipped, learning rate lowered) before the task fails.
    max_nonfinite_steps: int = Field(default=5, ge=0, le=MAX_ITERATIONS)
    device: Literal["auto", "cpu", "cuda"] = "auto"
    # Torch intra-op threads; 0 lets torch choose.
    num_threads: int = Field(default=0, ge=0, le=1024)
    # Learning-rate schedule of one train_detector call: linear warm-up from 0.1% over
    # warmup_iterations, then constant or a cosine decay to min_lr_fraction × learning_rate.
    warmup_iterations: int = Field(default=50, ge=0, le=MAX_ITERATIONS)
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    min_lr_fraction: float = Field(default=0.05, ge=0.0, le=1.0)
    # Gradient norm clip (0 disables); random initialisation is unstable without it.
    grad_clip_norm: float = Field(default=10.0, ge=0.0, le=MAX_GRAD_CLIP_NORM)
    # R-CNN anchors (and proposal scale) span this range, as fractions of input_size:
    # at 128 px, 10 px objects up to the whole image.
    anchor_size_range: tuple[float, float] = (0.08, 1.0)
    # Channels of the R-CNN feature pyramid (torchvision: 256; RoIAlign's CPU backward and
    # the box head scale with it).
    fpn_channels: int = Field(default=128, ge=8, le=1024)
    # Width of the R-CNN box head's two fully connected layers (torchvision: 1024).
    representation_size: int = Field(default=256, ge=8, le=4096)
    # RPN proposals kept per image after NMS (torchvision's COCO values: 2000 / 1000).
    rpn_proposals_train: int = Field(default=300, ge=1, le=10_000)
    rpn_proposals_test: int = Field(default=100, ge=1, le=10_000)
    # RoIs sampled per image for the box head's loss (torchvision: 512).
    roi_samples_per_image: int = Field(default=64, ge=1, le=MAX_BATCH)
    # Edge Boxes proposals per image for the fast_rcnn family (the whole-image box included).
    edge_boxes: int = Field(default=200, ge=1, le=5000)
    # Detections returned per image, and the score below which none is returned.
    detections_per_image: int = Field(default=20, ge=1, le=1_000)
    box_score_threshold: float = Field(default=0.05, ge=0.0, lt=1.0)
    # Detection at several input sizes (longer side, px), merged by per-class NMS (R-CNN
    # families; each size costs a full inference): a sheet too small to find at input_size is
    # found at a larger one. Empty: input_size alone. Training always runs at input_size.
    test_sizes: tuple[Annotated[int, Field(ge=MIN_TEST_SIZE, le=MAX_TEST_SIZE)], ...] = Field(default=(), max_length=8)
    # Detection also on the image turned by these quarter turns (1: 90° counter-clockwise, 2, 3;
    # 0: as it is), at every test size, all merged the same way (R-CNN families; each turn costs
    # the sizes' inference again): the wild's camera has any roll, and one of the four views
    # brings any sheet within 45° of upright. Empty: the image as it is.
    test_turns: tuple[Literal[0, 1, 2, 3], ...] = Field(default=(), max_length=4)
    # How those views' boxes merge (R-CNN families). None: per-class NMS, a box keeps the best
    # score any view gave it. A fraction α: the views vote, a box scoring 1 − Π_views (1 − α·s),
    # s each view's best score for it, so a sheet most views find outranks clutter one view is
    # sure of (an ensemble's members then combine by the same rule at α = 1, so two detectors
    # score as one whose views all voted). One view alone keeps its scores.
    view_vote: float | None = Field(default=None, gt=0.0, le=1.0)
    # Each detection checked against its class's texture (SIFT matches, an affine map fitted by
    # RANSAC, workers/train/texture_check.py): a box the texture confirms takes the texture's
    # mapped outline as its box (a piece of a sheet becomes the whole) and ranks above the paper's
    # 0.8 cut and every box without such evidence; a box matching another class's texture is
    # renamed. The checkpoint then carries the textures. Off: the network's scores alone (the
    # paper has no such step).
    texture_check: bool = False
    # With the texture check, the texture also searches the whole image for sheets the network
    # gave no box for (SIFT matches of each class fitted by RANSAC, one sheet after another): each
    # sheet found is a detection confirmed as the check confirms one. Off: only the network's
    # boxes are checked.
    texture_search: bool = False
    # How the texture check scores each detection. ``tiers``: boxes the texture confirmed score
    # 0.9 or more, the others keep their side of the 0.8 cut. ``shipped``: the score is the chance
    # the box is true, read from the network's score and the texture's evidence by the calibration
    # foldwise ships (workers/train/calibration.json, fitted by bench/calibrate.py on one half of
    # its out-of-domain sets), recorded in every checkpoint trained with it. `foldwise calibrate`
    # fits one on your own labelled photographs instead.
    calibration: Literal["tiers", "shipped"] = "tiers"
    # With several views and the texture check, detection runs in two passes: one view (the
    # largest test size, upright) and the check first, every view only for images where the
    # texture confirmed nothing (bench/README.md, "Detection's speed against its accuracy"). Off:
    # every view on every image (`foldwise detect --every-view` for one call).
    cascade: bool = True
    augmentation: AugmentationConfig = AugmentationConfig()

    @model_validator(mode="after")
    def _buildable(self) -> DetectorConfig:
        from foldwise.weights import backbone_problem, pretrained_problem

        if problem := backbone_problem(self.family, self.backbone) or pretrained_problem(
            self.family, self.backbone, self.pretrained
        ):
            raise ValueError(problem.removeprefix("detector."))
        if self.family == "yolo" and self.trainable_backbone_stages is not None:
            raise ValueError(
                "trainable_backbone_stages: only read by the R-CNN families (yolo trains its whole backbone)"
            )
        if self.family == "yolo" and self.test_sizes:
            raise ValueError("test_sizes: only read by the R-CNN families (yolo letterboxes into input_size)")
        if self.family == "yolo" and self.test_turns:
            raise ValueError("test_turns: only read by the R-CNN families")
        if self.texture_search and not self.texture_check:
            raise ValueError("texture_search: searches with the texture check's textures; set texture_check: true too")
        if self.calibration != "tiers" and not self.texture_check:
            raise ValueError("calibration: calibrates the texture check's scores; set texture_check: true too")
        if self.family == "yolo" and self.view_vote is not None:
            raise ValueError("view_vote: only read by the R-CNN families (yolo detects at one view)")
        return self

    @field_validator("test_sizes", "test_turns")
    @classmethod
    def _distinct_views(cls, value: tuple[int, ...], info: ValidationInfo) -> tuple[int, ...]:
        if len(set(value)) != len(value):
            raise ValueError(f"{info.field_name.removeprefix('test_')} repeat: {list(value)}")
        return value

    @field_validator("anchor_size_range")
    @classmethod
    def _anchor_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not 0 < low < high <= 4:
            raise ValueError(f"must be two fractions of input_size with 0 < low < high <= 4, got {list(value)}")
        return value


def view_count(test_sizes: Sequence[int], test_turns: Sequence[int]) -> int:
    """How many views a detector runs at these sizes and turns (empty: its one size, upright)."""
    return max(len(test_sizes), 1) * max(len(test_turns), 1)


def _parse_view_list(text: str, field: str, what: str) -> tuple[int, ...]:
    """``text`` (comma-separated whole numbers) as ``DetectorConfig.<field>``, checked as the
    config checks it; a ValueError says ``what`` the list must be and what is wrong."""
    try:
        values = [int(value) for value in text.split(",")]
    except ValueError:
        raise ValueError(f"{text!r}: a comma list of {what} (not whole numbers)") from None
    try:
        return getattr(DetectorConfig(**{field: values}), field)
    except ValidationError as error:
        problem = error.errors()[0]["msg"]
        raise ValueError(f"{text!r}: a comma list of {what} ({problem})") from None


def parse_test_sizes(text: str) -> tuple[int, ...]:
    """``"128,256"`` as ``detector.test_sizes`` (for command-line options); a ValueError names what is wrong."""
    return _parse_view_list(text, "test_sizes", f"distinct input sizes, {MIN_TEST_SIZE} to {MAX_TEST_SIZE} px")


def parse_test_turns(text: str) -> tuple[int, ...]:
    """``"0,1,2,3"`` as ``detector.test_turns`` (for command-line options); a ValueError names what is wrong."""
    return _parse_view_list(text, "test_turns", "distinct quarter turns, 0 to 3")


class EvaluationConfig(_Section):
    score_threshold: float = Field(default=0.8, ge=0.0, le=1.0, description="the paper's confidence cut")
    iou_threshold: float = Field(default=0.5, gt=0.0, le=1.0)
    batch_size: int = Field(default=16, ge=1, le=MAX_BATCH)
    # pycocotools' metrics beside the paper's mAP. The stopping rule never reads them, and on a
    # 3,150-image test set they cost ~20 s per increment, against ~1 s for the VOC mAP.
    coco: bool = True
    # The views the loop scores each increment's model at (its P, which the stopping rule reads
    # and the tables show): "detector", those the detector config names (test_sizes × test_turns,
    # as every other caller gets them); "trained", the one view it trained at (input_size,
    # upright), the paper's P. The loop compares models with each other, which one view does at
    # a fraction of the cost: at twelve views the loop's evaluation was 60% of quick.yaml's
    # `make run`. The checkpoint keeps its views; bench/wild.py and `foldwise detect` use them.
    views: Literal["detector", "trained"] = "detector"
    # The score P of each increment that the stopping rule reads and that picks a stage's best
    # model: "map", the paper's mAP at score_threshold; "map_unthresholded", the VOC mAP over every
    # detection. A detector a few hundred iterations old ranks its boxes well long before any
    # scores 0.8: at the cut its P reads 0 and two zeros in a row look like a plateau.
    loop_score: Literal["map", "map_unthresholded"] = "map"


class TaskLimitsConfig(_Section):
    """Time limits per task kind and the delivery cap: a task that hangs or kills its worker on
    every delivery ends as a failure with its reason instead of being redelivered forever."""

    # Soft limits (the task stops and records why); the hard limit, HARD_LIMIT_GRACE_S later,
    # kills a task that ignores the soft one. Render: per θ (a batch gets its θ count times it).
    render_time_limit_s: float = Field(default=600.0, gt=0, le=86_400)
    train_time_limit_s: float = Field(
        default=86_400.0, gt=0, le=30 * 86_400, description="per increment: train + evaluate"
    )
    max_deliveries: int = Field(default=3, ge=1, le=100, description="times a θ or model may start before it fails")


class ExperimentConfig(_Section):
    name: str = Field(min_length=1, max_length=200)
    # active_learning: Algorithm 1 (stopping rule, ω_be opens the next stage); learnability:
    # Algorithm 2 (κ increments per stage, ω_κ opens the next difficulty; see LearnabilityConfig);
    # canonical_baseline: the paper's Table 2 (one canonical stage; see CanonicalBaselineConfig).
    kind: Literal["active_learning", "learnability", "canonical_baseline"] = "active_learning"
    seed: int = Field(default=0, ge=0, lt=2**31)
    assets: AssetsConfig = AssetsConfig()
    render: RenderConfig = RenderConfig()
    curriculum: CurriculumConfig = CurriculumConfig()
    test_set: TestSetConfig = TestSetConfig()
    active_learning: ActiveLearningConfig = ActiveLearningConfig()
    detector: DetectorConfig = DetectorConfig()
    evaluation: EvaluationConfig = EvaluationConfig()
    tasks: TaskLimitsConfig = TaskLimitsConfig()
    learnability: LearnabilityConfig = LearnabilityConfig()
    canonical_baseline: CanonicalBaselineConfig = CanonicalBaselineConfig()

    @field_validator("name")
    @classmethod
    def _printable(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be blank")
        return value

    @model_validator(mode="after")
    def _kind_fits(self) -> ExperimentConfig:
        """Keys the chosen kind would silently ignore are errors (each message starts with its
        key). A value equal to its default is let through: a stored config holds every key."""
        for section, default in (
            ("learnability", LearnabilityConfig()),
            ("canonical_baseline", CanonicalBaselineConfig()),
        ):
            if self.kind != section and getattr(self, section) != default:
                raise ValueError(f"{section}: only read by kind: {section} (this config's kind is {self.kind})")
        if self.kind == "active_learning":
            return self
        start = self.learnability.start
        if start == "initial" and self.learnability.canonical_increments is not None:
            raise ValueError(
                "learnability.canonical_increments: only read with learnability.start: canonical "
                "(start: initial trains no canonical stage)"
            )
        if start == "canonical" and self.learnability.canonical_increments is None:
            raise ValueError(
                "learnability.canonical_increments: learnability.start: canonical needs the canonical stage's "
                "number of increments"
            )
        if self.curriculum.mixed is not None:
            why = {
                "learnability": "it measures one condition at a time",
                "canonical_baseline": "it trains on canonical images only; its test set is set by curriculum.conditions",
            }[self.kind]
            raise ValueError(f"curriculum.mixed: kind: {self.kind} has no mixed stage ({why})")
        if self.kind == "learnability" and self.test_set.covers != "curriculum":
            raise ValueError(
                f"test_set.covers: kind: learnability tests each condition on its own test set; "
                f"it must be 'curriculum', got {self.test_set.covers!r}"
            )
        sets_increments = "learnability.kappa" if self.kind == "learnability" else "canonical_baseline.increments"
        defaults = ActiveLearningConfig()
        for key in STOPPING_RULE_KEYS:
            if getattr(self.active_learning, key) != getattr(defaults, key):
                raise ValueError(
                    f"active_learning.{key}: kind: {self.kind} has no stopping rule; "
                    f"{sets_increments} sets the increments per stage"
                )
        return self

    def stage_increments_cap(self, condition: str) -> int:
        """The most increments a stage of ``condition`` trains: κ for learnability (its canonical
        stage: canonical_increments), the fixed count for the canonical baseline, else the cap."""
        from foldwise.theta import CANONICAL

        if self.kind == "learnability" and condition == CANONICAL:
            return self.learnability.canonical_increments
        if self.kind == "learnability":
            return self.learnability.kappa
        if self.kind == "canonical_baseline":
            return self.canonical_baseline.increments
        return self.stage_active_learning(condition).max_increments

    def stage_order(self) -> list[tuple[str, str]]:
        """(condition, difficulty) in curriculum order: for c in C, for δ in Δ; then the mixed
        stages ("mixed", δ). The canonical baseline has one stage, ("canonical", "canonical"):
        its images vary no condition, as a canonical θ's difficulty says; a learnability
        experiment with ``start: canonical`` trains that stage before every condition."""
        from foldwise.theta import CANONICAL, MIXED

        if self.kind == "canonical_baseline":
            return [(CANONICAL, CANONICAL)]
        stages = [(c, d) for c in self.curriculum.conditions for d in self.curriculum.difficulties]
        if not self.curriculum.single_condition_stages:
            stages = []
        if self.starts_from_canonical:
            stages.insert(0, (CANONICAL, CANONICAL))
        if self.curriculum.mixed is not None:
            stages += [(MIXED, d) for d in self.curriculum.mixed.difficulties]
        return stages

    def test_pairs(self) -> list[tuple[str, str]]:
        """The (condition, difficulty) pairs of the standard test set."""
        if self.test_set.covers == "curriculum" and (self.kind == "canonical_baseline" or self.starts_from_canonical):
            # A canonical stage trains no condition: the curriculum names the conditions it is scored on.
            return [(c, d) for c in self.curriculum.conditions for d in self.curriculum.difficulties]
        if self.test_set.covers == "curriculum" and not self.curriculum.single_condition_stages:
            # The mixed stages alone train; every (condition, difficulty) is still scored.
            singles = [(c, d) for c in self.curriculum.conditions for d in self.curriculum.difficulties]
            return singles + self.stage_order()
        if self.test_set.covers == "curriculum":
            return self.stage_order()
        table = load_condition_table()
        codes = table.table3 if self.test_set.covers == "table3" else table.codes
        return [(c, d) for c in codes for d in table.difficulties]

    @property
    def starts_from_canonical(self) -> bool:
        """A learnability experiment whose conditions start from a shared canonical stage."""
        return self.kind == "learnability" and self.learnability.start == "canonical"

    def stage_active_learning(self, condition: str) -> ActiveLearningConfig:
        """The active-learning settings of a stage of ``condition`` (a mixed stage's overrides applied)."""
        from foldwise.theta import MIXED

        mixed = self.curriculum.mixed
        if condition != MIXED or mixed is None:
            return self.active_learning
        changes = mixed.active_learning.model_dump(exclude_none=True)
        return self.active_learning.model_copy(update=changes) if changes else self.active_learning

    def mixed_draw(self):
        """How this experiment's mixed θ draw their conditions (foldwise.sampling.MixedDraw)."""
        from foldwise.sampling import MixedDraw

        return self.curriculum.mixed.draw() if self.curriculum.mixed is not None else MixedDraw()


# A message that begins with the dotted key it is about ("active_learning.M: ...").
KEYED_MESSAGE = re.compile(r"^[a-z_]+(\.[A-Za-z_]+)*: ")
# A config error lists at most this many keys (a document of thousands of bad entries is one mistake).
MAX_ERRORS_LISTED = 20


def _format_validation_error(error: ValidationError) -> str:
    lines = []
    for item in error.errors():
        key = ".".join(str(part) for part in item["loc"]) or "(top level)"
        message = item["msg"]
        if item["type"] == "extra_forbidden":
            message = "unknown key"
        elif item["type"] == "value_error":
            message = message.removeprefix("Value error, ")
            # A check across sections (ExperimentConfig._kind_fits) names its key itself.
            if not item["loc"] and KEYED_MESSAGE.match(message):
                lines.append(message)
                continue
        # A message about one element of a list ("[1]: ...") reads as the element's key.
        lines.append(f"{key}{'' if message.startswith('[') else ': '}{message}")
    if len(lines) > MAX_ERRORS_LISTED:
        lines[MAX_ERRORS_LISTED:] = [f"... and {len(lines) - MAX_ERRORS_LISTED} more errors"]
    return "invalid experiment config:\n  " + "\n  ".join(lines)


def parse_config(data: Any) -> ExperimentConfig:
    if not isinstance(data, dict):
        raise ConfigError(f"invalid experiment config: expected a mapping at the top level, got {type(data).__name__}")
    try:
        check_nesting(data)
    except DocumentError as error:
        raise ConfigError(f"invalid experiment config: {error}") from None
    try:
        return ExperimentConfig.model_validate(data)
    except ValidationError as error:
        raise ConfigError(_format_validation_error(error)) from None


def parse_config_text(text: str) -> ExperimentConfig:
    """YAML (or JSON, which is YAML) text to a validated config."""
    try:
        data = load_yaml(text)  # YAML 1.2 scalars (1e-3 is a float), no repeated key, bounded nesting
    except DocumentError as error:
        raise ConfigError(f"invalid experiment config: {error}") from None
    return parse_config(data)


def load_config(path: str | Path) -> ExperimentConfig:
    path = Path(path)
    if not path.is_file():
        what_it_is = "is not a file" if path.exists() else "does not exist"
        raise ConfigError(f"experiment config {str(path)!r} {what_it_is}")
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as error:
        raise ConfigError(f"experiment config {str(path)!r} cannot be read: {error.strerror or error}") from None
    except UnicodeDecodeError as error:
        raise ConfigError(f"experiment config {str(path)!r} is not UTF-8 text (byte {error.start})") from None
    return parse_config_text(text)
