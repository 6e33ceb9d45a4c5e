"""A training run's files in its output folder: the checkpoint while it trains, and when
it ends train_log.csv / .png and the returned Gaussians (.npz, .ply). Without a folder
nothing is written."""
from __future__ import annotations

from pathlib import Path

from mi_grg.training.checkpoint import CHECKPOINT_NAME, save_checkpoint


class RunFiles:
    """The files of one run in ``out_dir`` (None: none)."""

    def __init__(self, out_dir=None):
        self.out = Path(out_dir) if out_dir is not None else None
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
        self.checkpoint_path = self.out / CHECKPOINT_NAME if self.out is not None else None

    def save_checkpoint(self, state, optimizer, densifier, stopper, cfg) -> None:
        if self.checkpoint_path is not None:
            save_checkpoint(self.checkpoint_path, state, optimizer, densifier, stopper, cfg)

    def write_final(self, log: list, returned: int, gaussians) -> None:
        """train_log.csv, train_log.png (the returned iteration marked) and the returned
        Gaussians as plain ones whose sum is the reconstruction (gaussians.npz / .ply)."""
        if self.out is None:
            return
        from mi_grg.data.ply import save_ply
        from mi_grg.evaluation.plotting import plot_log
        from mi_grg.training.log import write_log
        write_log(self.out / "train_log.csv", log)
        plot_log(self.out / "train_log.png", log, returned)
        gaussians.save_npz(self.out / "gaussians.npz")
        save_ply(gaussians, self.out / "gaussians.ply")
