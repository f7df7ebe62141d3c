"""What made a job's outputs, for its report: the service's version, the pose model, the brain
localiser and where each stack's mask came from; never the clients' file names (they often name the
patient).

Example (two stacks, one sent with its brain mask):
    >>> from types import SimpleNamespace as U
    >>> from service.preprocess.localise import default_localiser
    >>> made = provenance({"name": "default"}, [U(localised=False), U(localised=True)], default_localiser(), False)
    >>> made["masks"], made["localiser"]["name"], made["service"]["name"]
    (['uploaded', 'localiser'], 'default', 'svrnet')
"""

from __future__ import annotations

from client.launch import installed_version
from service.preprocess.localise import Localiser, default_localiser


def localiser_provenance(uploads: list, localiser: Localiser | None) -> dict | None:
    """The localiser (``localiser``, default the shipped one) that found the brain of the stacks
    without a mask (or with a region around the head), as ``/v1/predict`` names it; None where every
    stack came with its brain's."""
    return (localiser or default_localiser()).provenance() if any(u.localised for u in uploads) else None


def provenance(model: dict | None, uploads: list, localiser: Localiser | None, masks_hold_csf: bool) -> dict:
    """What made a job's outputs: this service's version, the pose model (the starting body's), the
    localiser (:func:`localiser_provenance`), and per stack whether its mask was uploaded or the
    localiser's (``"uploaded"`` / ``"localiser"``). No file names: they often name the patient."""
    return {"service": {"name": "svrnet", "version": installed_version() or "unknown"}, "model": model,
            "localiser": localiser_provenance(uploads, localiser),
            "masks": ["localiser" if u.localised else "uploaded" for u in uploads],
            "masks_hold_csf": masks_hold_csf}
