"""Which slices a reconstruction job starts from, and with which poses, given the service's own
``/v1/predict`` answer: its accepted slices where enough are accepted, else every slice; never a
stack the request found mirrored or apart from its fetus, or a slice whose brain lost its signal, unless
nothing else is left.

Example:
    >>> body = {"stacks": [{"slices": [{"accepted": True}, {"accepted": False}]}]}
    >>> start_label(body, [(None, np.array([True, True]))])
    'every_slice'
"""

from __future__ import annotations

import numpy as np

from service.jobs.uploaded_poses import accepted_without_frame, posed_slices, poses_from_predict_body, signal_lost_slices
from service.preprocess.intensity import SIGNAL_LOST

MIN_ACCEPTED_SHARE = 0.3
"""A job starts from the accepted slices alone when at least this share of the request's posed slices
(those not ``empty``) is accepted, and at least :data:`MIN_ACCEPTED_SLICES`; otherwise from every slice."""
MIN_ACCEPTED_SLICES = 30
"""Fewer accepted slices than this make no volume to judge a job's paths by: their volume is no brain
(docs/reports/reconstruction-experiments.md, "The figures behind the job's constants")."""


def starting_inclusion(poses: list[tuple[np.ndarray, np.ndarray]], posed: list[np.ndarray] | None = None,
                       min_share: float = MIN_ACCEPTED_SHARE, min_slices: int = MIN_ACCEPTED_SLICES,
                       ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Which of the service's own poses a job starts from: the accepted slices (``accepted`` judges the
    returned pose by its calibrated expected error: the slices it rejects hold most of the misplaced
    ones), unless fewer than ``min_share`` of the ``posed`` slices (default: every slice), or fewer
    than ``min_slices``, are accepted: then every slice, and the reconstruction's stack fit and robust
    statistics judge them. Poses a client uploads keep the client's flags.

    Example (two of three accepted: those two; one of three under a share of 0.5, or two under 30
    slices: all three):
        >>> poses = [(np.zeros((3, 4, 4)), np.array([True, True, False]))]
        >>> [inc.tolist() for _, inc in starting_inclusion(poses, min_slices=2)]
        [[True, True, False]]
        >>> [inc.tolist() for _, inc in starting_inclusion([(np.zeros((3, 4, 4)), np.array([True, False, False]))], min_share=0.5, min_slices=1)]
        [[True, True, True]]
        >>> [inc.tolist() for _, inc in starting_inclusion(poses)]
        [[True, True, True]]
    """
    posed = posed if posed is not None else [np.ones(len(acc), bool) for _, acc in poses]
    n_posed = sum(int(np.sum(p)) for p in posed)
    n_accepted = sum(int(np.sum(acc & p)) for (_, acc), p in zip(poses, posed))
    if n_posed and n_accepted >= min_share * n_posed and n_accepted >= min_slices:
        return [(mats, acc.copy()) for mats, acc in poses]
    return [(mats, np.ones(len(mats), dtype=bool)) for mats, _ in poses]


def lost_reasons(reasons: list[str | None] | None, body: dict) -> list[str | None] | None:
    """A job's per-slice exclusion reasons (all stacks' slices in order) with ``signal_lost`` for the
    slices left out because their brain lost its signal (:func:`starting_poses`), not ``not_used``.

    Example:
        >>> body = {"stacks": [{"slices": [{"signal_lost": True}, {}]}, {"slices": [{"signal_lost": True}]}]}
        >>> lost_reasons(["not_used", "not_used", None], body)
        ['signal_lost', 'not_used', None]
    """
    if reasons is None:
        return None
    lost = np.concatenate(signal_lost_slices(body) or [np.zeros(0, bool)])
    return [SIGNAL_LOST if r == "not_used" and k < len(lost) and lost[k] else r for k, r in enumerate(reasons)]


def starting_poses(body: dict, min_share: float = MIN_ACCEPTED_SHARE, min_slices: int = MIN_ACCEPTED_SLICES,
                   keep_signal_lost: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(atlas_from_voxel, include)`` per stack that a job starts from, given the service's own
    ``/v1/predict`` body (:func:`~service.jobs.uploaded_poses.poses_from_predict_body`, accepted as
    :func:`~service.jobs.uploaded_poses.accepted_without_frame` reads them, :func:`starting_inclusion`),
    less the slices whose brain lost its signal (their images would darken the volume where they
    lie; kept with ``keep_signal_lost``, or where nothing else is left), and less every slice of a
    stack the request found mirrored (``consistency.mirrored``: its slices lie on the twin of where
    the others put them, and would blend the brain with its mirror image) or apart from the
    request's fetus (``consistency.apart_from_request``: another brain); kept where nothing else is
    left. The share of accepted slices is that of the stacks kept: a twin's stack, none of its slices
    accepted, does not make a job start from every slice of the fetus's."""
    poses = poses_from_predict_body(body, [len(st["slices"]) for st in body["stacks"]])
    poses = [(mats, own) for (mats, _), own in zip(poses, accepted_without_frame(body))]
    left_out = np.array([any((st.get("consistency") or {}).get(key) for key in ("mirrored", "apart_from_request"))
                         for st in body["stacks"]], bool)       # numpy's bools: ~ is not, as for the masks
    posed = [p & ~out for p, out in zip(posed_slices(body), left_out)]     # the share among the stacks kept
    started = starting_inclusion(poses, posed, min_share, min_slices)
    started = _unless_nothing_left(started, [(mats, include & ~out) for (mats, include), out in zip(started, left_out)])
    kept = [(mats, include & ~lost) for (mats, include), lost in zip(started, signal_lost_slices(body))]
    return started if keep_signal_lost else _unless_nothing_left(started, kept)


def _unless_nothing_left(poses: list[tuple[np.ndarray, np.ndarray]], fewer: list[tuple[np.ndarray, np.ndarray]]
                         ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``fewer`` (the same poses, fewer slices included), or ``poses`` where ``fewer`` includes none."""
    return fewer if any(include.any() for _, include in fewer) else poses


def start_label(body: dict, poses: list[tuple[np.ndarray, np.ndarray]]) -> str:
    """The report's ``started_from`` for a job that started from ``poses`` (:func:`starting_poses` of the
    service's own ``body``): ``accepted_slices`` where it kept the accepted slices alone (every slice,
    where all were accepted), else ``every_slice``.

    Example (two stacks: one slice of three not accepted, and the job kept or overrode the flags):
        >>> body = {"stacks": [{"slices": [{"accepted": True}, {"accepted": False}]}, {"slices": [{"accepted": True}]}]}
        >>> start_label(body, [(None, np.array([True, False])), (None, np.array([True]))])
        'accepted_slices'
        >>> start_label(body, [(None, np.array([True, True])), (None, np.array([True]))])
        'every_slice'
    """
    accepted = accepted_without_frame(body)
    kept = all(np.array_equal(include, acc) or np.array_equal(include, acc & ~lost)
               for (_, include), acc, lost in zip(poses, accepted, signal_lost_slices(body)))
    return "accepted_slices" if kept else "every_slice"


def uploaded_start(body: dict, poses: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    """What a job starts from given a client's ``poses`` (read from ``body``,
    :func:`~service.jobs.uploaded_poses.poses_from_predict_body`), and its report's ``started_from``:
    the client's flags (``uploaded_poses``), unless they accept no slice. ``/v1/predict``'s answer for
    stacks without masks often accepts none; the job then starts as from its own prediction of them
    (:func:`starting_poses`, :func:`start_label`), as it would without the upload.

    Example (a body that accepts one slice of two, and one that accepts none):
        >>> body = {"stacks": [{"slices": [{"accepted": a, "atlas_from_voxel": np.eye(4).tolist()} for a in (True, False)]}]}
        >>> uploaded_start(body, [(np.zeros((2, 4, 4)), np.array([True, False]))])[1]
        'uploaded_poses'
        >>> body["stacks"][0]["slices"][0]["accepted"] = False
        >>> start, label = uploaded_start(body, [(np.zeros((2, 4, 4)), np.array([False, False]))])
        >>> label, start[0][1].tolist()
        ('every_slice', [True, True])
    """
    return (poses, "uploaded_poses") if any(np.any(accepted) for _, accepted in poses) else own_start(body)


def own_start(body: dict) -> tuple[list[tuple[np.ndarray, np.ndarray]], str]:
    """:func:`starting_poses` of the service's own ``/v1/predict`` ``body`` and their :func:`start_label`."""
    poses = starting_poses(body)
    return poses, start_label(body, poses)
