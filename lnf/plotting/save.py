"""Atomic figure files: a PNG and a vector PDF beside it, each through a temporary name and a rename."""
from __future__ import annotations

import os
import uuid
from pathlib import Path

from matplotlib.figure import Figure

from lnf.plotting.style import _DPI


def vector_path(path) -> Path:
    """Where :func:`save_figure` writes the PDF of a PNG at ``path``: the same stem with suffix ``.pdf``
    (``fig3.png`` → ``fig3.pdf``); for a ``path`` that itself ends in ``.pdf`` (the PNG then has that name),
    ``<stem>.vector.pdf``."""
    path = Path(path)
    pdf = path.with_suffix(".pdf")
    return pdf if pdf != path else path.with_name(f"{path.stem}.vector.pdf")



def save_figure(fig: Figure, path, *, pdf: bool | None = None, **savefig_kwargs) -> Path:
    """Write ``fig`` as a PNG (200 dpi) to ``path`` and, with ``pdf``, as a vector PDF of the same stem beside
    it (:func:`vector_path`: ``fig3.png`` → ``fig3.pdf``), both atomically; return the PNG's path. ``pdf=None``
    (the default) writes the PDF unless the environment sets ``LNF_FIGURE_PDF=0`` (PNG only: quicker, for
    runs that draw many figures nobody will print).

    Each file is rendered to a uniquely named temporary file in the same directory, then ``os.replace``d
    onto its name, so a reader never sees a half-written file (nor a temporary one after an error: they are
    removed). Parent directories are created. The raster is always PNG, whatever the suffix of ``path``. The
    PDF embeds its fonts as TrueType (editable text). Other keyword arguments (``dpi`` too) go to
    ``fig.savefig`` for both files.
    """
    import matplotlib as mpl

    if not isinstance(fig, Figure):
        raise ValueError(f"fig must be a matplotlib.figure.Figure, got {type(fig).__name__}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stamp = f"{os.getpid()}.{uuid.uuid4().hex[:8]}"
    if pdf is None:
        pdf = os.environ.get("LNF_FIGURE_PDF", "1").strip().lower() not in ("0", "false", "no", "off")
    targets = [(path, "png")] + ([(vector_path(path), "pdf")] if pdf else [])
    temps = [(target.with_name(f".{target.name}.{stamp}.tmp.{fmt}"), target, fmt) for target, fmt in targets]
    dpi = savefig_kwargs.pop("dpi", _DPI)  # of the PNG, and of the images embedded in the PDF
    try:
        for tmp, _, fmt in temps:
            with mpl.rc_context({"pdf.fonttype": 42}):
                fig.savefig(tmp, format=fmt, dpi=dpi, **savefig_kwargs)
        for tmp, target, _ in temps:
            os.replace(tmp, target)
    except BaseException:
        for tmp, _, _ in temps:
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
        raise
    return path
