"""Ctrl-C inside the training loop, acted on between iterations."""
from __future__ import annotations

import signal
import sys
import threading


class DeferredInterrupt:
    """Ctrl-C (SIGINT) inside the training loop, noted and acted on once the iteration in
    progress is done: inside one the optimiser, the densifier and the generator advance at
    different moments, so only between iterations is there one state to checkpoint. A
    second Ctrl-C interrupts at once. Does nothing outside the main thread (no signal
    handler there) or where SIGINT is ignored."""

    def __init__(self):
        self.requested, self._installed, self._old = False, False, None

    def __enter__(self):
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
            self._old = signal.signal(signal.SIGINT, self._note)
            self._installed = True
        return self

    def _note(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, self._previous())
        print("\ninterrupted: finishing this iteration and writing a checkpoint "
              "(Ctrl-C again to stop at once)", file=sys.stderr)

    def _previous(self):
        # None: a handler installed from C, which Python cannot reinstate
        return signal.default_int_handler if self._old is None else self._old

    def __exit__(self, *exc):
        if self._installed:
            signal.signal(signal.SIGINT, self._previous())
        return False
