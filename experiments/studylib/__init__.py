"""Shared machinery of the benchmark studies in experiments/: Hydra multiruns, CSV tables, charts.

Each study script runs `python -m lnf.train -m ...` (and `python -m lnf.evaluate -m ...`) as Hydra
multiruns into ``outputs/studies/<study>/<sweep>/<job>/``, collects every job's ``metrics.json`` with
its overrides into one CSV, and draws its charts from that CSV. A sweep whose jobs all finished with the
same command is reused (pass --fresh to rerun it); a folder that is not reused is renamed
``<sweep>.replaced-<UTC time>``, never deleted (:func:`keep_aside`). Every study takes
``--scene`` (any ``conf/experiment/<scene>.yaml``, or ``<DIR>/experiment/<scene>.yaml`` of a config folder of
your own given with ``--config-dir DIR``, as ``python -m lnf.train --config-dir DIR`` takes it), ``--full`` (the
full study: the default model size and training budget) and ``--smoke`` (tiny settings, for the test suite).

No study names a scene: what a study does on a scene it asks the scene object, built from the composed
experiment config (:meth:`Study.scene_object`): which baselines can run it (``Scene.baselines()``), whether
its full-order reference is expensive (``Scene.expensive_reference``), its stability release cases
(``Scene.stability_cases()``). Without ``--scene`` a study runs the experiment named like the training
config's default scene (:func:`default_experiment`).

The package, by concern: :mod:`.study` (a study's settings and command line), :mod:`.jobs` (running its jobs),
:mod:`.results` (collecting their rows), :mod:`.charts` and :mod:`.tables` (its figures and summary). Studies use
it as ``from experiments import studylib as S``.
"""
from experiments.studylib.charts import (COLORS, DODGE, DODGE_FRACTION, DODGE_NOTE, LABELS, LINESTYLES, MARKERS,
                                         QUANTITY_WORDS, caption, dodged, figure_legend, legend_outside, log_axes,
                                         metric_label, place_labels, plot_marking_failures, pyplot, readable_log_ticks,
                                         save_figure, ticks_at)
from experiments.studylib.jobs import CONF, ROOT, JobWorker, job_environment, run_in_worker
from experiments.studylib.results import collect, dominates, keep_aside, method_of, pareto_mask, write_csv
from experiments.studylib.study import (CHARTED, COMMON, METHODS, REDUCED_NEURAL, SMOKE_DATA, SMOKE_NEURAL, Study,
                                        config_file, default_experiment, experiment_file, parse_args)
from experiments.studylib.tables import fmt, markdown_table, per_axis, write_text_atomic
