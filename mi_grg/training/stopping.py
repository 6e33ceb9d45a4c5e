"""A training run's early-stop state machine (``mi_grg.protocol.early_stop`` judges, this
keeps the state): held-out values observed while densifying, judged after it; the state
kept within the stop margin of the best; on a stop, the run either ends there or goes on
from the kept state on every view (``mi_grg.protocol.views``)."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from mi_grg.protocol.early_stop import EarlyStopper
from mi_grg.protocol.views import stop_from


class StopControl:
    """The stopper of a run (``protocol``: TrainConfig's Protocol part) and its verdict
    ``stop`` (views.Stop, None until the rule fires)."""

    def __init__(self, protocol):
        self.protocol = protocol
        self.stopper = EarlyStopper(drop=protocol.stop_drop, patience=protocol.stop_patience,
                                    keep=protocol.keep_state, noise=protocol.stop_noise)
        self.stop = None

    def restore(self) -> None:
        """The verdict of the stopper's state (a resumed run's)."""
        self.stop = stop_from(self.stopper.state_dict())

    def judge(self, it: int, watched, densifying: bool, state, raw: dict, density_scale,
              views):
        """Judge the watched value of iteration ``it`` (None: nothing to judge). Keeps the
        state in ``state`` when the stopper keeps it; on a stop, ``state.stopped_by`` when
        the run ends here, else the kept state becomes the current one. Returns (raw,
        density scale) to continue from."""
        if watched is None:
            return raw, density_scale
        if densifying:       # densification reshapes the model: judge states only after it
            self.stopper.observe(it, watched)     # informs the rule's noise margin only
            return raw, density_scale
        if self.protocol.monitor_3d:
            self.stopper.label = "3-D PSNR vs ground truth (research option)"
        verdict = self.stopper.update(it, watched)
        if self.stopper.kept_iteration == it:
            state.kept_raw = {k: dr.detach(v) for k, v in raw.items()}
            state.kept_density_scale = None if density_scale is None else mi.Float(density_scale)
        elif verdict == "stop":
            self.stop = stop_from(self.stopper.state_dict())
            if views.end(self.stop) == it:
                state.stopped_by = self.stopper.reason
            else:   # go on from the kept state, on every view
                raw = {k: dr.detach(v) for k, v in state.kept_raw.items()}
                for v in raw.values():
                    dr.enable_grad(v)
                state.raw, density_scale = raw, state.kept_density_scale
        return raw, density_scale

    def ending(self, state, views, iterations: int) -> None:
        """``state.stopped_by`` of a run that ended without a reason yet."""
        stop = self.stop
        if state.stopped_by is None and stop is not None and state.iteration >= views.end(stop):
            state.stopped_by = (f"{self.stopper.reason}; then "
                                f"{views.after_stop(stop.kept_iteration)} iterations on "
                                f"every view from the state of iteration {stop.kept_iteration}")
        if state.stopped_by is None:
            state.stopped_by = (f"iteration budget ({iterations}) reached"
                                if state.iteration >= iterations else "interrupted")

    def summary(self, state, views, returned: int) -> dict:
        """The summary's stop fields: best and kept iterations, the best value, the view
        record and the margin the last decision used."""
        s = self.stopper
        best = s.best if math.isfinite(s.best) else None
        return {"best_iteration": s.best_iteration, "kept_iteration": s.kept_iteration,
                "best_heldout_psnr": best,
                "views": views.record(state.iteration, self.stop, s.history, s.reason, returned),
                "stop_margin": {"drop": self.protocol.stop_drop, "noise": self.protocol.stop_noise,
                                "scatter_db": s.scatter(),
                                "margin_db": s.margin() if best is not None else None}}
