"""Training samples for the confidence forest: balanced per image, from self-generated or ground-truth labels.

Each image contributes as many positive as negative samples (DESIGN section
5): ``n = min(#positives, #negatives, max_per_class)`` of each, drawn without
replacement from its labelled pixels that have a valid query disparity. An
image with only one class contributes nothing.

Deviation, on by default (``band_negatives``, :data:`~selfcontra_ros.confidence.constants.TRAINING`; 0 = the
paper, where unknown pixels are ignored): self labels lend the draw the unlabelled pixels of the query's own
fattening band (:func:`band_negatives`, :class:`BandPrior`) as negatives, except those the band cue
(:mod:`~selfcontra_ros.confidence.band_cue`, ``band_cue``) calls right (and, optionally, those that look like
the object at their disparity rather than the background beyond their drop: ``band_look``, off by default).
Ground-truth labels are used as they are.

:func:`train` is a pure function of its samples and parameters.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from selfcontra_ros.confidence import constants
from selfcontra_ros.confidence.band_cue import FEATURES as BAND_CUE_FEATURES
from selfcontra_ros.confidence.band_cue import band_cue_features, default_band_cue, strip_textures
from selfcontra_ros.confidence.features import FeatureContext, compute_features, feature_names
from selfcontra_ros.confidence.forest import ForestModel, fit_forest
from selfcontra_ros.confidence.kernels import band_look
from selfcontra_ros.errors import SelfContraError
from selfcontra_ros.labeler import LabelerParams
from selfcontra_ros.labels import NEGATIVE, POSITIVE, UNKNOWN
from selfcontra_ros.matching.base import MatcherParams, to_grey
from selfcontra_ros.stages.voting import fattening_band

__all__ = [
    "BAND_KEYS",
    "BandPrior",
    "Samples",
    "TrainParams",
    "balanced_indices",
    "band_labeler",
    "band_look_scores",
    "band_negatives",
    "frame_samples",
    "merge_samples",
    "prior_band",
    "recorded_params",
    "train",
]


@dataclass
class Samples:
    """Training samples of one feature set.

    Attributes:
        feature_set: name of the feature set (``ensemble``, ``gcp``, ``park``).
        features: (N, F) float32 features.
        labels: (N,) bool, True = positive (correct disparity).
        frames: number of images that contributed.
    """

    feature_set: str
    features: NDArray[np.float32]
    labels: NDArray[np.bool_]
    frames: int = 0


@dataclass(frozen=True)
class TrainParams:
    """Forest and metadata of a training run.

    Attributes:
        forest: overrides of :data:`~selfcontra_ros.confidence.constants.FOREST`.
        n_jobs: scikit-learn worker count.
        metadata: extra JSON-serialisable facts stored with the model (sources, query algorithm).
    """

    forest: dict[str, Any] = field(default_factory=dict)
    n_jobs: int | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class BandPrior:
    """How self labels lend training the unlabelled pixels of the query's fattening band (:func:`band_negatives`).

    Attributes:
        share: probability that each unknown band pixel is drawn as a negative (0: the paper, no prior).
        look: band pixels whose look (:func:`band_look_scores`) is at least this are not drawn (``inf``: off).
        cue: band pixels the band cue (:mod:`~selfcontra_ros.confidence.band_cue`) calls right with at least
            this probability are not drawn (``inf``: off).
        texture: band pixels whose thin strip's texture (the band cue's ``strip_texture``, grey levels) is
            below this are not drawn (0: off).
    """

    share: float = float(constants.TRAINING["band_negatives"])
    look: float = float(constants.TRAINING["band_look"])
    cue: float = float(constants.TRAINING["band_cue"])
    texture: float = float(constants.TRAINING["band_texture"])

    def __post_init__(self) -> None:
        if not 0.0 <= self.share <= 1.0:
            raise SelfContraError(f"the band prior's share must be in [0, 1], got {self.share}")
        if math.isnan(self.look):
            raise SelfContraError("the band prior's look must be a number (inf: off), got NaN")
        if not (0.0 <= self.cue <= 1.0 or self.cue == math.inf):
            raise SelfContraError(f"the band prior's cue must be a probability in [0, 1] or inf (off), got {self.cue}")
        if not (math.isfinite(self.texture) and self.texture >= 0):
            raise SelfContraError(f"the band prior's texture must be >= 0 grey levels (0: off), got {self.texture}")

    def metadata(self) -> dict[str, Any]:
        """The prior as a model file records it (JSON: an infinite look or cue, i.e. off, is None)."""
        return {
            "band_negatives": float(self.share),
            "band_look": float(self.look) if math.isfinite(self.look) else None,
            "band_cue": float(self.cue) if math.isfinite(self.cue) else None,
            "band_texture": float(self.texture),
        }

    def apply(
        self,
        label_image: NDArray[np.integer],
        disparity: NDArray[np.floating],
        rng: np.random.Generator,
        *,
        left: NDArray[np.uint8],
        right: NDArray[np.uint8],
        labeler: LabelerParams | None = None,
    ) -> NDArray[np.uint8]:
        """:func:`band_negatives` of ``label_image`` with this prior (``left`` / ``right``: the query's pair)."""
        return band_negatives(
            label_image,
            disparity,
            self.share,
            rng,
            image=left,
            look=self.look,
            labeler=labeler,
            right=right,
            cue=self.cue,
            texture=self.texture,
        )


def balanced_indices(labels: NDArray[np.integer], max_per_class: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices of an equal number of POSITIVE and NEGATIVE entries of ``labels`` (others ignored).

    ``n = min(#positive, #negative, max_per_class)`` of each class, drawn
    without replacement; sorted. Empty when a class is missing.
    """
    labels = np.asarray(labels)
    positive = np.flatnonzero(labels == POSITIVE)
    negative = np.flatnonzero(labels == NEGATIVE)
    n = min(positive.size, negative.size, int(max_per_class))
    if n <= 0:
        return np.zeros(0, dtype=np.int64)
    chosen = np.concatenate([rng.choice(positive, n, replace=False), rng.choice(negative, n, replace=False)])
    return np.sort(chosen).astype(np.int64)


def band_look_scores(
    image: NDArray[np.uint8],
    disparity: NDArray[np.floating],
    band: NDArray[np.bool_],
    rows: NDArray[np.integer],
    cols: NDArray[np.integer],
    *,
    jump_px: float | None = None,
) -> NDArray[np.float32]:
    """The look of band pixels ``(rows, cols)``: like the object at their disparity (> 0) or the background (< 0).

    A fattened pixel is background that carries the foreground's disparity, so it looks like the background
    beyond its disparity drop; a right band pixel looks like the object's interior. The look
    (:func:`~selfcontra_ros.confidence.kernels.band_look`; sizes ``BAND_LOOK_*`` in
    :mod:`~selfcontra_ros.confidence.constants`) is the pixel's grey value (3x3 Gaussian-smoothed) as a
    z-score against the pixels of a 9x49 window more than the labeler's ``stage2_edge_jump_px`` below its
    disparity, minus its z-score against those within 1 px of its disparity outside the band. Where either
    set has fewer than 5 pixels, the same over the next of ``BAND_LOOK_WINDOWS`` (none by default); NaN
    where the last falls short too.

    Args:
        image: HxW grey or HxWx3 RGB left image of the disparity map.
        disparity: HxW query disparity; non-finite or <= 0 is invalid.
        band: HxW fattening band of ``disparity``.
        rows, cols: (N,) band pixels to score (valid disparity).
        jump_px: the band's disparity drop, pixels (the labeler's ``stage2_edge_jump_px``); None: the default's.
    """
    grey = to_grey(np.asarray(image)).astype(np.float32)
    if constants.BAND_LOOK_SMOOTHING > 1:
        size = constants.BAND_LOOK_SMOOTHING
        grey = np.asarray(cv2.GaussianBlur(grey, (size, size), 0), dtype=np.float32)
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    jump = LabelerParams().stage2_edge_jump_px if jump_px is None else float(jump_px)
    look = np.full(rows.size, np.nan, np.float32)
    pending = np.arange(rows.size)
    for window in constants.BAND_LOOK_WINDOWS:
        if pending.size == 0:
            break
        found = band_look(
            grey,
            disparity,
            band,
            rows[pending],
            cols[pending],
            jump=jump,
            window=window,
            min_count=constants.BAND_LOOK_MIN_COUNT,
        )
        look[pending] = found
        pending = pending[np.isnan(found)]
    return look


#: The labeler parameters that shape the fattening band (:func:`~selfcontra_ros.stages.voting.fattening_band`).
BAND_KEYS = ("stage2_edge_jump_px", "stage2_edge_occluded_side_px", "stage2_edge_other_px")
# The band cue's column of the strip's texture (BandPrior.texture).
_STRIP_TEXTURE = BAND_CUE_FEATURES.index("strip_texture")


def band_labeler(recorded: Mapping[str, Any] | None) -> LabelerParams | None:
    """The labeler of a label set, as far as its fattening band goes, from its recorded parameters.

    ``recorded`` is the ``labeler`` section a label folder's or labelled bag's ``metrics.json`` keeps
    (``params.labeler``). Only the :data:`BAND_KEYS` are read, each missing one keeps its default, so that labels
    made by another version of the package (with parameters this one does not know) still train.

    Returns:
        :class:`~selfcontra_ros.labeler.LabelerParams` with the recorded band sizes (others default), or None
        when nothing was recorded.

    Raises:
        SelfContraError: a recorded band size that is not a valid labeler parameter.
    """
    if not isinstance(recorded, Mapping):
        return None
    try:
        return LabelerParams.from_dict({key: recorded[key] for key in BAND_KEYS if key in recorded})
    except (TypeError, ValueError) as exc:
        raise SelfContraError(f"the labels' recorded fattening band is invalid: {exc}") from exc


def recorded_params(recorded: Mapping[str, Any]) -> tuple[MatcherParams | None, LabelerParams | None]:
    """The query algorithm and the labeler's band (:func:`band_labeler`) of a label set's recorded ``params``.

    ``recorded`` is the ``params`` section of a label folder's or labelled bag's ``metrics.json``; either part
    is None where it was not recorded.

    Raises:
        SelfContraError: a recorded band size that is not a valid labeler parameter.
    """
    matcher = recorded.get("matcher")
    return (MatcherParams(**matcher) if isinstance(matcher, dict) else None), band_labeler(recorded.get("labeler"))


def _band_params(labeler: LabelerParams | None) -> LabelerParams:
    """The labeler whose band sizes the band prior uses: ``labeler``, or the defaults for None or no band."""
    return labeler if labeler is not None and labeler.stage2_edge_jump_px > 0 else LabelerParams()


def prior_band(disparity: NDArray[np.floating], labeler: LabelerParams | None = None) -> NDArray[np.bool_]:
    """The fattening band the band prior draws from (:func:`band_negatives`): ``labeler``'s, or the default's.

    Args:
        disparity: HxW query disparity; non-finite or <= 0 is invalid (never in the band).
        labeler: the labeler that made the labels (its ``stage2_edge_*`` sizes); None, or a labeler without a
            band (``stage2_edge_jump_px`` 0), gives the default labeler's band.
    """
    p = _band_params(labeler)
    return fattening_band(
        np.asarray(disparity, dtype=np.float32),
        jump_px=p.stage2_edge_jump_px,
        occluded_side_px=p.stage2_edge_occluded_side_px,
        other_px=p.stage2_edge_other_px,
    )


def band_negatives(
    label_image: NDArray[np.integer],
    disparity: NDArray[np.floating],
    share: float,
    rng: np.random.Generator,
    *,
    image: NDArray[np.uint8] | None = None,
    look: float = float("inf"),
    labeler: LabelerParams | None = None,
    right: NDArray[np.uint8] | None = None,
    cue: float = float("inf"),
    cue_model: ForestModel | None = None,
    texture: float = 0.0,
) -> NDArray[np.uint8]:
    """``label_image`` with the unknown pixels of the query's fattening band drawn as negatives for training.

    The band is the labeler's (:func:`~selfcontra_ros.stages.voting.fattening_band` of ``disparity`` with the
    ``stage2_edge_*`` sizes of the ``labeler`` that made the labels): the foreground side of
    a disparity edge, where a window matcher fattens and where the labeler never gives a positive. The
    consistency test contradicts few of its errors (a fattened point that every nearby view fattens alike is
    confirmed by none and contradicted by none), so a forest trained on the self labels alone almost never
    sees these pixels and learns nothing of the query's most common error. Measured: the band holds half or
    more of SGBM's bad pixels at 4-10x the error rate outside it, on the synthetic scenes (street / orbit /
    room: 48 / 35 / 56 % of its unlabelled pixels wrong, against 9 / 4 / 23 % outside) and on real pairs
    (KITTI 2015 000000_10, Middlebury Cones and Teddy: 18-31 % wrong against 1.5-4 %, 50-75 % of the bad
    pixels). As negatives they are noisy, which is why they go to training only and never into a label
    image: the forest learns the band as a prior and ranks inside it by the other features.

    With a finite ``look`` the band pixels that look like the object at their disparity rather than the
    background beyond their drop (:func:`band_look_scores` at least ``look``) stay out of the draw: they are
    mostly right, and a right pixel drawn as a negative teaches the forest to distrust exactly the edges it
    should trust. Pixels whose look cannot be computed are drawn.

    With a finite ``cue`` the band pixels the band cue (:mod:`~selfcontra_ros.confidence.band_cue`) calls right
    with a probability of at least ``cue`` stay out of the draw too. With ``texture`` > 0 so do the band pixels
    whose thin strip (the cue's ``strip_texture``: 1x9 pixels, mean absolute deviation) varies by less than
    ``texture`` grey levels. Not because they are right (on the synthetic street and room most of them are
    wrong; on orbit and the real pairs most are right) but because the labels hold few textureless positives
    (an ambiguous match casts no vote, ``ambiguity_min_texture``, so a flat surface is rarely confirmed):
    drawn as negatives they teach the forest that a flat patch is an error, whatever its depth (measured in
    ``docs/label_quality.md``).

    Args:
        label_image: HxW codes (0 unknown, 1 positive, 2 negative).
        disparity: HxW query disparity the labels belong to; non-finite or <= 0 is invalid (never drawn).
        share: probability that each unknown band pixel is drawn as a negative (0: the labels as they are).
        rng: random generator (used only for a share strictly between 0 and 1).
        image: the left image of ``disparity`` (HxW grey or HxWx3 RGB); needed for a finite ``look`` or ``cue``.
        look: band pixels whose look is at least this are not drawn; ``inf``: every band pixel may be.
        labeler: the parameters of the labeler that made ``label_image`` (only its ``stage2_edge_*`` sizes are
            used, so that the prior covers the band the labeler kept from positives); None, or a labeler
            without a band (``stage2_edge_jump_px`` 0, the paper), draws from the default labeler's band:
            the prior is the query's fattening, whether or not the labeler abstained there.
        right: the right image of the pair; needed for a finite ``cue``.
        cue: band pixels the band cue calls right with at least this probability are not drawn; ``inf``: off.
        cue_model: the band cue; None: the package's (:func:`~selfcontra_ros.confidence.band_cue.default_band_cue`).
        texture: band pixels whose strip texture is below this many grey levels are not drawn; 0: off (needs
            both images, as the cue).

    Returns:
        HxW uint8 codes; labelled pixels are never changed.

    Raises:
        SelfContraError: shapes that do not match, a finite ``look`` without an image, or a finite ``cue``
            or a ``texture`` > 0 without both images.
    """
    labels = np.asarray(label_image).astype(np.uint8)
    if labels.shape != np.shape(disparity):
        raise SelfContraError(f"label image {labels.shape} does not match the disparity map {np.shape(disparity)}")
    if share <= 0:
        return labels
    p = _band_params(labeler)
    band = prior_band(disparity, labeler)
    picked = band & (labels == UNKNOWN)
    if share < 1:
        picked &= rng.random(labels.shape) < share
    strip = math.isfinite(cue) or texture > 0  # both read the band cue's strip
    if not (math.isfinite(look) or strip) or not picked.any():
        labels[picked] = NEGATIVE
        return labels
    if image is None or (strip and right is None):
        raise SelfContraError(
            "band_negatives: a finite look needs the left image, a finite cue or a texture > 0 both images"
        )
    if np.shape(image)[:2] != labels.shape:
        raise SelfContraError(f"image {np.shape(image)} does not match the disparity map {labels.shape}")
    rows, cols = np.nonzero(picked)
    kept = np.zeros(rows.size, dtype=bool)
    if math.isfinite(look) or math.isfinite(cue):  # the cue reads the look too
        scores = band_look_scores(image, disparity, band, rows, cols, jump_px=p.stage2_edge_jump_px)
        kept |= scores >= look  # NaN compares False: drawn
    if math.isfinite(cue):
        assert right is not None
        features = band_cue_features(image, right, disparity, rows, cols, scores, p)
        model = cue_model if cue_model is not None else default_band_cue()
        kept |= model.predict(features) >= cue
        kept |= features[:, _STRIP_TEXTURE] < texture
    elif texture > 0:  # the strip's texture alone, without the cue's scan and windows
        assert right is not None
        kept |= strip_textures(image, right, rows, cols) < texture
    picked[rows[kept], cols[kept]] = False
    labels[picked] = NEGATIVE
    return labels


def frame_samples(
    feature_set: str,
    ctx: FeatureContext,
    label_image: NDArray[np.integer],
    rng: np.random.Generator,
    *,
    max_per_class: int = int(constants.TRAINING["max_per_class"]),
) -> Samples:
    """Balanced samples of one image: features only for the chosen pixels' image, labels from ``label_image``.

    Args:
        feature_set: feature set to compute.
        ctx: feature context of the image's query disparity.
        label_image: HxW codes (0 unknown, 1 positive, 2 negative).
        rng: random generator of the draw.
        max_per_class: cap on the samples per class.
    """
    label_image = np.asarray(label_image)
    if label_image.shape != ctx.shape:
        raise SelfContraError(f"label image {label_image.shape} does not match the disparity map {ctx.shape}")
    at_valid = label_image[ctx.rows, ctx.cols]
    chosen = balanced_indices(at_valid, max_per_class, rng)
    width = len(feature_names(feature_set))
    if chosen.size == 0:
        return Samples(feature_set, np.zeros((0, width), np.float32), np.zeros(0, bool), frames=0)
    features, _ = compute_features(feature_set, ctx)
    return Samples(feature_set, features[chosen], at_valid[chosen] == POSITIVE, frames=1)


def merge_samples(parts: Iterable[Samples]) -> Samples:
    """Concatenate samples of one feature set."""
    parts = list(parts)
    if not parts:
        raise SelfContraError("no training samples")
    names = {p.feature_set for p in parts}
    if len(names) != 1:
        raise SelfContraError(f"cannot merge samples of different feature sets {sorted(names)}")
    return Samples(
        feature_set=parts[0].feature_set,
        features=np.concatenate([p.features for p in parts]).astype(np.float32),
        labels=np.concatenate([p.labels for p in parts]).astype(bool),
        frames=sum(p.frames for p in parts),
    )


def train(samples: Samples, params: TrainParams | None = None) -> ForestModel:
    """Train the confidence forest on ``samples`` (pure: same samples and parameters give the same model).

    Raises:
        SelfContraError: without samples of both classes.
    """
    params = params if params is not None else TrainParams()
    if samples.labels.size == 0:
        raise SelfContraError(f"no labelled training samples for feature set {samples.feature_set!r}")
    metadata = {
        **params.metadata,
        "feature_set": samples.feature_set,
        "feature_names": feature_names(samples.feature_set),
        "constants_version": constants.VERSION,
        "training_samples": int(samples.labels.size),
        "training_frames": int(samples.frames),
        "training_positive_share": float(samples.labels.mean()),
    }
    return fit_forest(samples.features, samples.labels, metadata, n_jobs=params.n_jobs, forest=params.forest)
