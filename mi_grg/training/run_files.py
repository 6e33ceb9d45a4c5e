"""A training run's files in its output folder: the checkpoint while it trains, when it
ends train_log.csv / .png, and the exported Gaussians (.npz, .ply) of the run's result
(``mi_grg.training.result``). Without a folder nothing is written."""
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

    def save_checkpoint(self, state, optimizer, densifier, stopper, cfg, n: int) -> None:
        if self.checkpoint_path is not None:
            save_checkpoint(self.checkpoint_path, state, optimizer, densifier, stopper, cfg,
                            n)

    def write_final(self, log: list, returned: int) -> None:
        """train_log.csv and train_log.png (the returned iteration marked)."""
        if self.out is None:
            return
        from mi_grg.evaluation.plotting import plot_log
        from mi_grg.training.log import write_log
        write_log(self.out / "train_log.csv", log)
        plot_log(self.out / "train_log.png", log, returned)

    def write_gaussians(self, g, stem: str) -> None:
        """The exported field (``mi_grg.training.result``) as <stem>.npz and .ply."""
        if self.out is None:
            return
        from mi_grg.data.ply import save_ply
        g.save_npz(self.out / f"{stem}.npz")
        save_ply(g, self.out / f"{stem}.ply")
