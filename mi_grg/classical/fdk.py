"""The ``--method fdk`` entry point (the FDK / FBP operator itself: ``mi_grg.core.fdk``)."""
from __future__ import annotations

from mi_grg.core.fdk import fdk


def reconstruct_fdk(case, *, filter: str = "ram-lak"):
    """FDK/FBP of ``case.train`` [view, v, u] in ``case.geometry``.

    Options:
        filter: ramp apodisation, one of "ram-lak" (default), "shepp-logan", "cosine",
            "hann".
    Returns float32 [x, y, z]. Unknown options raise TypeError (Python keyword rules).
    """
    return fdk(case.train, case.geometry, filter=filter)
