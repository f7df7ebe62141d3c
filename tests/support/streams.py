"""Streamed stacks for the tests (fixed seeds): the phantom acquired slice by slice with a known
rigid offset, and an estimator that answers each slice's true pose."""

from __future__ import annotations

import hashlib

import numpy as np
from scipy.spatial.transform import Rotation

from service.inference.estimator import PoseEstimate
from service.io.volume import Volume
from service.pipeline.prepare import StackUpload, prepare_stack
from service.streaming.frames import SliceFrame
from tests.api.conftest import INFO
from tests.support.phantoms import acquire_stack, phantom_brain, stack_affine

SHAPE = (64, 64, 20)


def _key(x: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(np.round(np.asarray(x, np.float64), 3)).tobytes()).hexdigest()


class KeyedOracle:
    """Returns the true network pose of each slice it has been told about, found by its input (the
    service feeds a slice's network input alike alone and within its stack when no N4 runs: the
    same to within float rounding, as scipy's filters may sum a batch in another order, so inputs are
    keyed at 1e-3 of the 0-255 scale); the atlas origin for any other input."""

    info = INFO

    def __init__(self) -> None:
        self.truth: dict[str, np.ndarray] = {}
        self.calls: list[int] = []

    def learn(self, inputs: np.ndarray, poses: np.ndarray) -> None:
        for x, p in zip(inputs, poses):
            self.truth[_key(x)] = p

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        self.calls.append(len(inputs))
        poses = np.stack([self.truth.get(_key(x), np.eye(4)) for x in inputs])
        n = len(inputs)
        return PoseEstimate(poses, np.ones(n), np.zeros(n, bool), spread_mm=np.full(n, 0.5))


def simulated_stack(seed: int, axis_rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A stack of the phantom with a small rigid offset: (image, mask, affine, true atlas_from_voxel per slice)."""
    img, mask, atlas_aff = phantom_brain(seed)
    affine = stack_affine(2, axis_rotation, shape=SHAPE)
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_rotvec([0.05, -0.03, 0.08]).as_matrix()
    offset[:3, 3] = (1.5, -2.0, 1.0)
    motion = np.repeat(offset[None], SHAPE[2], axis=0)
    image, m = acquire_stack(img, mask, atlas_aff, affine, SHAPE, 2, motion)
    return image, m, affine, motion @ affine


def frames_of(name: str, image: np.ndarray, mask: np.ndarray, affine: np.ndarray) -> list[SliceFrame]:
    out = []
    for k in range(image.shape[2]):
        sent = affine.copy()
        sent[:3, 3] = affine[:3, 3] + k * affine[:3, 2]
        out.append(SliceFrame(name, k, image[:, :, k], sent, mask[:, :, k]))
    return out


def teach(oracle: KeyedOracle, name: str, image: np.ndarray, mask: np.ndarray, affine: np.ndarray,
          atlas_from_voxel: np.ndarray) -> None:
    """Tell the oracle each slice's true network pose, through the service's own preparation."""
    prepared = prepare_stack(StackUpload(name, Volume(image, affine, slice_axis=2), Volume(mask, affine)), INFO, False)
    nfv = prepared.network_from_voxel()
    truth = atlas_from_voxel @ np.linalg.inv(nfv)       # atlas_from_network: slice k's voxel (i, j, k) frame
    oracle.learn(prepared.prepared.inputs, truth)


def two_stacks_case(seed: int = 3) -> tuple[KeyedOracle, list[list[SliceFrame]], list[np.ndarray]]:
    """An axial and a coronal stack of one phantom, their frames, their true atlas_from_voxel, and
    an oracle taught both."""
    oracle = KeyedOracle()
    stacks, truths = [], []
    for name, rot in (("ax", np.eye(3)), ("cor", Rotation.from_euler("x", 90, degrees=True).as_matrix())):
        image, mask, affine, truth = simulated_stack(seed, rot)
        teach(oracle, name, image, mask, affine, truth)
        stacks.append(frames_of(name, image, mask, affine))
        truths.append(truth)
    return oracle, stacks, truths


def true_sent(truth: np.ndarray, k: int) -> np.ndarray:
    """The true atlas_from_voxel of slice ``k`` as sent (voxel (i0, i1, 0))."""
    shift = np.eye(4)
    shift[2, 3] = k
    return truth[k] @ shift
