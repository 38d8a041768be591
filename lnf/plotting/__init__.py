"""Figures for the lifted-pendulum benchmark (the paper's Figure 3) and friends.

Pure functions of numpy arrays that return :class:`matplotlib.figure.Figure` objects.
Figures are built with ``Figure()`` directly, never through ``pyplot``: nothing needs a
display, no global figure registry fills up, and the process-wide backend is left alone
(PNG output goes through Agg regardless of the selected backend).

Public API
----------
- :func:`latent_and_energy_figure` -- latent q̃(t) predicted vs projected, energies predicted
  vs true, training horizon marked (Figure 3, top row).
- :func:`field_snapshots_figure` -- predicted field, true field and absolute error at a few
  times before/after the training horizon (Figure 3, bottom).
- :func:`figure3` -- both of the above in one figure, for a 1-, 2- or 3-D body, its fields given on a
  midpoint grid (``grid_shape``) or on scattered points (``points``: mesh nodes, random samples).
- :func:`default_snapshot_indices` -- evenly spaced sample indices on each side of the horizon.
- :func:`save_figure` -- atomic PNG write (200 dpi), with a vector PDF of the same stem beside it.

Modules: ``figures`` (the public figures), ``energy`` (latent and energy panels), ``fields`` (field snapshots on
grids, scattered points, 1-D and 3-D bodies), ``checks`` (argument validation), ``style``, ``save``.

Non-finite values in predictions (a diverged rollout) are plotted, not hidden and not fatal:
lines get gaps, images show masked pixels (or triangles touching a non-finite point) in grey, colour
limits use the finite values only.

Colour scales. Fields use a diverging map symmetric about 0, its limit the largest |value| of the true
field (or the 99th percentile of |predicted| where that is larger); predicted values beyond it saturate
and the colour bar gets an arrow. Errors |pred − true| use a light-to-dark sequential map (small errors
light), its limit the 99th percentile of the finite errors, so that one outlier (a corner, a diverging
patch) does not turn the rest of the panel into a single colour; where errors exceed it the colour bar
gets an arrow (``extend="max"``).

Energies. The energy panel shows the total energy E = T + V predicted against true over the whole range
(its drift is what a long rollout is judged by); a third panel shows the kinetic/potential exchange, over
the whole range when the series oscillate a few times only, else in a window of a few periods around the
training horizon (shaded on the total-energy panel), so that a 20 s rollout is no solid band.
"""
from __future__ import annotations

from lnf.plotting.figures import default_snapshot_indices, field_snapshots_figure, figure3, latent_and_energy_figure
from lnf.plotting.save import save_figure, vector_path
from lnf.plotting.style import _DPI, _subscript, ENERGY_KEYS  # noqa: F401  (_DPI, _subscript: the studies' and callbacks')

__all__ = [
    "latent_and_energy_figure",
    "field_snapshots_figure",
    "figure3",
    "default_snapshot_indices",
    "save_figure",
    "vector_path",
    "ENERGY_KEYS",
]
