"""Slice-to-volume reconstruction (SVR) in atlas space from per-slice ``atlas_from_voxel`` transforms.

numpy/scipy (and SimpleITK's registration), no torch: it runs inside the service's job workers. Every stage is vectorised
over all pixels of all slices.

Modules:
    * :mod:`~service.reconstruction.slices` -- :class:`SliceSet`, the masked pixels of all included slices;
    * :mod:`~service.reconstruction.grid` -- output grid, trilinear sampling/splatting (exact adjoints);
    * :mod:`~service.reconstruction.gaussian_average` -- the paper's Gaussian average (initial volume);
    * :mod:`~service.reconstruction.forward` -- PSF acquisition model ``A`` and ``A^T``;
    * :mod:`~service.reconstruction.registration` -- batched rigid slice-to-volume registration (NCC);
    * :mod:`~service.reconstruction.robust` -- EM outlier rejection of pixels and slices;
    * :mod:`~service.reconstruction.intensity` -- each slice's gain and shading matched to the volume;
    * :mod:`~service.reconstruction.superresolution` -- CG super-resolution, edge-preserving prior;
    * :mod:`~service.reconstruction.stack_rigid` -- one robust, twin-aware rigid transform per stack;
    * :mod:`~service.reconstruction.stack_registration` -- stack-to-stack registration, 4 -> 2 -> 1 mm;
    * :mod:`~service.reconstruction.coarse_to_fine` -- the coarse steps and each slice's starting pose;
    * :mod:`~service.reconstruction.config` -- :class:`ReconstructionConfig`, every stage's settings;
    * :mod:`~service.reconstruction.pipeline` -- :func:`reconstruct`, the whole loop;
    * :mod:`~service.reconstruction.quality` -- the quality report without ground truth;
    * :mod:`~service.reconstruction.never_worse` -- the paths a job tries, the best one kept;
    * :mod:`~service.reconstruction.atlas_frame` -- the atlas frame re-estimated by the network;
    * :mod:`~service.reconstruction.midline` -- the brain's own midline put on the atlas plane;
    * :mod:`~service.reconstruction.refined_poses` -- refined poses in the ``/v1/predict`` schema;
    * :mod:`~service.reconstruction.export` -- volume, ITK ``.tfm`` transforms, listing, JSON report;
    * :mod:`~service.reconstruction.preview` -- PNG of three orthogonal mid-planes.

Usage::

    ss = SliceSet.from_stacks([(volume, mask, atlas_from_voxel, accepted), ...])
    result = reconstruct(ss, resolution_mm=0.8, svr_iterations=3, progress=callback)
    report = export.write_outputs(result, ss, out_dir)
"""

from service.reconstruction.config import ReconstructionConfig
from service.reconstruction.pipeline import Cancelled, ReconstructionResult, reconstruct
from service.reconstruction.slices import SliceSet

__all__ = ["Cancelled", "ReconstructionConfig", "ReconstructionResult", "SliceSet", "reconstruct"]
