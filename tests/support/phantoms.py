"""Phantoms for the tests (fixed seeds): a synthetic brain in atlas space, and stacks acquired from
it with known per-slice motion, written by SimpleITK or nibabel."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from service.geometry import sampling
from service.geometry.pose import apply


def phantom_brain(seed: int, shape: tuple[int, int, int] = (56, 64, 56), spacing: float = 1.6,
                  radii_mm: tuple[float, float, float] = (30.0, 38.0, 32.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An asymmetric ellipsoidal 'brain' with ventricle-like blobs and texture; returns (T2, mask, affine)."""
    rng = np.random.default_rng(seed)
    aff = np.diag([spacing, spacing, spacing, 1.0])
    aff[:3, 3] = -(np.array(shape) - 1) / 2 * spacing + [1.0, 3.0, 8.0]
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1)
    xyz = ijk * spacing + aff[:3, 3]
    c = np.array([0.0, 3.0, 8.0])
    r = np.asarray(radii_mm) * rng.uniform(0.95, 1.05, 3)
    mask = (((xyz - c) / r) ** 2).sum(-1) <= 1.0
    img = 80.0 + 10 * ndimage.gaussian_filter(rng.normal(size=shape), 2.0)
    for centre, radius, value in [((8, 10, 12), 8, 250), ((-10, 8, 10), 7, 220), ((0, -20, 0), 9, 40),
                                  ((5, 25, -5), 6, 160), ((-6, -5, -15), 5, 200)]:
        img[np.linalg.norm(xyz - (c + centre), axis=-1) < radius] = value
    img = ndimage.gaussian_filter(np.where(mask, img, 0.0), 0.8).astype(np.float32)
    return img, mask.astype(np.float32), aff


def symmetric_phantom_brain(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`phantom_brain` made mirror-symmetric about the atlas plane ``x = 0`` (its centre lies on
    it): the mean of the image and its mirror image, the mask where both masks are."""
    from service.reconstruction.midline import mirror_image

    image, mask, affine = phantom_brain(seed)
    return (0.5 * (image + mirror_image(image, affine, 0.0)),
            ((mask + mirror_image(mask, affine, 0.0)) > 1.0).astype(np.float32), affine)


def stack_affine(slice_axis: int, rotation: np.ndarray, inplane_mm: float = 1.2, thickness_mm: float = 3.0,
                 shape: tuple[int, int, int] = (64, 64, 24), centre_mm=(0.0, 3.0, 8.0)) -> np.ndarray:
    """A stack geometry whose ``slice_axis`` has the thickest spacing, centred on ``centre_mm``."""
    sp = np.full(3, inplane_mm)
    sp[slice_axis] = thickness_mm
    aff = np.eye(4)
    aff[:3, :3] = rotation * sp
    aff[:3, 3] = np.asarray(centre_mm) - aff[:3, :3] @ ((np.asarray(shape) - 1) / 2.0)
    return aff


def acquire_stack(image: np.ndarray, mask: np.ndarray, atlas_affine: np.ndarray, affine: np.ndarray,
                  shape: tuple[int, int, int], slice_axis: int, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stack voxels sampled from the atlas phantom: slice ``s`` sees the atlas through ``motion[s]``.

    ``motion[s]`` is atlas_from_scanner for slice ``s``: the true ``atlas_from_voxel`` of the slice is
    ``motion[s] @ affine``.
    """
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).astype(np.float64)
    scanner = apply(affine, ijk)
    per_slice = np.moveaxis(scanner, slice_axis, 0)                       # [n, ..., 3]
    atlas = apply(motion[:, None, None], per_slice)
    atlas = np.moveaxis(atlas, 0, slice_axis)
    img = sampling.sample_points(image, atlas_affine, atlas)
    msk = sampling.sample_points(mask, atlas_affine, atlas) > 0.5
    return img.astype(np.float32), msk


def orthogonal_stacks_case(directory, stack_prefix: str = "s", seed: int = 5):  # noqa: ANN001, ANN201
    """Three small orthogonal stacks (36 x 36 x 12, 2 mm x 5 mm) of :func:`phantom_brain` with their masks,
    written to ``directory``; returns ``([(stack_path, mask_path)], poses)`` with ``poses`` the true
    poses as a ``/v1/predict`` body."""
    from service.io.volume import Volume, write_volume

    brain = phantom_brain(seed)
    files, body = [], {"stacks": []}
    for axis in range(3):
        shape = [36, 36, 36]
        shape[axis] = 12
        aff = stack_affine(axis, np.eye(3), 2.0, 5.0, tuple(shape))
        g = np.broadcast_to(np.eye(4), (12, 4, 4))
        img, msk = acquire_stack(*brain, aff, tuple(shape), axis, g)
        stack, mask = directory / f"{stack_prefix}{axis}.nii.gz", directory / f"m{axis}.nii.gz"
        write_volume(Volume(img, aff), stack)
        write_volume(Volume(msk.astype(np.uint8), aff), mask)
        files.append((stack, mask))
        body["stacks"].append({"slices": [{"index": s, "accepted": True, "atlas_from_voxel": (g[s] @ aff).tolist()}
                                          for s in range(12)]})
    return files, body


def mirror_symmetric_volume(plane_x: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """A 1 mm volume, asymmetric in y and z, mirror-symmetric about x = plane_x (a random blob field).

    The grid is centred on the plane so that the mirror maps voxel centres onto voxel centres.
    """
    rng = np.random.default_rng(3)
    n = 61
    aff = np.eye(4)
    aff[:3, 3] = [plane_x - 30.0, -30.0, -30.0]
    xyz = np.stack(np.meshgrid(*[np.arange(n) - 30.0] * 3, indexing="ij"), -1)
    centres = rng.uniform(-20, 20, (12, 3))
    vol = np.zeros((n, n, n))
    for c, amp in zip(centres, rng.uniform(0.5, 2.0, 12)):
        for sx in (1.0, -1.0):                      # each blob and its mirror image
            d = xyz - c * np.array([sx, 1.0, 1.0])
            vol += amp * np.exp(-np.sum(d * d, -1) / 40.0)
    vol += 0.02 * xyz[..., 1] + 0.01 * xyz[..., 2]  # breaks any other symmetry
    return vol.astype(np.float32), aff


def ellipsoid_brain_maps(n: int = 16, size: int = 48) -> np.ndarray:
    """A localiser's per-slice probability maps ``[n, size, size]`` of an ellipsoidal brain filling
    slices 1..n-2 (0.9 inside)."""
    k, r, c = np.mgrid[:n, :size, :size]
    inside = ((k - (n - 1) / 2) / ((n - 1) / 2)) ** 2 + ((r - 20) / 14) ** 2 + ((c - 20) / 14) ** 2 < 1
    return np.where(inside, 0.9, 0.0).astype(np.float32)


def one_fetus_scene(stacks: list[tuple]) -> list[tuple]:
    """Generated stacks ``(volume, brain mask)`` of independent scenes placed as one request's stacks
    are: each stack's brain centred on the scanner's origin (the stacks of one scan share the
    scanner's frame, and one fetus's brain lies within a few centimetres in all of them)."""
    from service.geometry.pose import translate
    from service.io.volume import Volume
    from service.preprocess.one_fetus import brain_centre_mm

    return [(Volume(v.array, translate(-brain_centre_mm(m, v.affine)) @ v.affine), m) for v, m in stacks]
