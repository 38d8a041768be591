"""A Hydra callback that holds a single run's output folder from before Hydra writes into it.

Hydra saves ``.hydra/config.yaml``, ``hydra.yaml`` and ``overrides.yaml`` into the run folder before it calls
``lnf.train``/``lnf.evaluate``, so the lock those take (:mod:`lnf.run_lock`) came too late: a second run refused
by it had already replaced the first run's ``.hydra/``. :class:`RunFolderGuard` takes the same lock in
``on_run_start``, before Hydra writes anything, and releases it in ``on_run_end``; the entry point's own lock is
then re-entrant. (A multirun's jobs each get a folder of their own.)
"""
from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, read_write

from lnf.run_lock import EVALUATION_RESULTS, RunFolderBusyError, run_folder_lock, set_aside


class RunFolderGuard(Callback):
    """Holds ``hydra.run.dir`` for the whole of a single run (see the module docstring)."""

    def __init__(self) -> None:
        self._held = ExitStack()

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        folder = Path(str(config.hydra.run.dir))
        command = "python -m lnf.evaluate" if "split" in config else "python -m lnf.train"
        try:
            self._held.enter_context(run_folder_lock(folder, command))
            # an evaluation, or a training that starts afresh (no checkpoint to resume): the folder's earlier run
            # keeps its own files (a resumed training is the same run: its .hydra/ is rewritten, run.json appended)
            if "split" in config or not _checkpoints(folder):
                set_aside(folder, (".hydra", *EVALUATION_RESULTS))
        except RunFolderBusyError:
            # Hydra turns a callback's exception into a warning and runs the job anyway: keep it from writing
            # .hydra/ over the running one's; the entry point's own lock then refuses the run, naming the holder
            with read_write(config.hydra):
                config.hydra.output_subdir = None

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._held.close()


def _checkpoints(folder: Path) -> list[Path]:
    """The training checkpoints in `folder` (lnf.training.checkpoints imports Lightning: read only for a training)."""
    from lnf.training.checkpoints import candidates

    return candidates(folder)
