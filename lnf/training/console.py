"""A quiet, informative console for ``lnf.train`` and ``lnf.evaluate``: known noise of Lightning and torch filtered
out by message (without importing Lightning); the progress bar is lnf/training/progress_bar.py.

Only the messages listed here are dropped, each matched by a precise regular expression (warnings by message and
category, log records by logger and message): every other warning, lnf's own ones included (a diverged rollout,
a dropped setting), and every error still shows.
"""
from __future__ import annotations

import logging
import os
import re
import warnings
from typing import Any

# (message regex, category) of warnings that say nothing about an lnf run
NOISE_WARNINGS: tuple[tuple[str, type[Warning]], ...] = (
    # torch ≥ 2.10 deprecates LeafSpec, which Lightning's own _pytree still instantiates
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning),
    # a dataset of few snapshots has fewer batches per epoch than log_every_n_steps: the epoch values are logged
    (r"The number of training batches \(\d+\) is smaller than the logging interval", UserWarning),
    # lnf resumes from the checkpoints of a reused output dir on purpose (lnf.train says "resuming from ...")
    (r"Checkpoint directory .* exists and is not empty", UserWarning),
    # lnf's DataLoaders run in the main process by default (data.num_workers=0, the snapshots are cheap)
    (r"The '\w+_dataloader' does not have many workers which may be a bottleneck", UserWarning),
)

# logger name -> message regexes of log records (at INFO) that repeat what lnf says or advertise
_RANK_ZERO = (
    r"💡 Tip: ",
    r"(GPU|TPU|HPU|IPU) available: ",
    r"LOCAL_RANK: \d+ - CUDA_VISIBLE_DEVICES: ",
    r"Loading `train_dataloader` to estimate number of stepping batches\.$",
    r"`Trainer\.fit` stopped: `max_epochs=\d+` reached\.$",  # the end-of-run table says how many epochs ran
    r"Restoring states from the checkpoint path at ",  # lnf.train says "resuming from ..."
    r"Restored all states from the checkpoint at ",
)
NOISE_LOGS: dict[str, tuple[str, ...]] = {
    "lightning.pytorch.utilities.rank_zero": _RANK_ZERO,
    "lightning.fabric.utilities.rank_zero": _RANK_ZERO,
    "lightning_utilities.core.rank_zero": _RANK_ZERO,
    "lightning.fabric.utilities.seed": (r"Seed set to -?\d+$",),  # the seed is in run.json
    "lightning.pytorch.trainer.connectors.checkpoint_connector": (r"`weights_only` was not set, defaulting to ",),
}


class MessageFilter(logging.Filter):
    """Drops the INFO (and lower) records of one logger whose message matches one of `patterns`; a warning or an
    error always passes."""

    def __init__(self, patterns: tuple[str, ...]) -> None:
        super().__init__()
        self.pattern = re.compile("|".join(f"(?:{p})" for p in patterns))

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno > logging.INFO:
            return True
        try:
            message = record.getMessage()
        except Exception:  # noqa: BLE001 - a malformed record is shown as it is
            return True
        return self.pattern.match(message) is None


#: the environment variables Lightning reads a process's global rank from, in its order (LOCAL_RANK before
#: SLURM_PROCID, which SLURM sets even where it does not manage the processes)
RANK_VARIABLES = ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")


def process_rank() -> int:
    """The global rank as Lightning reads it from the environment (:data:`RANK_VARIABLES`); 0 alone. Read here, not
    through Lightning, so that lnf.evaluate starts without importing it."""
    for key in RANK_VARIABLES:
        if os.environ.get(key) is not None:
            return int(os.environ[key])
    return 0


def quiet_console() -> None:
    """Filter the known noise of :data:`NOISE_WARNINGS` and :data:`NOISE_LOGS` (idempotent). On the other
    processes of a distributed run (DDP, SLURM tasks) lnf logs only warnings and errors: rank 0 says once what
    every rank does (the dataset it reuses, where it resumes)."""
    for message, category in NOISE_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category)
    for name, patterns in NOISE_LOGS.items():
        logger = logging.getLogger(name)
        if not any(isinstance(f, MessageFilter) for f in logger.filters):
            logger.addFilter(MessageFilter(patterns))
    # matplotlib's PDF backend subsets fonts with fontTools (40 INFO lines a figure); scikit-fem logs every basis
    # it builds and every form it assembles
    for name in ("fontTools", "skfem"):
        chatty = logging.getLogger(name)
        if chatty.level == logging.NOTSET:  # a level the user set is kept
            chatty.setLevel(logging.WARNING)
    if process_rank() > 0 and logging.getLogger("lnf").getEffectiveLevel() < logging.WARNING:
        logging.getLogger("lnf").setLevel(logging.WARNING)  # lnf.* loggers inherit it


def format_metric(value: Any) -> Any:
    """A float (or a 0-d tensor) in scientific notation with 3 significant digits (``1.23e-04``); other values
    unchanged."""
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:
        value = value.item()
    if isinstance(value, float):
        return f"{value:.2e}"
    return value
