"""How a reconstruction runs: every stage's settings (:class:`ReconstructionConfig`), which
:func:`~service.reconstruction.pipeline.reconstruct` takes and the job's paths vary
(:mod:`~service.reconstruction.never_worse`).

Example (the slice level alone, without the stack steps):
    >>> from dataclasses import replace
    >>> replace(ReconstructionConfig(), coarse_to_fine=False).coarse_to_fine
    False
"""

from __future__ import annotations

from dataclasses import dataclass

from service.consistency.slice_order import SliceOrder
from service.reconstruction.slices import BIN_BELOW_FRACTION
from service.reconstruction.superresolution import DEFAULT_DELTA_FRACTION, DEFAULT_LAMBDA


@dataclass
class ReconstructionConfig:
    """Tuning of :func:`~service.reconstruction.pipeline.reconstruct` (the defaults are what the
    benchmark and the tests use).

    Attributes:
        inplane_binning: average 2 x 2 in-plane pixel blocks of slices whose pixels are at most
            ``bin_below_fraction`` of the output voxel size
            (:meth:`~service.reconstruction.slices.SliceSet.binned`) before anything else: a 0.55 mm
            pixel is finer than a 0.8 mm grid resolves, and every stage costs in proportion to the
            pixels (real size: 1.4 M pixels -> 0.36 M).
        bin_below_fraction: see ``inplane_binning``.
        margin_mm: margin around the pixels' bounding box when no field of view is given.
        fov_growth_mm: when no field of view is given, it reaches at most this much beyond the
            pixels' box at the starting poses (and ``margin_mm``), whatever the coarse step did: a
            coarse step that scrambles slices (extreme motion) would otherwise spread them over a
            grid several times the brain's, and every later stage, its time and its memory, with it.
        ga_sigma_mm: Gaussian-average smoothing (default: ``gaussian_average.default_sigma_mm``).
        register: run slice-to-volume registration in each round (False: super-resolution only).
        leave_out_folds: register the slices of each fold of stacks (stack index modulo this many
            folds) to a volume re-solved without that fold, so that a misplaced slice is not pulled
            back by its own imprint on the volume (1 or a single stack: register to the volume).
        leave_out_sr_iterations: CG iterations of each leave-out volume (warm-started).
        registration_subsample: registration uses every n-th pixel.
        registration_psf_points: through-plane PSF points during registration.
        registration_iterations: iteration bound of each registration.
        registration_step_mm: initial (and largest) step of the registration, mm == degrees.
        anchor_frame: remove the common rigid drift of all slices after each registration
            (:func:`~service.reconstruction.registration.anchor_frame`).
        coarse_to_fine: (with ``register``) before the slice level, fit one rigid transform per stack, register the
            stacks to each other and start each slice from its own or its stack's pose
            (:mod:`~service.reconstruction.coarse_to_fine`).
        symmetry_plane_x_mm: the atlas mid-sagittal plane of the poses' model: slices whose pose
            lies on the twin branch of their stack are flipped (``None``: no twin handling).
        stack_levels_mm: stack registration resolutions (and trust radii), coarse to fine.
        stack_sweeps: stack registration sweeps per level.
        stack_follow_motion_mm: register a stack as a rigid body of its slices where the stack
            stage's motion model puts them when that model moves them by more than this from the
            rigid stack (RMS E.D., mm), else as its file's grid (distorted by any motion); 0: every
            stack with motion, ``inf``: none.
        slice_orders: per stack, what is known of its acquisition order
            (:class:`~service.consistency.slice_order.SliceOrder`; ``None``: the stage chooses).
        capture_schedule: ``(trust radius mm, extra blur sigma mm)`` of the first registration rounds
            when the coarse step found the predictions coarse (see :func:`~service.reconstruction.pipeline.capture`)
            (wide capture range against a blurred volume); later rounds use
            ``registration_step_mm`` and the forward model's blur.
        psf_points: through-plane PSF points of the super-resolution forward model.
        sr_iterations: CG iterations per round.
        lam: relative regularisation weight of the last round.
        lam_initial: regularisation of round 0, the smooth sharpening of the Gaussian average that
            the first registration uses as its target (a blurred target biases registration).
        lam_first: regularisation of the first registration round; the rounds in between
            interpolate geometrically down to ``lam`` (strong early smoothing while the poses are
            still inconsistent).
        delta_fraction: edge threshold as a fraction of the 99th intensity percentile.
        robust: EM pixel weights and slice exclusion (False: all weights 1).
        robust_tolerance: pixel weights use the EM inlier Gaussian widened by this factor, so only
            gross outliers lose weight (1: the plain EM posteriors, which also down-weight the
            sharpest edges and lose detail on clean data).
        exclude_ratio: slices with potential below this fraction of the median are excluded (and
            slices whose NCC with the volume is an outlier, :func:`~service.reconstruction.robust.ncc_outliers`;
            one that started from its own predicted pose restarts once from its stack's).
        registration_prior_sd_mm: hold each slice near its starting pose in registration, this far
            expected (mm == degrees; :func:`~service.reconstruction.registration.register_slices`'s
            ``prior``); ``None``: no prior.
        intensity_matching: fit each slice's gain and in-plane shading against the volume in every
            round (:mod:`~service.reconstruction.intensity`; False: one scale per stack).
        quality: measure the result without ground truth (:mod:`~service.reconstruction.quality`;
            its leave-one-stack-out volumes cost a few CG iterations per stack).
    """

    inplane_binning: bool = True
    bin_below_fraction: float = BIN_BELOW_FRACTION
    margin_mm: float = 5.0
    fov_growth_mm: float = 30.0
    ga_sigma_mm: float | None = None
    register: bool = True
    leave_out_folds: int = 3
    leave_out_sr_iterations: int = 4
    registration_subsample: int = 2
    registration_psf_points: int = 3
    registration_iterations: int = 30
    registration_step_mm: float = 1.0
    anchor_frame: bool = True
    coarse_to_fine: bool = True
    symmetry_plane_x_mm: float | None = None
    stack_levels_mm: tuple[float, ...] = (4.0, 2.0, 1.0)
    stack_sweeps: int = 2
    stack_follow_motion_mm: float = 0.0
    slice_orders: tuple[SliceOrder, ...] | None = None
    capture_schedule: tuple[tuple[float, float], ...] = ((4.0, 2.0), (2.0, 1.0))
    psf_points: int = 5
    sr_iterations: int = 8
    lam: float = DEFAULT_LAMBDA
    lam_initial: float = 1.0
    lam_first: float = 0.3
    delta_fraction: float = DEFAULT_DELTA_FRACTION
    robust: bool = True
    robust_tolerance: float = 3.0
    exclude_ratio: float = 0.5
    intensity_matching: bool = True
    quality: bool = True
    registration_prior_sd_mm: float | None = None
