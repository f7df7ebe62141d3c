"""Slice poses written as other reconstruction tools read them, to start those tools from our poses.

An answer of ``/v1/predict`` (``svrnet predict --out``) or a job's refined poses (``svrnet
reconstruct --poses-out``) gives every slice ``k`` of stack ``s`` its ``atlas_from_voxel`` ``P_sk``
(voxel ``(i, j, k)`` of the stack file -> atlas RAS mm) beside the stack's ``scanner_from_voxel``
``S_s`` (as the server read the file). Two tools take per-slice poses as input:

* **NeSVoR** (``nesvor reconstruct --input-slices DIR``) reads a folder of one-slice NIfTI files
  ``{i}.nii.gz`` with ``mask_{i}.nii.gz``, each placed by its affine (voxel -> world, sform first),
  its third voxel size the slice thickness. Each slice's affine here is ``P_sk`` moved to the
  slice's own index 0, its third column scaled to the thickness: the slice in atlas space. A slice
  is cut along the stack's ``slice_axis`` (the answer's; a file may store its slices along any
  axis), its in-plane axes the next two in cyclic order, so the affine keeps the file's handedness.
  ``slices.tsv`` maps ``i`` back to stack and slice (NeSVoR keeps no such table).
* **NiftyMIC** (``niftymic_reconstruct_volume_from_slices --dir-input-mc DIR``) reads, per slice of
  a stack file ``NAME.nii.gz``, ``NAME_slice{k}.tfm``: a SimpleITK transform ``T`` (LPS) whose
  composition with the slice's own voxel -> world map is its corrected one, so
  ``T = F P_sk S_s^-1 F`` (``F = diag(-1, -1, 1, 1)``): scanner -> atlas, the inverse of the
  ``.tfm`` files of ``svrnet predict --transforms-out``, which follow ITK's registration
  convention. NiftyMIC drops a slice without a file, so the slices not written are left out. It
  also reads ``NAME.tfm``, the stack's own move (applied first, and undone in each slice's): here
  the mean of its slices' ``T`` (rotations by their chordal mean), so that the volume NiftyMIC
  starts from, a stack resampled into the reconstruction space, lies there too. NiftyMIC cuts a
  stack's slices along the file's third axis: a stack whose ``slice_axis`` is another is written
  again into ``DIR/stacks/`` with its voxels in cyclic order, the slice axis last (the same image,
  placed alike), and so is a stack ITK reads otherwise than the service (:func:`read_as_itk_does`).
  NiftyMIC takes a mask's voxels as stored, on its stack's voxels, and refuses values
  above 1: the mask of a stack written again, or one stored in another voxel order or with other
  values, is written into ``DIR/masks/`` as ``NAME_mask.nii.gz`` (0 and 1); give NiftyMIC those files.

Only the slices the answer trusts are written unless ``all_slices`` (a prediction's accepted ones;
of a job's refined poses, those the job reconstructed from, ``included``, and those it placed by
their stack's motion or by its volume within the answer's ``max_expected_error_mm``, with their
``refined_expected_error_mm`` in ``slices.tsv``); slices without brain (``empty``) never.
SVRTK's ``-transformations`` folder is not written: it numbers slices after cropping the stacks
to its mask, which only a run of SVRTK knows (docs/reconstruction.md gives the recipe).

Example (one slice 5 mm right of where it was acquired):
    >>> S = np.diag([1.0, 1.0, 3.0, 1.0]); P = S.copy(); P[0, 3] = 5.0
    >>> niftymic_transform(P, S)[:3, 3].tolist()       # scanner LPS -> atlas LPS: 5 mm towards the right (-L)
    [-5.0, 0.0, 0.0]
    >>> slice_affine(P, 2, 2.5)[:3, 3].tolist(), float(slice_affine(P, 2, 2.5)[2, 2])   # voxel (0, 0, 2) of the stack
    ([5.0, 0.0, 6.0], 2.5)
"""

from __future__ import annotations

import gzip
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
from numpy.typing import ArrayLike, NDArray

from client.errors import UnusableInput
from client.export_folder import clear_for_export, write_manifest
from client.files import write_whole
from client.scanner_stack import mask_voxels, named_as_stored, nifti_image, slice_axis_of
from client.slice_transforms import stack_from_atlas_lps, tfm_text

FORMATS = ("nesvor", "niftymic")


def niftymic_transform(atlas_from_voxel: ArrayLike, scanner_from_voxel: ArrayLike) -> NDArray[np.float64]:
    """NiftyMIC's ``4 x 4`` LPS transform of one slice: its scanner position -> its atlas position (the
    inverse of :func:`~client.slice_transforms.stack_from_atlas_lps`)."""
    return np.linalg.inv(stack_from_atlas_lps(atlas_from_voxel, scanner_from_voxel))


def axis_order(slice_axis: int) -> tuple[int, int, int]:
    """The stack's voxel axes in the order a slice file holds them: the two in-plane axes in cyclic
    order after ``slice_axis``, then ``slice_axis`` (a cyclic permutation keeps the affine's
    handedness)."""
    a = int(slice_axis)
    if a not in (0, 1, 2):
        raise UnusableInput(f"export: slice_axis {slice_axis!r} is not 0, 1 or 2")
    return (a + 1) % 3, (a + 2) % 3, a


def reordered(voxel_map: ArrayLike, slice_axis: int) -> NDArray[np.float64]:
    """``voxel_map`` (stack voxel -> world) of the stack's voxels in :func:`axis_order`: the map of
    index ``(u, v, w)`` of the reordered array ``np.transpose(data, axis_order(slice_axis))``."""
    m = np.asarray(voxel_map, np.float64)
    return m @ np.eye(4)[:, list(axis_order(slice_axis)) + [3]]


def slice_affine(atlas_from_voxel: ArrayLike, k: int, thickness_mm: float, slice_axis: int = 2) -> NDArray[np.float64]:
    """The affine of slice ``k`` saved alone (its voxel ``(u, v, 0)`` is the stack's voxel at ``u, v``
    in plane (:func:`axis_order`) and ``k`` along ``slice_axis``), the third axis one slice
    thickness long, as NeSVoR reads a slice's profile."""
    a = reordered(atlas_from_voxel, slice_axis) @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, k], [0, 0, 0, 1.0]])
    a[:3, 2] *= thickness_mm / np.linalg.norm(a[:3, 2])
    return a


NIFTYMIC_EXTENSIONS = ("nii.gz", "nii")
"""The file name endings NiftyMIC reads a stack from, in the order it tries them."""


def niftymic_name(path: Path) -> str:
    """The name NiftyMIC gives the stack read from ``path``, which its ``.tfm`` files must start with:
    the file name without every match of the regular expression ``.`` + its ending (NiftyMIC's
    ``Stack.from_filename``); :class:`UnusableInput` for a name NiftyMIC does not read.

    Example (the ending's dot matches any character, elsewhere in the name too):
        >>> niftymic_name(Path("ax.nii.gz")), niftymic_name(Path("haste_nii.nii"))
        ('ax', 'haste')
    """
    ending = next((e for e in NIFTYMIC_EXTENSIONS if path.name.endswith(e)), None)
    if ending is None:
        raise UnusableInput(f"export: NiftyMIC reads stacks named *.nii or *.nii.gz, not {path.name}: rename it")
    return re.sub("." + ending, "", path.name)


def mean_transform(transforms: ArrayLike) -> NDArray[np.float64]:
    """The mean of rigid ``4 x 4`` transforms: the rotations' chordal mean (the rotation nearest their
    sum), the translations' mean.

    Example:
        >>> t = np.stack([np.eye(4), np.eye(4)]); t[1, :3, 3] = (2.0, 0.0, 4.0)
        >>> mean_transform(t)[:3, 3].tolist()
        [1.0, 0.0, 2.0]
    """
    t = np.asarray(transforms, np.float64)
    u, _, vt = np.linalg.svd(t[:, :3, :3].sum(axis=0))
    out = np.eye(4)
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    out[:3, 3] = t[:, :3, 3].mean(axis=0)
    return out


def matched_stacks(answer: dict[str, Any], stacks: list[Path]) -> list[dict[str, Any]]:
    """The answer's stack objects in the order of the files ``stacks``: by file name where the answer
    names them so, each name once, else (a job's refined poses name them ``stacks[i]``; two files of
    one name from two folders) by place.

    Example (two folders' ``ax.nii.gz``, given in the order they were sent):
        >>> answer = {"stacks": [{"filename": "ax.nii.gz", "index": 0}, {"filename": "ax.nii.gz", "index": 1}]}
        >>> [s["index"] for s in matched_stacks(answer, [Path("a/ax.nii.gz"), Path("b/ax.nii.gz")])]
        [0, 1]
    """
    found = answer.get("stacks") or []
    if len(found) != len(stacks):
        raise UnusableInput(f"export: the answer holds {len(found)} stacks, {len(stacks)} files were given")
    by_name = {str(s.get("filename")): s for s in found}
    names_once = len(by_name) == len(found) and len({p.name for p in stacks}) == len(stacks)
    if names_once and all(p.name in by_name for p in stacks):
        return [by_name[p.name] for p in stacks]
    return list(found)


def _chosen(stack: dict[str, Any], all_slices: bool, limit_mm: float | None = None) -> list[dict[str, Any]]:
    """The slices of ``stack`` to write: those with brain that the answer trusts (:func:`_trusted`), or
    every one with brain."""
    return [s for s in stack.get("slices") or []
            if s.get("reason") != "empty" and (all_slices or _trusted(s, limit_mm))]


def _trusted(item: dict[str, Any], limit_mm: float | None = None) -> bool:
    """Whether the answer trusts a slice's pose. A job's refined poses: the slices it reconstructed from
    (``included``), and those it placed otherwise (by their stack's motion or by registration to its
    volume) whose ``refined_expected_error_mm`` is within ``limit_mm`` (the answer's
    ``max_expected_error_mm``, the limit its prediction accepted by). A prediction: its accepted slices.

    Example:
        >>> _trusted({"accepted": False, "included": False, "placed_by_stack_motion": True,
        ...           "refined_expected_error_mm": 3.1}, 4.8), _trusted({"accepted": True}, 4.8)
        (True, True)
        >>> _trusted({"accepted": False, "included": False, "placed_by_volume": True,
        ...           "refined_expected_error_mm": 6.0}, 4.8)
        False
    """
    if "included" not in item:
        return bool(item.get("accepted"))
    placed = bool(item.get("placed_by_stack_motion") or item.get("placed_by_volume"))
    error = item.get("refined_expected_error_mm")
    return bool(item["included"]) or (placed and limit_mm is not None and error is not None and float(error) <= limit_mm)


def _read_stack(path: Path, stack: dict[str, Any], mask: Path | None,
                ) -> tuple[nib.Nifti1Image, NDArray, NDArray[np.float32], NDArray[np.bool_] | None]:
    """A stack file and its mask file read whole and checked (:func:`_stack_file`, :func:`_mask`):
    the image, its ``scanner_from_voxel``, its voxels and its mask (None: none given). Every file is
    read before anything is written, so that a file that does not read leaves no half-written folder."""
    image, sfv = _stack_file(path, stack)
    try:
        voxels = np.asarray(image.dataobj, np.float32).reshape(image.shape[:3])
    except (OSError, ValueError, EOFError, TypeError) as e:
        raise UnusableInput(f"export: {path.name}: its voxels do not read ({e})") from None
    return image, sfv, voxels, None if mask is None else _mask(mask, image)


def _stack_file(path: Path, stack: dict[str, Any]) -> tuple[nib.Nifti1Image, NDArray]:
    """The stack file read with nibabel, checked to be the grid the answer's poses are of."""
    try:
        image = nifti_image(path)
    except (nib.filebasedimages.ImageFileError, OSError, ValueError) as e:
        raise UnusableInput(f"export: {path.name} is not a NIfTI file ({e}); NeSVoR and NiftyMIC read NIfTI") from None
    if stack.get("scanner_from_voxel") is None:
        raise UnusableInput(f"export: the answer's stack {stack.get('index')} has no scanner_from_voxel (the placement "
                            "the service read its file with); export an answer of svrnet predict or a job's poses")
    sfv = np.asarray(stack["scanner_from_voxel"], np.float64)
    same_grid = tuple(image.shape[:3]) == tuple(stack.get("shape") or image.shape[:3])
    if not same_grid or not np.allclose(image.affine, sfv, atol=1e-3):
        raise UnusableInput(f"export: {path.name} is not the file the answer's stack {stack.get('index')} was read from "
                            "(another grid or placement)")
    return image, sfv


def itk_opens(path: Path, image: nib.Nifti1Image) -> bool:
    """Whether SimpleITK (NiftyMIC's reader) opens the NIfTI file ``path`` (``image``, read by its
    content): a NIfTI-1 file compressed as its name says (ITK goes by the name, and reads no NIfTI-2)."""
    return named_as_stored(path) and not isinstance(image, nib.Nifti2Image)


def read_as_itk_does(path: Path, image: nib.Nifti1Image, scanner_from_voxel: NDArray) -> bool:
    """Whether an ITK-based tool (NiftyMIC) reads the stack file ``path`` as the service read it: a
    NIfTI-1 file (SimpleITK reads no NIfTI-2), compressed as its name says (ITK goes by the name),
    placed by its qform where the service placed it (ITK takes the qform where both are set, the
    service the sform) with voxel sizes that agree with that placement (ITK takes them from pixdim).
    A stack that is not is written again for the tool, placed as the service placed it.

    Example (a NIfTI-1 file whose qform lies 7 mm from its sform):
        >>> import tempfile
        >>> image = nib.Nifti1Image(np.zeros((3, 4, 2), np.float32), np.diag([1.0, 2.0, 3.0, 1.0]))
        >>> path = Path(tempfile.mkdtemp()) / "s.nii"; nib.save(image, path)
        >>> read_as_itk_does(path, nib.load(path), image.affine)
        True
        >>> moved = image.affine.copy(); moved[0, 3] = 7.0; image.set_qform(moved, 1); nib.save(image, path)
        >>> read_as_itk_does(path, nib.load(path), image.affine)
        False
    """
    header = image.header
    if not itk_opens(path, image):
        return False
    both = header["qform_code"] > 0 and header["sform_code"] > 0
    if both and not np.allclose(header.get_qform(), header.get_sform(), atol=1e-3):
        return False
    zooms = np.asarray(header.get_zooms()[:3], np.float64)
    return bool(np.allclose(zooms, np.linalg.norm(scanner_from_voxel[:3, :3], axis=0), rtol=1e-3))


@dataclass
class Exported:
    """What :func:`export` wrote: the slices, and the stack files (and masks) to give the tool: the
    files given, or their copies rewritten with the slice axis last (NiftyMIC)."""

    count: int
    stacks: list[Path]
    masks: list[Path] | None = None


def export(answer: dict[str, Any], stacks: list[Path], masks: list[Path] | None, folder: Path, to: str,
           all_slices: bool = False, thickness_mm: list[float] | None = None, overwrite: bool = False) -> Exported:
    """Write the slices of ``answer`` for the tool ``to`` (:data:`FORMATS`) into ``folder``, a new or
    empty folder unless ``overwrite`` (:func:`clear_for_export`), and the list of what it wrote
    (:data:`~client.export_folder.MANIFEST`). ``stacks`` (and ``masks``): the files
    the answer was made from, NIfTI. ``thickness_mm``: one per stack, or one for all (default: each
    stack's slice spacing)."""
    if to not in FORMATS:
        raise UnusableInput(f"export: unknown format {to!r}; one of {', '.join(FORMATS)}")
    folder = Path(folder).expanduser()                   # as a shell would (the CLI's paths come expanded)
    stacks = [Path(p).expanduser() for p in stacks]
    masks = None if masks is None else [Path(p).expanduser() for p in masks]
    done = Exported(0, list(stacks), None if not masks else list(masks))
    rows = ["i\tstack\tfile\tslice\taccepted\texpected_error_mm"]
    stems = [niftymic_name(p).casefold() for p in stacks] if to == "niftymic" else []
    if len(set(stems)) < len(stems):                # AX and ax: one file on macOS's and Windows's disks
        clash = [niftymic_name(p) for p, stem in zip(stacks, stems) if stems.count(stem) > 1]
        raise UnusableInput("export: NiftyMIC names each stack's transforms by its file name, and two stacks are "
                            f"named {' and '.join(repr(c) for c in clash[:2])} (alike but for case): rename one")
    answered = matched_stacks(answer, stacks)           # the answer and every file checked before the folder is touched
    read = [_read_stack(path, stack, None if not masks else masks[s])
            for s, (path, stack) in enumerate(zip(stacks, answered))]
    limit = answer.get("max_expected_error_mm")
    before = clear_for_export(folder, overwrite, [*stacks, *(masks or [])])
    for s, (path, stack, (image, sfv, voxels, brain)) in enumerate(zip(stacks, answered, read)):
        chosen = _chosen(stack, all_slices, limit)
        axis = int(stack["slice_axis"]) if stack.get("slice_axis") is not None else \
            slice_axis_of(np.linalg.norm(sfv[:3, :3], axis=0))          # the service's rule, not a guess
        if to == "niftymic":
            _niftymic_stack(path, chosen, _chosen(stack, True), sfv, folder)
            if axis != 2 or not read_as_itk_does(path, image, sfv):     # NiftyMIC cuts along the third axis
                done.stacks[s] = _rewritten(voxels, sfv, axis, folder / "stacks" / path.name)
            if masks and done.masks is not None:
                if axis != 2 or not _binary_as_stored(masks[s], image):     # NiftyMIC takes it voxel by voxel
                    done.masks[s] = _rewritten(brain.astype(np.uint8), sfv, axis,
                                               folder / "masks" / f"{niftymic_name(path)}_mask.nii.gz")
            done.count += len(chosen)
            continue
        order = axis_order(axis)
        data = np.transpose(voxels, order)
        mask = None if brain is None else np.transpose(brain, order)
        spacing = float(np.linalg.norm(sfv[:3, axis]))
        thick = spacing if not thickness_mm else float(thickness_mm[0] if len(thickness_mm) == 1 else thickness_mm[s])
        for item in chosen:
            k = int(item["index"])
            a = slice_affine(item["atlas_from_voxel"], k, thick, axis)
            for name, values in ((f"{done.count}.nii.gz", data[:, :, k:k + 1]),
                                 (f"mask_{done.count}.nii.gz", None if mask is None else mask[:, :, k:k + 1].astype(np.uint8))):
                if values is not None:
                    _write_nifti(values, a, folder / name)
            expected = item.get("refined_expected_error_mm", item.get("expected_error_mm"))   # a job's, where refined
            rows.append(f"{done.count}\t{s}\t{path.name}\t{k}\t{int(_trusted(item, limit))}\t"
                        f"{'nan' if expected is None else f'{float(expected):.3f}'}")
            done.count += 1
    if to == "nesvor":
        write_whole(folder / "slices.tsv", ("\n".join(rows) + "\n").encode())
    write_manifest(folder, before)
    return done


def _niftymic_stack(path: Path, chosen: list[dict[str, Any]], with_brain: list[dict[str, Any]], sfv: NDArray,
                    folder: Path) -> None:
    """NiftyMIC's ``NAME_slice{k}.tfm`` per chosen slice and ``NAME.tfm``, their mean (the module); the
    mean of every slice with brain where none is chosen (NiftyMIC then leaves the stack out: it
    removes a stack none of whose slices has a file)."""
    stem = niftymic_name(path)
    moves = [niftymic_transform(item["atlas_from_voxel"], sfv) for item in chosen]
    for item, t in zip(chosen, moves):
        write_whole(folder / f"{stem}_slice{int(item['index'])}.tfm", tfm_text(t).encode())
    placing = moves or [niftymic_transform(item["atlas_from_voxel"], sfv) for item in with_brain]
    if placing:
        write_whole(folder / f"{stem}.tfm", tfm_text(mean_transform(placing)).encode())


def _mask(path: Path, stack: nib.Nifti1Image) -> NDArray[np.bool_]:
    """The mask file ``path`` as a boolean array on ``stack``'s voxels (the voxels the server takes for
    brain: :func:`~client.scanner_stack.mask_voxels`), brought into
    the stack's voxel order where it stores the same grid's voxels in another (axes swapped or
    reversed, as tools that reorient files write them; as the service reads it);
    :class:`UnusableInput` when it is on another grid or not a NIfTI file.

    Example (a mask stored with the stack's axes reversed and swapped):
        >>> import tempfile
        >>> stack = nib.Nifti1Image(np.zeros((3, 4, 2), np.float32), np.diag([1.0, 2.0, 3.0, 1.0]))
        >>> m = np.zeros((3, 4, 2), np.uint8); m[0, 1, 1] = 1
        >>> flip = np.diag([1.0, -1.0, 1.0, 1.0]); flip[1, 3] = 3                  # voxel j -> 3 - j
        >>> swap = np.eye(4)[[2, 1, 0, 3]]                                           # axes 0 and 2 exchanged
        >>> stored = nib.Nifti1Image(np.transpose(m[:, ::-1, :], (2, 1, 0)), stack.affine @ flip @ swap)
        >>> path = Path(tempfile.mkdtemp()) / "m.nii.gz"; nib.save(stored, path)
        >>> np.argwhere(_mask(path, stack)).tolist()
        [[0, 1, 1]]
    """
    try:
        image = nifti_image(path)
        values = np.asarray(image.dataobj)
    except (nib.filebasedimages.ImageFileError, OSError, ValueError, EOFError) as e:
        raise UnusableInput(f"export: {path.name} is not a NIfTI mask ({e})") from None
    shape = tuple(stack.shape[:3])
    if values.ndim > 3 and values.size == int(np.prod(values.shape[:3])):
        values = values.reshape(values.shape[:3])
    refused = UnusableInput(f"export: {path.name} is not on its stack's grid ({values.shape} against {shape})")
    if values.ndim != 3:
        raise refused
    mask_from_stack = np.linalg.inv(image.affine) @ stack.affine      # stack voxel -> mask voxel
    signs = np.round(mask_from_stack[:3, :3])
    if not np.allclose(mask_from_stack[:3, :3], signs, atol=1e-3) or sorted(np.abs(signs).sum(0)) != [1, 1, 1] \
            or sorted(np.abs(signs).sum(1)) != [1, 1, 1]:
        raise refused
    axes = [int(np.flatnonzero(signs[:, j])[0]) for j in range(3)]      # the mask axis of each stack axis
    moved = np.transpose(values, axes)
    if moved.shape != shape:
        raise refused
    for j, i in enumerate(axes):
        corner = mask_from_stack[i, 3]                                  # where stack voxel 0 lies on that mask axis
        if signs[i, j] < 0:
            moved = np.flip(moved, j)
            corner = values.shape[i] - 1 - corner
        if abs(corner) > 1e-2:
            raise refused
    return mask_voxels(moved)


def _binary_as_stored(path: Path, stack: nib.Nifti1Image) -> bool:
    """Whether the mask file ``path`` (on ``stack``'s grid: :func:`_mask`) holds the stack's voxels in
    the stack's order and only the values 0 and 1, compressed as its name says: as NiftyMIC reads a
    mask, giving it the stack's placement and taking its voxels as they are stored, refusing values
    above 1, and reading by the file's name.

    Example (a mask of 0 and 255):
        >>> import tempfile
        >>> stack = nib.Nifti1Image(np.zeros((3, 4, 2), np.float32), np.diag([1.0, 2.0, 3.0, 1.0]))
        >>> path = Path(tempfile.mkdtemp()) / "m.nii.gz"
        >>> nib.save(nib.Nifti1Image(np.full((3, 4, 2), 255, np.uint8), stack.affine), path)
        >>> _binary_as_stored(path, stack)
        False
    """
    image = nifti_image(path)
    if not itk_opens(path, image):
        return False
    values = np.asarray(image.dataobj)
    same_order = np.allclose(np.linalg.inv(image.affine) @ stack.affine, np.eye(4), atol=1e-2)
    return bool(same_order and values.shape == tuple(stack.shape[:3]) and np.isin(values, (0, 1)).all())


def _rewritten(values: NDArray, scanner_from_voxel: NDArray, slice_axis: int, path: Path) -> Path:
    """``values`` (the stack's voxels) written to ``path`` in :func:`axis_order`, placed as before."""
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_nifti(np.ascontiguousarray(np.transpose(values, axis_order(slice_axis))),
                 reordered(scanner_from_voxel, slice_axis), path, code=1)
    return path


def _write_nifti(values: NDArray, affine: NDArray, path: Path, code: int = 2) -> None:
    """``values`` as a NIfTI-1 file placed by ``affine``, qform and sform alike (``code`` 2: aligned to
    another space, the atlas; 1: scanner); gzipped where the name ends in ``.gz`` (ITK's readers
    take a file's compression from its name)."""
    out = nib.Nifti1Image(values, affine)
    out.set_qform(affine, code)
    out.set_sform(affine, code)
    raw = out.to_bytes()
    write_whole(path, gzip.compress(raw, compresslevel=6) if path.name.endswith(".gz") else raw)
