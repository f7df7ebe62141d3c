"""Response bodies of API v1 (``shared/design/api-v1.md``), for validation and the OpenAPI page."""

from __future__ import annotations

import functools
import typing
from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from service.consistency.refined_errors import AGREED_MISMATCH

Vec3 = list[float]
Mat = list[list[float]]


class ModelRef(BaseModel):
    name: str
    version: str
    backbone: str
    sha256: str


class LocaliserRef(BaseModel):
    name: str
    version: str
    sha256: str


class SliceResult(BaseModel):
    index: int = Field(description="index along slice_axis")
    accepted: bool
    reason: Optional[Literal["empty", "high_variance", "high_expected_error", "degenerate_anchor_points", "outside_atlas",
                             "inconsistent_with_stack"]]
    geodesic_variance: Optional[float] = Field(description="SE(3) geodesic variance of the MC samples")
    anchor_points_mm: list[Vec3] = Field(description="P1, P2, P3 of the mean pose, atlas RAS mm")
    rotation: Mat = Field(description="3x3, slice frame -> atlas (Fréchet mean)")
    rotation_vector: Vec3
    quaternion_wxyz: list[float]
    translation_mm: Vec3
    atlas_from_voxel: Mat = Field(description="4x4: voxel (i, j, k, 1) of this slice -> atlas RAS mm")
    branch: Literal["network", "twin"] = Field(
        "network", description="'twin' when stack consistency put the slice on the left-right twin of the "
                               "network's majority MC branch (a slice and its twin render the same image)")
    twin_mass: float = Field(0.0, ge=0.0, le=1.0,
                             description="fraction of the MC samples that sat on the other twin of the returned pose")
    network_atlas_from_voxel: Optional[Mat] = Field(
        None, description="4x4: the network's own pose of this slice (MC majority branch, before stack consistency)")
    expected_error_mm: Optional[float] = Field(
        None, description="expected E.D. (mm) of the returned pose: the stack model's posterior spread where the "
                          "stack is consistent (scaled by the slice's remaining image mismatch where image "
                          "consistency refined it), else the MC spread times the model's calibration (mc_error_scale); "
                          "plus what no stage sees: the request's placement in the atlas (the model's floor) and, "
                          "where the stack decided its left-right branch, the chance that the slice sits on its "
                          "mirror twin times its squared distance to it")
    signal_lost: Optional[bool] = Field(
        False, description="the slice's brain lost its signal (over 15 % of its brain pixels under 0.4 x its stack's "
                           "brain median: a signal void, motion within the slice): no other stack's image checks its "
                           "pose; null where there is no stack to judge it against (a stream's slice before its "
                           "stack ends, a stack of one slice)")
    cut_by_field_of_view: bool = Field(
        False, description="the slice's brain runs out of its picture (the field of view ends inside the brain): the "
                           "network saw part of a brain, and its pose may be far off (its accept flag says whether "
                           "the stages placed it); a field of view that holds the whole head avoids it")


class ImageConsistency(BaseModel):
    stacks: int = Field(description="stacks refined together")
    pairs: int = Field(description="crossing slice pairs whose images were compared")
    slices_refined: int = Field(description="slices of this stack that took part")
    median_move_mm: float = Field(description="median E.D. between a taking-part slice's pose before and after")
    mismatch_before: Optional[float] = Field(None, description="mean squared image difference along the crossings "
                                                               "(noise units), at the stage's poses")
    mismatch_after: Optional[float] = Field(None, description="the same at the refined poses")
    agreed: Optional[bool] = Field(None, description=f"whether mismatch_after is at most {AGREED_MISMATCH:g}: the "
                                                     "refinement brought the slices into agreement and may lower "
                                                     "their expected errors (false: the stage's stand; a stack "
                                                     "refined against fixed partners keeps at least them either way)")


class StackConsistency(BaseModel):
    decidable: bool = Field(description="false when the slices do not agree on one stack: poses left as the network gave them")
    atlas_from_scanner: Optional[Mat] = Field(
        None, description="4x4 the stack's placement: scanner RAS mm -> atlas RAS mm (the file's own geometry) where "
                          "its slices were on average over the acquisition (the robust rigid fit moved by the mean "
                          "of the fitted motion)")
    inlier_fraction: float = Field(description="share of the usable slices the rigid fit explains")
    twinned_slices: int = Field(description="slices moved to the twin of the network's branch")
    inconsistent_slices: int = Field(description="slices whose network pose disagreed with the stack model (every "
                                                 "slice of a mirrored stack)")
    acquisition_order: Optional[str] = Field(None, description="acquisition order the motion model chose among those the request allowed (slice_order): "
                                                     "sequential, interleaved-even-first, interleaved-odd-first, or given")
    motion_bandwidth_slices: Optional[float] = Field(
        None, description="length (in acquisitions) of the motion model; null: one rigid fit sufficed")
    network_error_mm: Optional[float] = Field(None, description="estimated E.D. of one network pose")
    model_error_mm: Optional[float] = Field(None, description="estimated E.D. of the stack model's prediction")
    branch_margin: Optional[float] = Field(
        None, description="how many times worse one rigid stack fits with every slice on its other twin")
    branch_decided: bool = Field(
        False, description="the stack's left-right branch is decided by its slices' order along the normal "
                            "(branch_margin >= 1.5); when false the poses are consistent but the whole stack "
                            "may be the mirror image")
    branch_from_request: bool = Field(
        False, description="the stack did not decide its left-right branch; the request's stacks that did "
                           "decided it (the branch whose rigid fit lies nearer to theirs: the stacks share the "
                           "scanner frame)")
    branch_agrees_with_request: bool = Field(
        False, description="the request decided the branch and the stack sits with the request's stacks on it (its "
                           "twin far from them): it is pooled and refined with them, like a stack that decided "
                           "its branch itself")
    mirrored: bool = Field(
        False, description="the request's other stacks hold the fetus where this stack does only reflected: its "
                           "voxels are the mirror image of what its file's header says (slices reversed, or rows "
                           "or columns flipped, without the affine); none of its slices is accepted "
                           "(inconsistent_with_stack), and it takes no part in the request's decisions")
    apart_from_request: bool = Field(
        False, description="the stack's brain (its mask's centre in the scanner frame) lies farther from the "
                           "request's fetus (where the uploaded masks' brains lie; without masks, most stacks' "
                           "brains) than a fetus moves between stacks (60 mm): another fetus's (a twin's "
                           "mask, another scan's file); none of its slices is accepted (inconsistent_with_stack), "
                           "and it takes no part in the request's decisions, pooling or image stage")
    apart_mm: Optional[float] = Field(
        None, description="with apart_from_request, how far its brain's centre lies from the request's fetus's (mm)")
    pooled_atlas_from_scanner: Optional[Mat] = Field(
        None, description="4x4: the stack's position after pooling it with the request's other stacks whose "
                          "left-right branch is known (decided by themselves, or agreeing with the request; the "
                          "returned poses use it); null when not pooled")
    stacks_pooled: Optional[int] = Field(None, description="stacks of the request pooled (null: this one was not)")
    between_stacks_sd_mm: Optional[float] = Field(
        None, description="spread of the fetus's position between the pooled stacks beyond their fits' errors "
                          "(mm per coordinate; 0: one position, fully pooled; large: each stack kept nearly its own)")
    image_consistency: Optional[ImageConsistency] = Field(
        None, description="the stack's slices refined where they cross the slices of the request's other settled "
                          "stacks (null: not refined: the field image_consistency off, or fewer than two stacks "
                          "that decided their left-right branch)")


class Localisation(BaseModel):
    method: Literal["mask", "network"] = Field(description="'mask': the uploaded mask; 'network': the service's "
                                                            "learned localiser found the brain")
    brain_volume_ml: float = Field(description="volume of the brain mask used (intracranial: brain and extra-axial CSF)")
    confidence: float = Field(description="0..1; 1 for an uploaded mask; low when no brain-like region was found "
                                          "(the stack's slices are then 'empty')")
    pose_mask_inset_mm: float = Field(description="how far inside the mask the pose network's slices were cut: 2.0 for "
                                      "a mask that holds the CSF around the brain (the localiser's, or masks_hold_csf)")
    region_of_interest: bool = Field(description="true where the uploaded mask was a region of interest around "
                                     "the head (it fills its box): the localiser found the brain inside it")


class Noise(BaseModel):
    input_noise: Optional[float] = Field(description="the noise SD the stack's slices carry into the pose network's "
                                                     "inputs (the brain rescaled to 0-255, on the network's 1.25 mm "
                                                     "pixels) as a share of their range; null when no slice holds "
                                                     "enough brain to tell (what scanners' noise gives: docs/accuracy.md)")
    beyond_calibration: bool = Field(description="input_noise exceeds what the network learnt and the pipeline's "
                                                 "benchmarks hold (0.10), as a low-field scanner's noise can: the "
                                                 "poses are less accurate, mostly by a larger turn and shift of the whole "
                                                 "request, which the slices' agreement cannot show")
    expected_error_added_mm: float = Field(0.0, description="what the stack's noise added, in quadrature, to each of "
                                                            "its slices' expected_error_mm (the model's noise "
                                                            "calibration; 0 below its onset, or for a model "
                                                            "without one), so that its accept flags judge the "
                                                            "error its noise brings too")


class Frame(BaseModel):
    request_network_error_mm: Optional[float] = Field(
        description="the request's network error: the RMS of consistency.network_error_mm (how far the network's "
                    "poses scatter about each stack's motion model) over the request's stacks whose fit is "
                    "decidable, weighted by their slices (all but degenerate ones); null when no stack's is (nothing is "
                    "added then). The same for every stack of a request (what requests give: docs/accuracy.md)")
    expected_error_added_mm: float = Field(0.0, description="what the request's frame error added, in quadrature, to "
                                                            "each slice's expected_error_mm: the whole request is "
                                                            "placed worse in the atlas frame where the network is "
                                                            "less sure of its slices, while they still agree with "
                                                            "each other (the model's frame_error calibration; 0 up "
                                                            "to its onset, or for a model without one). A "
                                                            "reconstruction job places its volume itself and reads "
                                                            "the expected errors without it")


class StackResult(BaseModel):
    index: int
    filename: str
    shape: list[int]
    spacing_mm: list[float]
    slice_axis: int
    scanner_from_voxel: Optional[list[list[float]]] = Field(
        None, description="4x4, voxel index (i, j, k, 1) of the uploaded file -> scanner RAS mm, as the service read "
                          "the file (atlas_from_voxel @ inv(scanner_from_voxel): a slice's map from scanner to atlas mm)")
    slices: list[SliceResult]
    consistency: Optional[StackConsistency] = Field(None, description="the stack-consistency stage (null when off)")
    localisation: Optional[Localisation] = Field(None, description="how the stack's brain was localised")
    noise: Optional[Noise] = Field(None, description="how noisy the stack's slices are as the pose network sees them")
    frame: Optional[Frame] = Field(None, description="the request's frame error: how much less sure of the whole "
                                                     "request's placement in the atlas frame its slices' network "
                                                     "errors make it")


class PredictResponse(BaseModel):
    request_id: str
    model: ModelRef
    mc_samples: int
    variance_threshold: float
    max_expected_error_mm: Optional[float] = Field(
        None, description="slices whose expected_error_mm exceeds it are not accepted (null: not judged by it)")
    localiser: Optional[LocaliserRef] = Field(
        None, description="the brain localiser that found the brain of the stacks sent without masks (null: masks sent)")
    stacks: list[StackResult]
    timing_ms: dict[str, float]


class RefinedBy(BaseModel):
    job_id: str
    stage: str


class RefinedSlice(SliceResult):
    included: Optional[bool] = Field(None, description="the job reconstructed from this slice")
    exclusion_reason: Optional[str] = None
    weight: Optional[float] = None
    ncc: Optional[float] = Field(None, description="NCC between the slice and the volume simulated at its pose")
    held_out_ncc: Optional[float] = Field(None, description="the same against the volume made without its stack")
    placed_by_stack_motion: Optional[bool] = Field(None, description="left out of the volume, placed by its stack's "
                                                   "motion through the slices in it")
    placed_by_volume: Optional[bool] = Field(None, description="left out of the volume, registered to it")
    refined_expected_error_mm: Optional[float] = Field(
        None, description="expected E.D. of the refined pose (mm); expected_error_mm stays the prediction's")


class RefinedStack(StackResult):
    slices: list[RefinedSlice]


class RefinedPoses(PredictResponse):
    """A job's refined poses (``GET /v1/reconstructions/{id}/poses``): a ``/v1/predict`` body with what
    the job made of each slice; a valid ``poses`` input to a new job."""

    stacks: list[RefinedStack]
    refined_by: Optional[RefinedBy] = None


class ModelDescription(BaseModel):
    name: str
    version: str
    backbone: str
    sha256: str
    input_size: int
    spacing_mm: float
    label_type: str
    variance_threshold: float
    max_expected_error_mm: Optional[float] = None
    trained_on: str
    mc_seed: Optional[int] = Field(None, description="the seed of the model's fixed MC-dropout draws (one answer per "
                                                     "request); null where every call draws afresh")
    licences: str = Field("", description="the licences of the model's training data, which the model inherits "
                                          "(empty where its file names none)")
    card: bool = Field(False, description="whether the model's folder holds its card (card.md: its data, training "
                                          "and measured accuracy)")


class LocaliserDescription(BaseModel):
    name: str
    version: str
    sha256: str
    default: bool = Field(description="the localiser stacks sent without masks go to")
    grid_mm: float = Field(description="the pixel size of the network's grid")
    licences: str = Field("", description="the licences of its training data (empty where its file names none)")
    card: bool = Field(False, description="whether its folder holds its card (card.md)")


JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class JobCreated(BaseModel):
    """``202`` of ``POST /v1/reconstructions`` (its ``Location`` header: ``status_url``)."""

    job_id: str
    status: JobState
    status_url: str


class JobStatus(BaseModel):
    """``GET /v1/reconstructions/{job_id}``: a job's state, its stage and progress, its results' URLs
    once it has succeeded (null before), its report (docs/reconstruction.md)."""

    model_config = ConfigDict(extra="allow")

    job_id: str
    status: JobState
    stage: Optional[str]
    progress: float = Field(ge=0.0, le=1.0)
    error: Optional[str]
    created_at: str = Field(description="ISO 8601, UTC")
    updated_at: str = Field(description="ISO 8601, UTC")
    started_at: Optional[str] = Field(description="ISO 8601, UTC; null until a worker has started it")
    result_url: Optional[str]
    preview_url: Optional[str]
    poses_url: Optional[str]
    transforms_url: Optional[str]
    report: Optional[dict]
    attempts: int
    workers: Optional[int] = Field(description="a queued job: the workers serving the queue (0: it waits "
                                                     "for one); null otherwise or where the back-end cannot tell")
    coherent: Optional[bool] = Field(description="a succeeded job: the report's quality.coherent")
    expires_at: Optional[str] = Field(description="a finished job: when the server deletes it and its files "
                                      "(ISO 8601, UTC; DELETE deletes them at once); null while it is queued or running")


class Problem(BaseModel):
    type: str
    title: str
    status: int
    detail: str
    request_id: Optional[str] = Field(None, description="the X-Request-ID of the answer, to quote")


def problem_responses(*codes: int) -> dict:
    """OpenAPI ``responses`` for these error statuses: problem+json bodies (RFC 7807). An API route
    (it asks for a key: 401) refuses a foreign browser page (403) at the same place
    (:func:`service.api.deps.early_rejection`).

    Example:
        >>> sorted(problem_responses(401, 404))
        [401, 403, 404]
    """
    codes = codes + ((403,) if 401 in codes else ())
    return {code: {"model": Problem} for code in sorted(set(codes))}


UPLOAD_ERRORS = problem_responses(400, 401, 404, 408, 413, 415, 422, 429, 503, 507)   # the routes that take stacks


def download(media_type: str, *codes: int) -> dict:
    """OpenAPI ``responses`` of a file download: ``200`` of ``media_type`` and these problem statuses."""
    return {200: {"content": {media_type: {"schema": {"type": "string", "format": "binary"}}}},
            **problem_responses(*codes)}


def _model_in(annotation: object) -> type[BaseModel] | None:
    """The pydantic model an annotation holds (itself, or inside Optional / list), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        if (found := _model_in(arg)) is not None:
            return found
    return None


def _holds_list(annotation: object) -> bool:
    """Whether an annotation is a list (itself, or inside Optional)."""
    return typing.get_origin(annotation) is list or any(_holds_list(a) for a in typing.get_args(annotation))


@functools.cache
def _adapter(annotation: object) -> TypeAdapter:
    return TypeAdapter(annotation)


def known_only(value: object, model: type[BaseModel]) -> object:
    """``value`` (parsed JSON) with only the fields ``model`` declares, at every level of nesting, each
    of the declared type (strictly: a field holding anything else is left out): what a client sends
    beyond the schema (a note, a patient's name, an object where a number belongs) is not kept.
    Fields the client leaves out stay out.

    Example:
        >>> known_only({"stacks": [{"index": 0, "note": "x", "slices": [{"index": 0, "who": "y"}]}], "extra": 1,
        ...             "mc_samples": {"hidden": "x"}}, PredictResponse)
        {'stacks': [{'index': 0, 'slices': [{'index': 0}]}]}
        >>> known_only({"stacks": [{"index": 0, "consistency": [{"acquisition_order": "x"}]}]}, PredictResponse)
        {'stacks': [{'index': 0}]}
    """
    if isinstance(value, list):
        return [kept for v in value if isinstance(v, dict) and (kept := known_only(v, model)) is not None]
    if not isinstance(value, dict):
        return None
    out = {}
    for name, field in model.model_fields.items():
        if name not in value:
            continue
        inner = _model_in(field.annotation)
        if inner is not None:
            if isinstance(value[name], list if _holds_list(field.annotation) else dict):   # the declared shape only
                out[name] = known_only(value[name], inner)
            continue
        try:
            _adapter(field.annotation).validate_python(value[name], strict=True)
        except ValidationError:
            continue
        out[name] = value[name]
    return out


def job_poses(body: dict) -> dict:
    """What a job keeps of an uploaded ``poses`` body (until it ends; its refined poses, kept for the
    retention time, are made from it): the typed fields of a ``/v1/predict`` body or of a job's
    refined poses (:func:`known_only`), less the earlier request's free text (its id, model, file
    names, acquisition order) and what the job makes again (timings, each slice's verdict).

    Example:
        >>> job_poses({"request_id": "r", "stacks": [{"filename": "Doe.nii", "slices": [{"index": 0, "ncc": 0.9}]}]})
        {'stacks': [{'slices': [{'index': 0}]}]}
    """
    kept = known_only(body, RefinedPoses)
    for earlier in ("request_id", "timing_ms", "model"):
        kept.pop(earlier, None)
    for stack in kept.get("stacks", []):
        stack.pop("filename", None)
        (stack.get("consistency") or {}).pop("acquisition_order", None)
        for s in stack.get("slices", []):
            for made_by_the_job in ("exclusion_reason", "weight", "ncc", "held_out_ncc", "placed_by_stack_motion",
                                    "placed_by_volume", "refined_expected_error_mm"):
                s.pop(made_by_the_job, None)
    return kept
