"""The numeric core: one pose convention, SE(3) statistics, anchor points, slice sampling.

This package depends on numpy and scipy only. It never imports fastapi, torch or onnxruntime, so
the training code (``model_export``) and the service share it without dragging either along.

Pose convention (the ONE convention of the project)
---------------------------------------------------
* **World / atlas space** is RAS millimetres, exactly the world space of the atlas NIfTI headers
  (``../shared/data/fetal_atlas``). Every affine in this package maps to RAS. SimpleITK's LPS
  appears only at file boundaries and is converted by :mod:`service.geometry.frames`.
* **Slice frame.** A slice plane is an ``L x L`` grid of square pixels of size ``s`` mm, centred on
  the origin of its own frame: pixel ``(row r, column c)`` sits at
  ``x = (c - (L - 1) / 2) * s``, ``y = (r - (L - 1) / 2) * s``, ``z = 0`` (mm). In-plane ``x`` runs
  along columns, ``y`` along rows, the normal is ``z``. Arrays of slices are indexed
  ``[..., row, column]``.
* **Pose.** A pose ``(R, t)`` maps slice-frame mm to atlas mm: ``p_atlas = R @ p_slice + t``.
  Poses are stored as homogeneous ``4 x 4`` float64 matrices acting on column vectors, batched on
  leading axes (``[..., 4, 4]``). ``t`` is the atlas position of the slice centre; the columns of
  ``R`` are the slice's x axis, y axis and normal in atlas space.
* **Anchor points** (the paper's labels) are the images under a pose of ``P1 = (-h, -h, 0)``
  (bottom-left corner), ``P2 = (0, 0, 0)`` (centre) and ``P3 = (h, -h, 0)`` (bottom-right corner)
  with ``h = ANCHOR_HALF_SIZE_MM`` (see :mod:`service.geometry.anchors`).
* **The twin.** Atlas space is left-right symmetric about ``x = x0``; a slice at ``T`` and at
  ``twin(T) = M T diag(1, 1, -1, 1)`` render the same image (see :mod:`service.geometry.twin`).

Example:
    >>> import numpy as np
    >>> from service.geometry import se3
    >>> pose = se3.exp(np.array([0.0, 0.0, np.pi / 2, 1.0, 2.0, 3.0]))
    >>> np.round(pose[:3, :3] @ np.array([1.0, 0.0, 0.0]), 6).tolist()
    [0.0, 1.0, 0.0]
"""

from service.geometry import anchors, encodings, frames, iterators, sampling, se3, twin
from service.geometry.anchors import ANCHOR_HALF_SIZE_MM
from service.geometry.pose import make_pose, slice_pixel_coordinates

__all__ = [
    "ANCHOR_HALF_SIZE_MM",
    "anchors",
    "encodings",
    "frames",
    "iterators",
    "make_pose",
    "sampling",
    "se3",
    "slice_pixel_coordinates",
    "twin",
]
