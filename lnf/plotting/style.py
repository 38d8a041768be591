"""Colours, line styles, sizes and label formats shared by lnf's figures."""
from __future__ import annotations

ENERGY_KEYS = ("kinetic_pred", "potential_pred", "kinetic_true", "potential_true")

_FIELD_CMAP = "RdBu_r"
_ERROR_CMAP = "magma_r"  # sequential, light (small errors) to dark (large errors)
_MASK_COLOR = "0.6"  # grey for NaN/inf pixels
_HORIZON_STYLE = dict(color="0.35", linestyle=":", linewidth=1.2)
_DPI = 200
_ERROR_PERCENTILE = 99.0  # the error colour scale ends at this percentile of the finite errors
_MAX_PERIODS = 8  # more oscillations of the energies than this: kinetic/potential drawn in a window
_WINDOW_PERIODS = 4  # ... of this many periods around the training horizon
_ERROR_LABEL = "absolute error\n|pred − true|\n(field's units)"
_X_LABELS = ("X₁", "X₂", "X₃")  # body (material) coordinates


def _format_t(t: float) -> str:
    return f"{t:.3g}"


def _subscript(n: int) -> str:
    return str(n).translate(str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉"))
