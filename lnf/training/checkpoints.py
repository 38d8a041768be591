"""Checkpoints that are never half-written, and the choice of the checkpoint a run resumes from.

Lightning's own writer stages a checkpoint in a temporary file of the system's temp folder and then
*copies* it over the real name: with a full disk that leaves a truncated ``last.ckpt`` under its real
name. :class:`AtomicCheckpointIO` writes to a temporary name in the checkpoint's own folder and renames
it, so a file under a checkpoint's name is always complete; :func:`resume_checkpoint` skips any
checkpoint that does not load and resumes from the newest one that does.
"""
from __future__ import annotations

import errno
import logging
import os
import re
from pathlib import Path
from typing import Any, Optional

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint

from lnf.tempfiles import writer_is_gone
from lnf.trust import read_weights_only

log = logging.getLogger("lnf.train")


class CheckpointWriteError(OSError):
    """A checkpoint could not be written; the message names the file and the cause."""


def save_atomic(payload: Any, path: str | os.PathLike) -> Path:
    """``torch.save(payload)`` to ``{path}.tmp-{pid}`` in the same folder, flushed to disk, then renamed over
    `path`. On any failure the temporary is removed, `path` keeps what it held, and the error names the file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            torch.save(payload, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        full = err.errno in (errno.ENOSPC, errno.EDQUOT)
        raise CheckpointWriteError(err.errno, f"could not write the checkpoint {path}: "
                                   f"{'the disk is full' if full else err.strerror or err}; "
                                   f"the previous file of that name (if any) is unchanged") from err
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint I/O that writes through :func:`save_atomic` (plugged into the Trainer by lnf.train)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Optional[Any] = None) -> None:
        if storage_options is not None:
            raise TypeError(f"AtomicCheckpointIO takes no storage_options, got {storage_options!r}")
        save_atomic(checkpoint, path)


def read_checkpoint(path: Path) -> tuple[Optional[dict[str, Any]], str]:
    """(the checkpoint dict, "") if `path` loads as a Lightning checkpoint, else (None, why not)."""
    try:
        ckpt = read_weights_only(path)  # never unpickles objects: a checkpoint runs no code it carries
    except Exception as err:  # noqa: BLE001 - any unpickling failure: truncated, zeroed, not a checkpoint
        return None, f"does not load ({type(err).__name__}: {err})"
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "epoch" not in ckpt:
        return None, "is not a Lightning checkpoint (no state_dict/epoch)"
    return ckpt, ""


def remove_stale_temporaries(output_dir: Path) -> None:
    """Delete ``*.ckpt.tmp-{pid}`` files of `output_dir` whose writer is gone (a SIGKILL runs no cleanup)."""
    for tmp in [*(output_dir / "checkpoints").glob("*.ckpt.tmp-*"), *output_dir.glob("*.ckpt.tmp-*")]:
        pid = tmp.name.rpartition(".tmp-")[2]
        if writer_is_gone(pid):
            log.warning("removing %s, left by an interrupted checkpoint write (process %s is gone)", tmp, pid)
            tmp.unlink(missing_ok=True)


def candidates(output_dir: Path) -> list[Path]:
    """Every checkpoint of a run folder, newest first: ``checkpoints/*.ckpt`` and Lightning's SLURM
    ``hpc_ckpt_*.ckpt`` (saved on requeue in the output folder)."""
    found = [p for p in [*(output_dir / "checkpoints").glob("*.ckpt"), *output_dir.glob("hpc_ckpt_*.ckpt")]
             if p.is_file()]
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


def newest_valid(paths: list[Path]) -> tuple[Optional[Path], Optional[dict[str, Any]]]:
    """The first of `paths` that loads (with its contents); each one that does not is named in a warning."""
    for path in paths:
        ckpt, why = read_checkpoint(path)
        if ckpt is not None:
            return path, ckpt
        log.warning("skipping checkpoint %s: it %s", path, why)
    return None, None


def resume_checkpoint(ckpt_path: Optional[str], output_dir: Path) -> tuple[Optional[Path], Optional[dict[str, Any]]]:
    """The checkpoint a run resumes from, and its contents (None, None for a fresh start).

    ckpt_path: null (resume from the newest valid checkpoint in the reused output folder, if any), "last"
    (``checkpoints/last.ckpt``; if it does not load, the newest valid one beside it, with a warning; an error
    if there is none) or a path (that file, which must load).
    """
    remove_stale_temporaries(output_dir)
    if ckpt_path is None:
        path, ckpt = newest_valid(candidates(output_dir))
        if path is not None:
            log.info("resuming from %s (the output dir holds a checkpoint; use a new dir to start afresh)", path)
        return path, ckpt
    if str(ckpt_path) == "last":
        last = output_dir / "checkpoints" / "last.ckpt"
        if not last.is_file():
            raise FileNotFoundError(f"ckpt_path=last: no checkpoint at {last}; expected a Lightning checkpoint "
                                    f"file, or ckpt_path=last with hydra.run.dir set to the run to resume")
        path, ckpt = newest_valid([last, *[p for p in candidates(output_dir) if p != last]])
        if path is None:
            raise ValueError(f"ckpt_path=last: {last} does not load and no other checkpoint of "
                             f"{output_dir} does; start afresh in a new output dir")
        log.info("resuming from %s", path)
        return path, ckpt
    path = Path(str(ckpt_path))
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={ckpt_path}: no checkpoint at {path}; expected a Lightning checkpoint "
                                f"file, or ckpt_path=last with hydra.run.dir set to the run to resume")
    ckpt, why = read_checkpoint(path)
    if ckpt is None:
        raise ValueError(f"ckpt_path={ckpt_path}: the file {why}; pick another checkpoint")
    return path, ckpt


PATH_KEYS = ("best_model_path", "kth_best_model_path", "last_model_path")


def checkpoint_names(callback: ModelCheckpoint) -> "re.Pattern[str]":
    """The file names `callback` itself writes: its ``filename`` template (each ``{...}`` any text; Lightning's
    ``epoch=…-step=…`` when unset) with an optional ``-vN`` version, or ``last``, then ``.ckpt``."""
    template = callback.filename or "{epoch}-{step}"
    body = ".+?".join(re.escape(part) for part in re.split(r"\{[^}]*\}", template))
    last = re.escape(callback.CHECKPOINT_NAME_LAST)
    return re.compile(rf"(?:{body}|{last})(?:-v\d+)?{re.escape(callback.FILE_EXTENSION)}")


def confined_state(state: dict[str, Any], dirpath: Any, names: "re.Pattern[str] | None" = None) -> dict[str, Any]:
    """A ModelCheckpoint's restored state with every file it names inside its own `dirpath`, and (given `names`,
    see :func:`checkpoint_names`) named as the callback names its own files.

    ModelCheckpoint deletes the files its state lists when it keeps its top k; a checkpoint's state is the file's
    to say, so a crafted one could name any file (``../../thesis.txt``, a user's ``mine.ckpt``) for deletion on
    resume. Any other path (after resolving ``..`` and links) is dropped, each named in a warning."""
    state = dict(state)
    root = Path(dirpath).resolve() if dirpath else None
    names = names or re.compile(r".+\.ckpt")

    def inside(path: Any) -> bool:
        if not path or root is None:
            return False
        resolved = Path(str(path)).resolve()
        return resolved.parent == root and bool(names.fullmatch(resolved.name))

    dropped = [str(state[k]) for k in PATH_KEYS if state.get(k) and not inside(state[k])]
    for key in PATH_KEYS:
        if state.get(key) and not inside(state[key]):
            state[key] = ""
    if isinstance(state.get("best_k_models"), dict):
        kept = {p: v for p, v in state["best_k_models"].items() if inside(p)}
        dropped += [str(p) for p in state["best_k_models"] if p not in kept]
        state["best_k_models"] = kept
    if dropped:
        log.warning("the resumed checkpoint's ModelCheckpoint state names files that are not this callback's own "
                    "checkpoints in %s (%s): ignored, and never deleted", root, ", ".join(sorted(set(dropped))))
    return state


def confine_restored_state(callback: ModelCheckpoint) -> ModelCheckpoint:
    """Make `callback` restore its state through :func:`confined_state` (lnf.train does it for every
    ModelCheckpoint, a user's own included)."""
    restore = callback.load_state_dict

    def load_state_dict(state: dict[str, Any]) -> None:
        restore(confined_state(state, callback.dirpath, checkpoint_names(callback)))

    callback.load_state_dict = load_state_dict  # type: ignore[method-assign]
    return callback
