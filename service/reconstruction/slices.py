"""The reconstruction's input: every masked pixel of every included slice, with its slice's pose.

Slices come from :func:`service.preprocess.stack.split_stack` (slice axis = the voxel axis of
largest spacing). Pixels are kept as voxel indices ``(i, j, k)`` of their own stack, so that the
atlas position of pixel ``k`` under any set of slice transforms is
``apply(atlas_from_voxel[slice_id[k]], voxel[k])`` (see :meth:`SliceSet.positions`). Pixels are stored
grouped by slice (``slice_id`` is non-decreasing), in stack, slice, row, column order.

Example:
    >>> import numpy as np
    >>> from service.io.volume import Volume
    >>> vol = Volume(np.ones((4, 5, 3), np.float32), np.diag([1.0, 1.0, 3.0, 1.0]))
    >>> mats = np.repeat(vol.affine[None], 3, axis=0)
    >>> ss = SliceSet.from_stacks([(vol, np.ones((4, 5, 3), bool), mats, np.array([True, False, True]))])
    >>> ss.n_slices, len(ss.values), float(ss.values[0]), ss.thickness_mm.tolist()
    (3, 40, 100.0, [3.0, 3.0, 3.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.geometry.sampling import FWHM_TO_SIGMA, INPLANE_FWHM_FACTOR
from service.io.volume import Volume
from service.preprocess.stack import split_stack

BIN_BELOW_FRACTION = 0.75
""":func:`inplane_bin_factors`: slices whose pixels are at most this fraction of the voxel size are binned 2 x 2."""

INTENSITY_SCALE = 100.0
"""Each stack is scaled so that the median of its masked intensities is this value."""

StackInput = tuple[Volume, "NDArray | None", ArrayLike, ArrayLike]


@dataclass
class SliceSet:
    """All pixels of all included slices, and per-slice geometry.

    Attributes:
        values: ``[N]`` float32 intensities (each stack scaled to median ``INTENSITY_SCALE`` in its mask).
        voxel: ``[N, 3]`` float32 voxel indices ``(i, j, k)`` of the pixels in their own stack.
        slice_id: ``[N]`` int32 index of each pixel's slice (into the per-slice arrays).
        atlas_from_voxel: ``[n, 4, 4]`` initial voxel -> atlas RAS mm transform of each slice.
        thickness_mm: ``[n]`` slice thickness of the slice's stack (its volume's ``slice_thickness_mm``;
            unknown: its slice spacing).
        pixel_mm: ``[n]`` mean in-plane pixel size.
        slice_axis: ``[n]`` the stack's voxel axis the slice was taken along.
        stack_index: ``[n]`` index of the slice's stack in the input list.
        slice_index: ``[n]`` index of the slice within its stack.
        stack_affine: ``[n, 4, 4]`` voxel -> scanner RAS affine of the slice's stack (its file header).
        include: ``[n]`` bool: accepted by the caller and with at least one masked pixel (only these
            slices have pixels).
    """

    values: NDArray[np.float32]
    voxel: NDArray[np.float32]
    slice_id: NDArray[np.int32]
    atlas_from_voxel: NDArray[np.float64]
    thickness_mm: NDArray[np.float64]
    pixel_mm: NDArray[np.float64]
    slice_axis: NDArray[np.int64]
    stack_index: NDArray[np.int64]
    slice_index: NDArray[np.int64]
    stack_affine: NDArray[np.float64]
    include: NDArray[np.bool_]

    @property
    def n_slices(self) -> int:
        """Number of slices (included or not)."""
        return len(self.atlas_from_voxel)

    @property
    def n_pixels(self) -> int:
        """Number of pixels ``N``."""
        return len(self.values)

    def pixel_counts(self) -> NDArray[np.int64]:
        """``[n]`` number of pixels of each slice."""
        return np.bincount(self.slice_id, minlength=self.n_slices)

    def positions(self, atlas_from_voxel: ArrayLike | None = None, pixels: NDArray | None = None) -> NDArray:
        """Atlas positions ``[N, 3]`` (float64 mm) of the pixels (or of the subset ``pixels``).

        Args:
            atlas_from_voxel: ``[n, 4, 4]`` slice transforms (default: the initial ones).
            pixels: optional index array selecting pixels.
        """
        t = np.asarray(self.atlas_from_voxel if atlas_from_voxel is None else atlas_from_voxel, np.float64)
        sid = self.slice_id if pixels is None else self.slice_id[pixels]
        vox = self.voxel if pixels is None else self.voxel[pixels]
        m = t[:, :3, :]
        out = m[sid, :, 3].copy()
        for j in range(3):
            out += m[sid, :, j] * vox[:, j:j + 1].astype(np.float64)
        return out

    def normals(self, atlas_from_voxel: ArrayLike | None = None) -> NDArray[np.float64]:
        """Unit slice normals ``[n, 3]`` in atlas space (the image of the slice axis; sign irrelevant)."""
        t = np.asarray(self.atlas_from_voxel if atlas_from_voxel is None else atlas_from_voxel, np.float64)
        cols = t[np.arange(len(t)), :3, self.slice_axis]
        return cols / np.maximum(np.linalg.norm(cols, axis=-1, keepdims=True), 1e-12)

    def centres(self, atlas_from_voxel: ArrayLike | None = None) -> NDArray[np.float64]:
        """``[n, 3]`` mean atlas position of each slice's pixels (0 for slices without pixels)."""
        pos = self.positions(atlas_from_voxel)
        counts = np.maximum(self.pixel_counts(), 1)[:, None]
        return np.stack([np.bincount(self.slice_id, pos[:, d], self.n_slices) for d in range(3)], -1) / counts

    def binned(self, factor: ArrayLike) -> "SliceSet":
        """The slice set with each slice's pixels averaged over ``f x f`` in-plane blocks.

        A block is the pixels of one slice whose in-plane voxel indices floor-divide to the same
        pair (blocks start at index 0). Its value is the mean of its masked pixels and its voxel
        coordinate their mean voxel coordinate -- for a full block ``(f a + (f - 1) / 2, f b + (f - 1) / 2)``,
        the block's centre -- so, ``atlas_from_voxel`` being affine, the binned pixel sits exactly at
        the mean atlas position of its pixels under any pose, and every per-slice array (poses, the
        result's slice weights) keeps its meaning. Blocks cut by the mask average fewer pixels and
        sit at their centroid.

        ``pixel_mm`` becomes the PSF-equivalent pixel size: the in-plane PSF of a binned pixel is the
        original one (sigma ``INPLANE_FWHM_FACTOR x pixel x FWHM_TO_SIGMA``) convolved with the
        uniform average of ``f`` samples ``pixel`` apart (variance ``(f^2 - 1) / 12 pixel^2``), and
        ``pixel_mm`` is chosen so that :func:`~service.reconstruction.forward.inplane_sigma_mm` gives
        that width.

        Args:
            factor: ``[n]`` (or a scalar) integer block size per slice (1: unchanged).

        Returns:
            A new :class:`SliceSet` (pixels still grouped by slice, in slice, row, column order).

        Example:
            >>> import numpy as np
            >>> from service.io.volume import Volume
            >>> vol = Volume(np.arange(32, dtype=np.float32).reshape(4, 4, 2) + 1, np.diag([1.0, 1.0, 3.0, 1.0]))
            >>> ss = SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 2, 0), np.ones(2, bool))])
            >>> b = ss.binned(2)
            >>> b.n_pixels, b.voxel[:2].tolist(), bool(np.isclose(b.values[0], ss.values[[0, 1, 4, 5]].mean()))
            (8, [[0.5, 0.5, 0.0], [2.5, 0.5, 0.0]], True)
        """
        f = np.broadcast_to(np.asarray(factor, np.int64), (self.n_slices,)).copy()
        f = np.maximum(f, 1)
        if np.all(f == 1) or self.n_pixels == 0:
            return self
        sid = self.slice_id.astype(np.int64)
        fp = f[sid]
        vox = self.voxel.astype(np.int64)
        axis = self.slice_axis[sid]
        first = np.where(axis == 0, 1, 0)                        # the in-plane axes p < q of each pixel's slice
        second = np.where(axis == 2, 1, 2)
        cols = np.take_along_axis(vox, first[:, None], 1)[:, 0] // fp       # storage order: q rows, p columns
        rows = np.take_along_axis(vox, second[:, None], 1)[:, 0] // fp
        span = int(max(rows.max(), cols.max())) + 1
        key = (sid * span + rows) * span + cols                  # non-decreasing in slice: grouping kept
        uniq, block = np.unique(key, return_inverse=True)
        block = block.reshape(-1)
        count = np.bincount(block).astype(np.float64)
        values = np.bincount(block, self.values.astype(np.float64)) / count
        voxel = np.stack([np.bincount(block, self.voxel[:, d].astype(np.float64)) / count for d in range(3)], -1)
        new_sid = (uniq // (span * span)).astype(np.int32)
        var = (INPLANE_FWHM_FACTOR * FWHM_TO_SIGMA) ** 2
        pixel_mm = self.pixel_mm * np.sqrt(1.0 + (f**2 - 1) / 12.0 / var)
        return SliceSet(values=values.astype(np.float32), voxel=voxel.astype(np.float32), slice_id=new_sid,
                        atlas_from_voxel=self.atlas_from_voxel.copy(), thickness_mm=self.thickness_mm.copy(),
                        pixel_mm=pixel_mm, slice_axis=self.slice_axis.copy(), stack_index=self.stack_index.copy(),
                        slice_index=self.slice_index.copy(), stack_affine=self.stack_affine.copy(),
                        include=self.include.copy())

    @classmethod
    def from_stacks(cls, stacks: list[StackInput]) -> "SliceSet":
        """Collect the masked pixels of the included slices of several stacks.

        Args:
            stacks: per stack ``(volume, mask, atlas_from_voxel [n, 4, 4], include [n])`` where
                ``mask`` is an array of the volume's shape (nonzero = brain; ``None``: every pixel),
                ``n`` is the number of slices along the slice axis (largest spacing), and
                ``atlas_from_voxel[s]`` maps voxel indices of slice ``s`` to atlas RAS mm.

        Returns:
            The :class:`SliceSet`.

        Raises:
            ValueError: if a transform or include array does not match its stack's slice count.
        """
        if not stacks:
            raise ValueError("SliceSet.from_stacks: no stacks")
        parts: dict[str, list] = {k: [] for k in ("values", "voxel", "slice_id", "mats", "thick", "pix", "axis",
                                                  "stack", "index", "saff", "include")}
        offset = 0
        for si, (volume, mask, mats, include) in enumerate(stacks):
            arr = np.asarray(volume.array, dtype=np.float32)
            m = np.ones(arr.shape, bool) if mask is None else np.asarray(mask) > 0
            if m.shape != arr.shape:
                raise ValueError(f"stack {si}: mask shape {m.shape} differs from the volume's {arr.shape}")
            split = split_stack(volume, m)
            n = len(split.images)
            mats = np.asarray(mats, dtype=np.float64)
            inc = np.asarray(include, dtype=bool).reshape(-1)
            if mats.shape != (n, 4, 4) or inc.shape != (n,):
                raise ValueError(f"stack {si}: expected {n} slices (transforms {mats.shape}, include {inc.shape})")
            a = split.slice_axis
            p, q = [ax for ax in range(3) if ax != a]
            x_axis, y_axis, sx, sy = split.layout                      # how each picture lies on the voxels
            finite = np.isfinite(split.images)
            brain = split.masks & finite
            inside = split.images[brain]
            scale = float(np.median(inside)) if inside.size else 0.0
            if not scale > 0:
                pos = inside[inside > 0]
                scale = float(pos.mean()) if pos.size else 1.0
            keep = brain & inc[:, None, None]
            s_idx, r_idx, c_idx = np.nonzero(keep)
            vox = np.empty((len(s_idx), 3), np.float32)
            h, w = keep.shape[1:]
            vox[:, a] = s_idx
            vox[:, y_axis] = r_idx if sy > 0 else h - 1 - r_idx
            vox[:, x_axis] = c_idx if sx > 0 else w - 1 - c_idx
            stored = np.lexsort((vox[:, p], vox[:, q], s_idx))          # each slice's pixels in the file's order
            parts["values"].append((split.images[keep] * np.float32(INTENSITY_SCALE / scale))[stored])
            parts["voxel"].append(vox[stored])
            parts["slice_id"].append((s_idx[stored] + offset).astype(np.int32))
            parts["mats"].append(mats)
            sp = volume.spacing
            parts["thick"].append(np.full(n, volume.slice_thickness_mm or sp[a]))
            parts["pix"].append(np.full(n, 0.5 * (sp[p] + sp[q])))
            parts["axis"].append(np.full(n, a))
            parts["stack"].append(np.full(n, si))
            parts["index"].append(np.arange(n))
            parts["saff"].append(np.repeat(np.asarray(volume.affine, np.float64)[None], n, axis=0))
            parts["include"].append(inc & keep.any(axis=(1, 2)))
            offset += n
        cat = {k: np.concatenate(v) for k, v in parts.items()}
        return cls(values=cat["values"].astype(np.float32), voxel=cat["voxel"], slice_id=cat["slice_id"],
                   atlas_from_voxel=cat["mats"], thickness_mm=cat["thick"], pixel_mm=cat["pix"],
                   slice_axis=cat["axis"].astype(np.int64), stack_index=cat["stack"].astype(np.int64),
                   slice_index=cat["index"].astype(np.int64), stack_affine=cat["saff"], include=cat["include"])


def inplane_bin_factors(slices: SliceSet, resolution_mm: float,
                        below_fraction: float = BIN_BELOW_FRACTION) -> NDArray[np.int64]:
    """``[n]`` in-plane binning per slice: 2 where its pixels are at most ``below_fraction x resolution_mm``, else 1.

    A 0.55 mm pixel is finer than a 0.8 mm reconstruction grid resolves; 2 x 2 blocks (1.1 mm)
    keep what the grid can hold at a quarter of the pixels (registration, forward model, memory).

    Example:
        >>> import numpy as np
        >>> from service.io.volume import Volume
        >>> vol = Volume(np.ones((4, 4, 2), np.float32), np.diag([0.55, 0.55, 3.0, 1.0]))
        >>> ss = SliceSet.from_stacks([(vol, None, np.repeat(vol.affine[None], 2, 0), np.ones(2, bool))])
        >>> inplane_bin_factors(ss, 0.8).tolist(), inplane_bin_factors(ss, 0.6).tolist()
        ([2, 2], [1, 1])
    """
    return np.where(slices.pixel_mm <= below_fraction * float(resolution_mm), 2, 1).astype(np.int64)
