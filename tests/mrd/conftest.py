"""An ``svrnet-mrd`` server on a free localhost port, and simulated stacks sent as MRD
images, posed by an oracle that knows the simulated truth."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import ismrmrd
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.geometry.frames import voxel_spacing
from service.inference.estimator import PoseEstimate
from service.inference.registry import ModelRegistry
from service.io.volume import Volume
from service.mrd.images import image_from_slice
from service.mrd.server import MrdServer, ServerLimits, session_factory
from service.preprocess.localisation import Localisation
from service.streaming.options import StreamLimits
from tests.support.streams import KeyedOracle, frames_of, simulated_stack, teach


class NearestOracle(KeyedOracle):
    """:class:`KeyedOracle` by nearest input: an MRD header's float32 geometry resamples a slice a
    hair differently from the stack it was taught on, so inputs match only nearly."""

    def __init__(self) -> None:
        super().__init__()
        self.inputs: list[np.ndarray] = []
        self.poses: list[np.ndarray] = []

    def learn(self, inputs: np.ndarray, poses: np.ndarray) -> None:
        self.inputs += [np.asarray(x, np.float64).ravel() for x in inputs]
        self.poses += list(poses)

    def estimate(self, inputs: np.ndarray, mc_samples: int) -> PoseEstimate:
        known = np.stack(self.inputs)
        rows = [int(np.argmin(((known - np.asarray(x, np.float64).ravel()) ** 2).sum(1))) for x in inputs]
        n = len(inputs)
        return PoseEstimate(np.stack([self.poses[r] for r in rows]), np.ones(n), np.zeros(n, bool),
                            spread_mm=np.full(n, 0.5))


class LookupLocaliser:
    """Finds each slice's true brain mask by its pixels (MRD images carry no mask; the pixels arrive
    exactly); a slice it never saw (the blank of one that never came) has no brain."""

    def __init__(self) -> None:
        self.masks: dict[bytes, np.ndarray] = {}

    def learn(self, image: np.ndarray, mask: np.ndarray) -> None:
        for k in range(image.shape[2]):
            self.masks[np.ascontiguousarray(image[:, :, k], np.float32).tobytes()] = np.asarray(mask[:, :, k], bool)

    def _mask(self, volume: Volume, only: int | None = None) -> np.ndarray:
        out = np.zeros(volume.array.shape, bool)
        for k in range(volume.array.shape[2]) if only is None else (only,):
            out[:, :, k] = self.masks.get(np.ascontiguousarray(volume.array[:, :, k], np.float32).tobytes(), False)
        return out

    def localise(self, volume: Volume, region: np.ndarray | None = None) -> Localisation:
        return Localisation.of(self._mask(volume), volume.spacing, "network", 1.0)

    def localise_slice(self, volume: Volume, which: int) -> Localisation:
        return Localisation.of(self._mask(volume, which), volume.spacing, "network", 1.0)

    def slice_in_stack(self, volume: Volume, which: int, others: dict | None = None, index: int = 0,
                       slice_mm: float | None = None) -> tuple[Localisation, np.ndarray]:
        return self.localise_slice(volume, which), np.zeros((1, 1), np.float16)


class Case:
    """Two simulated stacks (axial: series 0, coronal: series 1) as MRD images, their truths, and the
    oracle and localiser that know them."""

    def __init__(self, seed: int = 3) -> None:
        self.oracle, self.localiser = NearestOracle(), LookupLocaliser()
        self.images: list[list[ismrmrd.Image]] = []
        self.truths: list[np.ndarray] = []
        for series, rot in enumerate((np.eye(3), Rotation.from_euler("x", 90, degrees=True).as_matrix())):
            image, mask, affine, truth = simulated_stack(seed, rot)
            # the pipeline cuts the pose network's slices with a localiser's mask less its CSF rim
            spacing = voxel_spacing(affine)
            pose_mask = Localisation.of(mask, spacing, "network", 1.0).pose_mask(spacing, axis=2)
            teach(self.oracle, str(series), image, pose_mask.astype(mask.dtype), affine, truth)
            self.localiser.learn(image, mask)
            self.images.append([image_from_slice(f.pixels, f.scanner_from_voxel, series=series, slice_index=f.index,
                                                 image_index=f.index)
                                for f in frames_of(str(series), image, mask, affine)])
            self.truths.append(truth)


@pytest.fixture(scope="module")
def case() -> Case:
    return Case()


@pytest.fixture
def serve(case: Case) -> Iterator[Any]:
    """``serve(stream_limits, server_limits)`` -> a running :class:`MrdServer` (shut down after the test)."""
    servers: list[MrdServer] = []

    def start(stream_limits: StreamLimits = StreamLimits(), limits: ServerLimits = ServerLimits()) -> MrdServer:
        factory = session_factory(ModelRegistry({"default": case.oracle}), case.localiser, stream_limits)  # type: ignore[dict-item]
        server = MrdServer(("127.0.0.1", 0), factory, stream_limits, limits)
        threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()
