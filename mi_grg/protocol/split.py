"""Which training views are held out for decisions."""
from __future__ import annotations

import numpy as np

#: Fewest views on each side of a split that decides: the held-out residual's noise level
#: and PSNR are averages, and one view is a single draw.
MIN_DECISION_VIEWS = 2


def holdout_split(n_views: int, holdout_every: int) -> tuple:
    """(fit, held) view indices [n - k], [k]: one view in every ``holdout_every`` is held out
    for decisions (early stopping, choosing a setting) and never fitted while it decides;
    0 holds out none. The one formula every method shares.

    The k = ceil(n / holdout_every) held-out views sit at the middles of k equal blocks of
    the view list, floor((j + 1/2) n / k): evenly spread, so that the widest gap the fitted
    views leave is the narrowest any k held-out views allow (two steps while k < n / 2,
    when neither end of the arc is held out). Why not views 0, n, 2n, ...: on a full circle
    the last of those is view 0's neighbour, a three-step gap, and which views are held
    out moved single cases by about a dB (docs/benchmarks.md, "Every view counts")."""
    n, every = int(n_views), int(holdout_every)
    if every < 0:
        raise ValueError(f"holdout_every must be >= 0 (0: no held-out views), got {every}")
    k = -(-n // every) if every else 0
    held = np.zeros(n, bool)
    held[(np.arange(k) * 2 + 1) * n // (2 * k) if k else []] = True
    return np.flatnonzero(~held), np.flatnonzero(held)


def decision_split(n_views: int, holdout_every: int, name: str) -> tuple:
    """``holdout_split`` for a run that decides on its held-out views: at least
    ``MIN_DECISION_VIEWS`` views to decide on and as many to fit, else a one-line error
    naming ``holdout_every``. ``name``: the method, for the message."""
    fit, held = holdout_split(n_views, holdout_every)
    if min(len(fit), len(held)) < MIN_DECISION_VIEWS:
        raise ValueError(
            f"{name}: holdout_every={holdout_every} leaves {len(held)} of {n_views} training "
            f"view(s) to decide on and {len(fit)} to fit; a decision needs at least "
            f"{MIN_DECISION_VIEWS} of each (lower holdout_every, or use holdout_every=0 / "
            "stop=none for no decision)")
    return fit, held
