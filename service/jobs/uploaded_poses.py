"""Poses in the ``/v1/predict`` schema read as a job's starting poses, and checked against its uploads.

A client may send a reconstruction job the body ``/v1/predict`` answered for its stacks (or a job's
refined poses, ``GET /v1/reconstructions/{job_id}/poses``) as ``poses``. :func:`in_upload_order`
matches its stacks to the uploaded ones by file name, :func:`poses_from_predict_body` reads it as
``(atlas_from_voxel, accepted)`` per stack (each stack's slices put in their ``index`` order,
:func:`in_index_order`) and refuses what does not fit the uploads, e.g. a pose that is no rigid
placement of the stack's voxels (:func:`not_rigid`). The API checks them when the job is submitted
(:mod:`service.api.reconstructions`); the worker reads them, or the service's own prediction, when
the job runs (:mod:`service.jobs.worker`).
"""

from __future__ import annotations

import numpy as np

from service.geometry import frames
from service.inference.acceptance import EMPTY
from service.io.acquisition_geometry import MAX_FIELD_OF_VIEW_MM


def poses_from_predict_body(body: dict, n_slices: list[int],
                            affines: list | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(atlas_from_voxel [n, 4, 4], accepted [n])`` per stack from a ``/v1/predict`` response body.

    ``affines``: each stack's voxel -> scanner affine, to check a client's poses against: each
    ``atlas_from_voxel`` a rigid placement of the stack's voxels (:func:`not_rigid`), and of a job's
    refined poses at least one slice included. A reconstruction's grid and its every stage are sized
    by those poses. A ``/v1/predict`` answer that accepts no slice is read as it is: the job then
    starts as from its own prediction (:func:`~service.jobs.starting_poses.starting_poses`).

    A stack's slices are matched by their ``index`` where they have one (the body's list is put in
    that order, :func:`in_index_order`), else by their place in the list. Of a job's refined poses
    (``refined_by``) the slices it reconstructed from (``included``) are the accepted ones.

    Raises:
        ValueError: naming what does not match the uploaded stacks.
    """
    stacks = body.get("stacks") if isinstance(body, dict) else None
    refined = isinstance(body, dict) and isinstance(body.get("refined_by"), dict)
    if not isinstance(stacks, list) or len(stacks) != len(n_slices):
        held = f"{len(stacks)}" if isinstance(stacks, list) else "no list of"
        raise ValueError(f"poses: the answer holds {held} stacks' results, and {len(n_slices)} stacks were uploaded; "
                         "send the answer of these stacks, in the order they are sent")
    out = []
    for i, (st, n) in enumerate(zip(stacks, n_slices)):
        slices = st.get("slices") if isinstance(st, dict) else None
        if not isinstance(slices, list):
            raise ValueError(f"poses: stack {i} has no list of slices")
        if len(slices) != n:
            raise ValueError(f"poses: stack {i} has {n} slices but the poses list {len(slices)}")
        if affines is not None and not of_grid(st.get("scanner_from_voxel"), affines[i]):
            raise ValueError(f"poses: stack {i}'s scanner_from_voxel is not the grid of the uploaded stack {i}: the "
                             "poses are of another stack; send the stacks in the order the poses have them")
        slices = st["slices"] = in_index_order(slices, i)
        try:
            mats = np.array([s["atlas_from_voxel"] for s in slices], dtype=np.float64)
            # A job's refined poses: the slices that job reconstructed from (``included``), whatever
            # the model first said of them (a job started from every slice when too few were accepted).
            acc = [s["included"] if refined and "included" in s else s["accepted"] for s in slices]
        except KeyError as exc:
            raise ValueError(f"poses: stack {i}: each slice needs atlas_from_voxel and accepted") from exc
        except (TypeError, ValueError, IndexError, RecursionError) as exc:
            raise ValueError(f"poses: stack {i}: each slice needs atlas_from_voxel (a 4x4 matrix of numbers) and "
                             "accepted") from exc
        if mats.shape != (n, 4, 4) or not np.isfinite(mats).all():
            raise ValueError(f"poses: stack {i}: atlas_from_voxel must be finite 4x4 matrices")
        if not all(isinstance(a, bool) for a in acc):
            raise ValueError(f"poses: stack {i}: accepted must be true or false")
        if (bad := not_a_pose(slices)) is not None:
            raise ValueError(f"poses: stack {i}, slice {bad}: rotation must be a 3x3 rotation matrix and translation_mm "
                             "three finite numbers (the refined poses keep the frame they give), or leave both out")
        if affines is not None and (bad := not_rigid(mats, affines[i])) is not None:
            edges = frames.voxel_spacing(np.asarray(affines[i], np.float64))
            raise ValueError(f"poses: stack {i}, slice {bad}: atlas_from_voxel is no rigid placement of the stack's "
                             f"voxels ({', '.join(f'{e:.4g}' for e in edges)} mm) within "
                             f"{MAX_FIELD_OF_VIEW_MM:.0f} mm of the atlas, keeping the stack's handedness")
        out.append((mats, np.array(acc, bool)))
    if affines is not None and refined and not any(acc.any() for _, acc in out):
        raise ValueError("poses: the job's refined poses include no slice (included: false everywhere); send poses "
                         "that include some, or a /v1/predict answer, or none")
    return out


def in_upload_order(body: dict, filenames: list[str]) -> dict:
    """``body`` (a ``/v1/predict`` answer) with its stacks matched to the uploaded stacks by file name.

    Poses belong to the files they were computed for; two stacks of one slice count and voxel size
    are otherwise told apart by nothing but their order. A body without file names, or with a job's
    ``stacks[i]`` in their place, is taken in its order; so are names that equal the uploads' in
    their order. Distinct names in another order are put in the uploads' order (each stack's
    ``index`` with them). Anything else is refused: names that differ from the uploads', names on
    some stacks only, and repeated names in another order (which stack is which cannot be told).

    Raises:
        ValueError: naming the poses' stacks and the uploaded ones.

    Example:
        >>> body = {"stacks": [{"index": 0, "filename": "cor.nii.gz"}, {"index": 1, "filename": "ax.nii.gz"}]}
        >>> [(s["index"], s["filename"]) for s in in_upload_order(body, ["ax.nii.gz", "cor.nii.gz"])["stacks"]]
        [(0, 'ax.nii.gz'), (1, 'cor.nii.gz')]
    """
    stacks = body.get("stacks") if isinstance(body, dict) else None
    if not isinstance(stacks, list) or len(stacks) != len(filenames):
        return body                                      # poses_from_predict_body names the count
    names = [s.get("filename") if isinstance(s, dict) else None for s in stacks]
    placeholders = [f"stacks[{i}]" for i in range(len(stacks))]         # a job's refined poses keep no client name
    if all(n is None for n in names) or names in (list(filenames), placeholders):
        return body
    listed = f"{', '.join(map(repr, names))}, not of the uploaded {', '.join(map(repr, filenames))}"
    if not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"poses: some stacks have no filename ({listed}); name every stack or none")
    if sorted(names) != sorted(filenames):
        raise ValueError(f"poses: they are of the stacks {listed}; send the files the poses were computed for, under "
                         "the same names (or poses without file names, matched by order)")
    if len(set(names)) < len(names):
        raise ValueError(f"poses: file names repeat ({listed}), so they cannot tell which stack is which; send the "
                         "stacks in the order /v1/predict had them")
    ordered = [stacks[names.index(f)] for f in filenames]
    return {**body, "stacks": [{**st, "index": k} if isinstance(st, dict) and "index" in st else st
                               for k, st in enumerate(ordered)]}


def in_index_order(slices: list, stack: int) -> list:
    """A stack's slices sorted by their ``index`` when they carry one (each of ``0 .. n - 1`` once); a
    list without indices is taken in its order.

    Example:
        >>> [s["index"] for s in in_index_order([{"index": 1}, {"index": 0}], 0)]
        [0, 1]
    """
    indices = [s.get("index") if isinstance(s, dict) else None for s in slices]
    if all(k is None for k in indices):
        return slices
    if sorted(k for k in indices if type(k) is int) != list(range(len(slices))):
        raise ValueError(f"poses: stack {stack}: each slice's index must be one of 0..{len(slices) - 1}, once each")
    return sorted(slices, key=lambda s: s["index"])


def of_grid(given: object, affine: np.ndarray, tolerance_mm: float = 1e-3) -> bool:
    """Whether a poses body's ``scanner_from_voxel`` of a stack (None: the body gives none) is the
    uploaded stack's voxel -> scanner ``affine``: two stacks of one slice count and voxel size are
    otherwise told apart by nothing.

    Example:
        >>> a = np.diag([1.1, 1.1, 3.0, 1.0])
        >>> of_grid(a.tolist(), a), of_grid(None, a), of_grid(np.diag([3.0, 1.1, 1.1, 1.0]).tolist(), a)
        (True, True, False)
    """
    if given is None:
        return True
    try:
        matrix = np.array(given, dtype=np.float64)
    except (TypeError, ValueError, RecursionError):
        return False
    return matrix.shape == (4, 4) and bool(np.allclose(matrix, affine, rtol=0.0, atol=tolerance_mm))


def not_a_pose(slices: list, tolerance: float = 1e-3) -> int | None:
    """The index of the first slice whose ``rotation`` is no rotation matrix (orthonormal within
    ``tolerance``, determinant +1) or whose ``translation_mm`` is no three finite numbers, where a
    slice gives either; else None. A job's refined poses keep the frame these give.

    Example:
        >>> good = {"rotation": np.eye(3).tolist(), "translation_mm": [1.0, 2.0, 3.0]}
        >>> not_a_pose([good, {}]), not_a_pose([good, {**good, "rotation": (2 * np.eye(3)).tolist()}])
        (None, 1)
        >>> not_a_pose([{"rotation": np.diag([1.0, 1.0, -1.0]).tolist(), "translation_mm": [0, 0, 0]}])
        0
    """
    for k, s in enumerate(slices):
        if "rotation" not in s and "translation_mm" not in s:
            continue
        try:
            r, t = (np.array(s.get(key), dtype=np.float64) for key in ("rotation", "translation_mm"))
        except (TypeError, ValueError, RecursionError):
            return k
        if r.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(r).all() and np.isfinite(t).all()):
            return k
        if np.abs(r.T @ r - np.eye(3)).max() > tolerance or np.linalg.det(r) <= 0:
            return k
    return None


def not_rigid(mats: np.ndarray, affine: np.ndarray, tolerance: float = 0.01) -> int | None:
    """The index of the first of ``mats [n, 4, 4]`` that is no rigid placement of the voxels of a stack
    whose voxel -> scanner map is ``affine`` (columns of its voxel edges' lengths within ``tolerance``
    relative, at right angles within ``tolerance`` in cosine, of its handedness: a matrix of the other
    mirrors the stack; last row 0, 0, 0, 1, translation within :data:`MAX_FIELD_OF_VIEW_MM`), else None.

    Example:
        >>> affine = np.diag([1.1, 1.1, 3.0, 1.0])
        >>> good = affine[None].repeat(2, 0)
        >>> bad = good.copy(); bad[1, 0, 0] = 11.0
        >>> mirrored = good.copy(); mirrored[1, 0, 0] = -1.1
        >>> not_rigid(good, affine), not_rigid(bad, affine), not_rigid(mirrored, affine)
        (None, 1, 1)
    """
    affine = np.asarray(affine, np.float64)
    spacing, handedness = frames.voxel_spacing(affine), np.sign(np.linalg.det(affine[:3, :3]))
    lengths = np.linalg.norm(mats[:, :3, :3], axis=1)                          # [n, 3]
    wrong = ((np.abs(lengths / spacing - 1.0).max(axis=1) > tolerance)
             | (frames.axes_cosine(mats[:, :3, :3]) > tolerance)
             | (np.abs(mats[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-6)
             | (np.linalg.norm(mats[:, :3, 3], axis=1) > MAX_FIELD_OF_VIEW_MM)
             | (np.sign(np.linalg.det(mats[:, :3, :3])) != handedness))
    return int(np.argmax(wrong)) if wrong.any() else None


def expected_errors(body: dict) -> np.ndarray:
    """``[n]`` every slice's ``expected_error_mm`` of a ``/v1/predict`` body (stacks in order, each
    stack's slices by their ``index``, :func:`in_index_order`, as :func:`poses_from_predict_body`
    reads the poses), NaN where a slice has none or not a finite, non-negative number (a client's
    body is read, not trusted); less its stack's ``frame.expected_error_added_mm`` in quadrature
    (:func:`frame_added_mm`): a job weighs its slices against each other and places the volume
    in the atlas frame itself, so the request's frame error is no slice's.

    Example:
        >>> expected_errors({"stacks": [{"slices": [{"expected_error_mm": 2.5}, {"expected_error_mm": None}]},
        ...                             {"slices": [{"expected_error_mm": "x"}, {}]}]}).tolist()
        [2.5, nan, nan, nan]
        >>> expected_errors({"stacks": [{"slices": [{"expected_error_mm": 10 ** 20}, {"expected_error_mm": 10 ** 400},
        ...                                         {"expected_error_mm": -1}]}]}).tolist()
        [1e+20, nan, nan]
        >>> expected_errors({"stacks": [{"slices": [{"index": 1, "expected_error_mm": 4.0},
        ...                                         {"index": 0, "expected_error_mm": 2.0}]}]}).tolist()
        [2.0, 4.0]
    """
    given = np.array([_number(s.get("expected_error_mm") if isinstance(s, dict) else None)
                      for i, st in enumerate(body.get("stacks", [])) for s in in_index_order(st.get("slices", []), i)],
                     dtype=np.float64)
    frame = frame_added_mm(body)
    with np.errstate(over="ignore"):                     # a finite but huge error stays huge
        return np.where(frame > 0, np.sqrt(np.maximum(given ** 2 - frame ** 2, 0.0)), given)


def frame_added_mm(body: dict) -> np.ndarray:
    """``[n]`` what the request's frame error added to each slice's expected error (its stack's
    ``frame.expected_error_added_mm``; 0 where the body has none: an answer of an earlier version,
    or a client's), in the order of :func:`expected_errors`.

    Example:
        >>> frame_added_mm({"stacks": [{"frame": {"expected_error_added_mm": 3.0}, "slices": [{}, {}]},
        ...                            {"slices": [{}]}]}).tolist()
        [3.0, 3.0, 0.0]
    """
    out = []
    for st in body.get("stacks", []):
        frame = st.get("frame") if isinstance(st, dict) else None
        added = _number(frame.get("expected_error_added_mm")) if isinstance(frame, dict) else 0.0
        out += [0.0 if np.isnan(added) else added] * len(st.get("slices", []) if isinstance(st, dict) else [])
    return np.array(out, dtype=np.float64)


def accepted_without_frame(body: dict) -> list[np.ndarray]:
    """Per stack of the service's own ``/v1/predict`` body, its slices accepted or rejected only for an
    expected error that the request's frame error put over the body's ``max_expected_error_mm``
    (:func:`expected_errors`), and not over its ``variance_threshold`` either (a reason the
    expected error's hides): what a job starts from. The request's frame error moves every slice
    alike, so it makes no slice worse to start from than another.

    Example (the second slice was over 4.4 mm by its frame error alone; the third is over without it):
        >>> slices = [{"accepted": True, "reason": None, "expected_error_mm": 2.0},
        ...           {"accepted": False, "reason": "high_expected_error", "expected_error_mm": 5.0},
        ...           {"accepted": False, "reason": "high_expected_error", "expected_error_mm": 6.0}]
        >>> body = {"max_expected_error_mm": 4.4, "variance_threshold": 400.0,
        ...         "stacks": [{"frame": {"expected_error_added_mm": 3.0}, "slices": slices}]}
        >>> [a.tolist() for a in accepted_without_frame(body)]
        [[True, True, False]]
        >>> slices[1]["geodesic_variance"] = 900.0              # over the spread's limit too
        >>> [a.tolist() for a in accepted_without_frame(body)]
        [[True, False, False]]
    """
    limit, spread = _number(body.get("max_expected_error_mm")), _number(body.get("variance_threshold"))
    own = expected_errors(body)
    out, start = [], 0
    for i, st in enumerate(body.get("stacks", [])):
        slices = in_index_order(st.get("slices", []), i)
        errors = own[start:start + len(slices)]
        start += len(slices)
        out.append(np.array([bool(s.get("accepted")) or (
            s.get("reason") == "high_expected_error" and e <= limit              # its only other fault can be the spread
            and not _number(s.get("geodesic_variance")) > spread) for s, e in zip(slices, errors)], dtype=bool))
    return out


def posed_slices(body: dict) -> list[np.ndarray]:
    """Per stack of a ``/v1/predict`` body, which slices were posed (not ``empty``)."""
    return [np.array([s.get("reason") != EMPTY for s in st["slices"]]) for st in body["stacks"]]


def signal_lost_slices(body: dict) -> list[np.ndarray]:
    """Per stack of a ``/v1/predict`` body, which slices lost the brain's signal (``signal_lost``)."""
    return [np.array([bool(s.get("signal_lost")) for s in st["slices"]], bool) for st in body["stacks"]]


def _number(value: object) -> float:
    """A JSON value as a finite, non-negative float, else NaN."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return np.nan
    try:
        as_float = float(value)
    except OverflowError:                                # an int beyond float's range (JSON has no limit)
        return np.nan
    return as_float if np.isfinite(as_float) and as_float >= 0 else np.nan
