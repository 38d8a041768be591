"""Operator Inference (OpInf): a non-intrusive reduced model fitted to snapshots, through the `opinf` package.

The comparison a model-reduction user makes first (Peherstorfer & Willcox 2016; Kramer, Peherstorfer &
Willcox 2024): a POD basis of the training snapshots and a polynomial (by default up to cubic) discrete-time
reduced model

    s_{k+1} = c + A s_k + H (s_k ⊗ s_k) + G (s_k ⊗ s_k ⊗ s_k)   (+ B u, with per-trajectory loads u)

whose operators are fitted by Tikhonov-regularised least squares to the reduced training pairs (s_k, s_{k+1}).
Nothing of the scene's physics enters; each least-squares fit takes milliseconds (the POD's SVD dominates).

What it reads is more than our model does: the fields q and velocities q̇ of the training trajectories on
the fine grid (every point, every training sample), where lnf learns from masked coarse observations. A
snapshot is x = [q, σ q̇] flattened over the points (σ makes both halves count alike, see :meth:`fit`),
centred on the training mean; the POD is weighted by each point's mass (quadrature weight × density, when
given: "mass-weighted POD"), so that s = Vᵀ W (x − x̄) is the L² projection. The reduced coordinates are
scaled by their largest training magnitude, so one grid of regularizers suits every scene.

The form (``operators``: "cA", "cAH" or "cAHG") and the regularizer λ are chosen on the validation trajectories:
each candidate is rolled out from their initial snapshots over the training horizon (the samples k <
``train_times``) and the one with the smallest median relative L² field error there is kept (rollouts that
diverge count as infinite). Predictions of a diverged trajectory (a non-finite reduced state, or one more than
``blowup`` times the largest training one) are NaN from that step on, as lnf marks its own diverged rollouts.

Plain numpy; `opinf` (the ``baselines`` extra: ``pip install -e ".[baselines]"``) is imported when first used.
"""
from __future__ import annotations

import itertools
import time
import warnings
from dataclasses import dataclass
from typing import Any, Optional, Sequence

import numpy as np

#: the default candidate forms (opinf operator strings) and regularizers λ (on the scaled reduced states)
OPERATORS = ("cA", "cAH", "cAHG")
REGULARIZERS = tuple(float(x) for x in np.logspace(-8, 2, 11))


def import_opinf() -> Any:
    """The `opinf` package, or an ImportError naming the extra that installs it."""
    try:
        import opinf
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise ImportError("the Operator Inference baseline needs the `opinf` package (>= 0.6): install lnf's "
                          "`baselines` extra, `pip install -e \".[baselines]\"` (the `dev` extra includes it), or "
                          "`pip install \"opinf>=0.6\"`") from exc
    return opinf


@dataclass
class Prediction:
    """Predicted trajectories. fields, velocities (n, T, N, A) float64 (NaN from the step a trajectory diverged);
    diverged_step (n,) int (−1: finite throughout); rollout_seconds (n,) wall-clock of each reduced rollout
    (the discrete model's steps, not the decoding); decode_seconds (n,) wall-clock of decoding each trajectory's
    fields and velocities at its T samples on the N points."""

    fields: np.ndarray
    velocities: np.ndarray
    diverged_step: np.ndarray
    rollout_seconds: np.ndarray
    decode_seconds: np.ndarray

    @property
    def diverged(self) -> np.ndarray:
        return self.diverged_step >= 0


@dataclass
class Selection:
    """One validated candidate: its form, regularizer, validation error (median over trajectories of the relative
    L² field error within the training horizon; inf when a rollout diverged) and the number that diverged."""

    operators: str
    regularizer: float
    val_error: float
    diverged: int


class OperatorInference:
    """POD + polynomial discrete-time OpInf model on snapshots [q, σ q̇] of the fine-grid fields.

    Args:
        rank: r, the number of POD modes (≥ 1; at most the number of training snapshots and of unknowns).
        operators: candidate forms, opinf operator strings over "c" (constant), "A" (linear), "H" (quadratic),
            "G" (cubic); "B" (the load input) is added to each when the trajectories have per-trajectory loads.
        regularizers: candidate Tikhonov parameters λ ≥ 0 (``opinf.lstsq.L2Solver``).
        velocity_weight: σ in x = [q, σ q̇]; None (default): the ratio of the training fluctuations' norms
            ‖q − q̄‖_W / ‖q̇ − q̄̇‖_W, so that both halves of a snapshot carry the same energy in the POD.
        blowup: a reduced state larger than `blowup` × the largest training one counts as diverged.
        svdsolver: the POD's SVD (``opinf.basis.PODBasis``): "dense", "randomized" (seeded: the same basis every
            run), or "auto" (default): dense (the economy SVD, cost rows × columns²) when the snapshot matrix has at
            most 5,000 rows or columns, else randomized. On the cantilever's 16,384 × 1,600 snapshots the dense SVD
            took 16 s and the randomized one 57 s (one thread each, same machine, same run).
    """

    def __init__(self, rank: int, operators: Sequence[str] = OPERATORS, regularizers: Sequence[float] = REGULARIZERS,
                 velocity_weight: Optional[float] = None, blowup: float = 100.0, svdsolver: str = "auto") -> None:
        if isinstance(rank, bool) or not isinstance(rank, (int, np.integer)) or rank < 1:
            raise ValueError(f"OperatorInference rank must be an integer ≥ 1, got {rank!r}")
        self.rank = int(rank)
        self.operators = tuple(str(o) for o in operators)
        if not self.operators or any(not o or set(o) - set("cAHG") for o in self.operators):
            raise ValueError(f"operators must be non-empty strings over 'c', 'A', 'H', 'G', got {operators!r}")
        self.regularizers = tuple(float(x) for x in regularizers)
        if not self.regularizers or not all(np.isfinite(x) and x >= 0 for x in self.regularizers):
            raise ValueError(f"regularizers must be finite numbers ≥ 0, got {regularizers!r}")
        if velocity_weight is not None and not (np.isfinite(velocity_weight) and velocity_weight > 0):
            raise ValueError(f"velocity_weight must be a finite number > 0, got {velocity_weight!r}")
        if not (np.isfinite(blowup) and blowup > 1):
            raise ValueError(f"blowup must be a finite number > 1, got {blowup!r}")
        if svdsolver not in ("auto", "dense", "randomized"):
            raise ValueError(f"svdsolver must be 'auto', 'dense' or 'randomized', got {svdsolver!r}")
        self.velocity_weight, self.blowup, self.svdsolver = velocity_weight, float(blowup), svdsolver
        self.basis: Any = None
        self.model: Any = None
        self.selection: Optional[Selection] = None
        self.candidates: list[Selection] = []
        self.fit_seconds = float("nan")
        self.shape: Optional[tuple[int, int]] = None  # (N, A) of the fields
        self.n_inputs = 0

    # -- snapshots ------------------------------------------------------------------------------
    def _snapshots(self, fields: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """(n, T, N, A) each → (D, n·T) columns x = [q, σ q̇] − x̄ (x̄ = 0 before fit sets it)."""
        n, T = fields.shape[:2]
        q = np.asarray(fields, dtype=np.float64).reshape(n * T, -1)
        v = np.asarray(velocities, dtype=np.float64).reshape(n * T, -1) * self.sigma
        return (np.concatenate([q, v], axis=1) - self.mean).T

    def encode(self, fields: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Reduced (scaled) states (n, T, r) of fields and velocities (n, T, N, A)."""
        n, T = fields.shape[:2]
        return (self.basis.compress(self._snapshots(fields, velocities)) / self.scale).T.reshape(n, T, self.rank)

    def decode(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fields and velocities (…, N, A) of reduced states (…, r)."""
        lead = states.shape[:-1]
        x = (self.basis.entries @ (states.reshape(-1, self.rank).T * self.scale)).T + self.mean
        half = x.shape[1] // 2
        return (x[:, :half].reshape(*lead, *self.shape), (x[:, half:] / self.sigma).reshape(*lead, *self.shape))

    # -- fitting --------------------------------------------------------------------------------
    def fit(self, fields: np.ndarray, velocities: np.ndarray, train_times: int, val_fields: np.ndarray,
            val_velocities: np.ndarray, point_weights: Optional[np.ndarray] = None,
            metric_weights: Optional[np.ndarray] = None, controls: Optional[np.ndarray] = None,
            val_controls: Optional[np.ndarray] = None) -> "OperatorInference":
        """Fit the basis on the training samples k < `train_times`, then every candidate (form × λ), and keep
        the one with the smallest validation error within the training horizon.

        Args:
            fields, velocities: training trajectories (n, T, N, A) on N points (only k < train_times is read).
            train_times: the training horizon in samples (≥ 2: a pair (s_k, s_{k+1}) at least).
            val_fields, val_velocities: validation trajectories (m, T', N, A), T' ≥ train_times.
            point_weights: (N,) weights of the POD's inner product (mass: quadrature weight × density); default
                equal.
            metric_weights: (N,) weights of the validation field error (lnf's metric: the points' quadrature
                weights); default equal.
            controls, val_controls: the loads of the training and validation trajectories, or None (both or
                neither): constant per trajectory (n, c), (m, c), or input series (n, ≥T, c), (m, ≥T', c) sampled
                with the fields (e.g. ``Scene.input_signals``), of which each step s_k → s_{k+1} is given the
                inputs at both ends (u_k, u_{k+1}): a first-order hold, exact for a linear response to piecewise-linear
                loads.
        """
        opinf = import_opinf()
        start = time.perf_counter()
        fields, velocities = np.asarray(fields), np.asarray(velocities)
        if fields.ndim != 4 or velocities.shape != fields.shape:
            raise ValueError(f"fields and velocities must be (n, T, N, A) alike, got {fields.shape} and "
                             f"{velocities.shape}")
        n, T, N, A = fields.shape
        train_times = int(train_times)
        if not 2 <= train_times <= T:
            raise ValueError(f"train_times must be in [2, {T}] (a pair of samples at least), got {train_times}")
        if val_fields.shape[2:] != (N, A) or val_velocities.shape != val_fields.shape \
                or val_fields.shape[1] < train_times:
            raise ValueError(f"validation fields must be (m, ≥{train_times}, {N}, {A}) like the velocities, got "
                             f"{val_fields.shape} and {val_velocities.shape}")
        if (controls is None) != (val_controls is None):
            raise ValueError("give the loads of both the training and the validation trajectories, or of neither")
        snapshots, unknowns = n * train_times, 2 * N * A
        if self.rank > min(snapshots, unknowns):
            raise ValueError(f"OperatorInference rank {self.rank} is larger than the training snapshots allow: "
                             f"{snapshots} snapshots ({n} trajectories × {train_times} samples) of {unknowns} "
                             f"values each give at most {min(snapshots, unknowns)} POD modes")
        self.shape = (N, A)
        w = np.ones(N) if point_weights is None else np.asarray(point_weights, dtype=np.float64)
        if w.shape != (N,) or not np.all(np.isfinite(w)) or not np.all(w > 0):
            raise ValueError(f"point_weights must be (N,) = ({N},) finite and > 0")
        w = w / w.sum()
        q, v = fields[:, :train_times].astype(np.float64), velocities[:, :train_times].astype(np.float64)
        wa = np.repeat(w, A)

        def fluctuation(x: np.ndarray) -> float:
            flat = x.reshape(-1, N * A)
            return float(np.sqrt(np.sum((flat - flat.mean(0)) ** 2 * wa)))

        if self.velocity_weight is not None:
            self.sigma = float(self.velocity_weight)
        else:
            nq, nv = fluctuation(q), fluctuation(v)
            self.sigma = nq / nv if nv > 0 and nq > 0 else 1.0
        self.mean = 0.0
        X = self._snapshots(q, v)
        self.mean = X.mean(axis=1)
        X = X - self.mean[:, None]
        solver = self.svdsolver if self.svdsolver != "auto" else "dense" if min(X.shape) <= 5000 else "randomized"
        options = {"random_state": 0} if solver == "randomized" else {}
        self.basis = opinf.basis.PODBasis(num_vectors=self.rank, weights=np.concatenate([wa, wa]), svdsolver=solver,
                                          **options).fit(X)
        self.basis_seconds = time.perf_counter() - start
        self.scale = 1.0
        S = self.basis.compress(X)  # (r, n·train_times)
        self.scale = float(np.max(np.abs(S))) or 1.0
        S = (S / self.scale).reshape(self.rank, n, train_times)
        self.state_bound = self.blowup * float(np.max(np.linalg.norm(S, axis=0)))
        states = S[:, :, :-1].reshape(self.rank, -1)
        nextstates = S[:, :, 1:].reshape(self.rank, -1)
        inputs = None
        self.n_inputs = 0
        if controls is not None:
            # loads enter affinely as B u (a load that changes the stiffness would need a bilinear term, not fitted)
            steps = self._step_inputs(controls, n, train_times, "controls")  # (n, train_times − 1, m)
            self.n_inputs = steps.shape[2]
            inputs = steps.transpose(2, 0, 1).reshape(self.n_inputs, -1)
        val_states0 = self.encode(val_fields[:, :1], val_velocities[:, :1])[:, 0]
        self.candidates = []
        best = None
        for ops, lam in itertools.product(self.operators, self.regularizers):
            ops_in = ops + ("B" if controls is not None else "")
            model = opinf.models.DiscreteModel(ops_in, solver=opinf.lstsq.L2Solver(regularizer=lam))
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "underdetermined" at λ = 0 with few snapshots: λ > 0 is selected then
                model.fit(states, nextstates, inputs=inputs)
            self.model = model
            pred = self._predict_from(val_states0, train_times, val_controls)
            err = _rel_l2(pred.fields, val_fields[:, :train_times], metric_weights)
            err = np.where(np.isfinite(err), err, np.inf)
            cand = Selection(ops_in, lam, float(np.median(err)), int(pred.diverged.sum()))
            self.candidates.append(cand)
            if best is None or cand.val_error < best[0].val_error:
                best = (cand, model)
        self.selection, self.model = best
        self.fit_seconds = time.perf_counter() - start
        return self

    @staticmethod
    def _step_inputs(controls: np.ndarray, n: int, n_times: int, name: str) -> np.ndarray:
        """The inputs (n, n_times − 1, m) of the steps k → k+1: constant loads (n, c) as they are (m = c), input
        series (n, ≥ n_times, c) as (u_k, u_{k+1}) (m = 2c)."""
        u = np.asarray(controls, dtype=np.float64)
        if u.ndim == 2 and u.shape[0] == n:
            return np.repeat(u[:, None, :], max(n_times - 1, 1), axis=1)
        if u.ndim == 3 and u.shape[0] == n and u.shape[1] >= n_times:
            u = u[:, :n_times]
            return np.concatenate([u[:, :-1], u[:, 1:]], axis=2) if n_times > 1 else np.concatenate([u, u], axis=2)
        raise ValueError(f"{name} must be loads per trajectory ({n}, c) or input series ({n}, ≥{n_times}, c), got "
                         f"shape {u.shape}")

    # -- prediction -----------------------------------------------------------------------------
    def _predict_from(self, states0: np.ndarray, n_times: int, controls: Optional[np.ndarray]) -> Prediction:
        m = states0.shape[0]
        S = np.full((m, n_times, self.rank), np.nan)
        step = np.full(m, -1, dtype=int)
        seconds, decode_seconds = np.zeros(m), np.zeros(m)
        fields = np.empty((m, n_times, *self.shape))
        velocities = np.empty_like(fields)
        steps = self._step_inputs(controls, m, n_times, "controls") if self.n_inputs else None
        if steps is not None and steps.shape[2] != self.n_inputs:
            raise ValueError(f"controls give {steps.shape[2]} inputs per step, the model was fitted with "
                             f"{self.n_inputs} (loads per trajectory and input series are not interchangeable)")
        for i in range(m):
            u = None if steps is None else steps[i].T  # (m, n_times − 1)
            t0 = time.perf_counter()
            with np.errstate(all="ignore"):
                traj = self.model.predict(states0[i], n_times, inputs=u).T  # (n_times, r)
            seconds[i] = time.perf_counter() - t0
            bad = ~np.all(np.isfinite(traj), axis=1)
            with np.errstate(all="ignore"):  # a blown-up state overflows its norm: counted as diverged
                bad |= ~(np.linalg.norm(traj, axis=1) <= self.state_bound)
            if bad.any():
                step[i] = int(np.argmax(bad))
                traj[step[i]:] = np.nan
            S[i] = traj
            t0 = time.perf_counter()
            with np.errstate(invalid="ignore"):
                fields[i], velocities[i] = self.decode(traj)
            decode_seconds[i] = time.perf_counter() - t0
        return Prediction(fields, velocities, step, seconds, decode_seconds)

    def predict(self, fields0: np.ndarray, velocities0: np.ndarray, n_times: int,
                controls: Optional[np.ndarray] = None) -> Prediction:
        """Roll out the selected model from initial fields and velocities (n, N, A) for `n_times` samples (the
        first is the projected initial snapshot); `controls` when the model was fitted with loads, in the form it
        was fitted with ((n, c), or input series (n, ≥ n_times, c))."""
        if self.model is None:
            raise RuntimeError("OperatorInference.predict before fit")
        if (controls is None) != (self.n_inputs == 0):
            raise ValueError("this model was fitted " + ("with" if self.n_inputs else "without") +
                             " loads: give `controls` " + ("(n, c) or (n, T, c)" if self.n_inputs else "None"))
        if int(n_times) < 1:
            raise ValueError(f"n_times must be ≥ 1, got {n_times!r}")
        s0 = self.encode(np.asarray(fields0)[:, None], np.asarray(velocities0)[:, None])[:, 0]
        return self._predict_from(s0, int(n_times), controls)

    def describe(self) -> dict[str, Any]:
        """The selected candidate and the fit, as a JSON-able record."""
        sel = self.selection
        return {"rank": self.rank, "operators": sel.operators if sel else None,
                "regularizer": sel.regularizer if sel else None, "val_error": sel.val_error if sel else None,
                "velocity_weight": getattr(self, "sigma", None), "fit_seconds": self.fit_seconds,
                "basis_seconds": getattr(self, "basis_seconds", None),
                "candidates": [vars(c) for c in self.candidates]}


def _rel_l2(pred: np.ndarray, true: np.ndarray, weights: Optional[np.ndarray]) -> np.ndarray:
    """lnf.metrics.field_rel_l2 over every sample (n,), with default equal weights."""
    from lnf.metrics import field_rel_l2

    N = true.shape[2]
    w = np.full(N, 1.0 / N) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    with np.errstate(invalid="ignore", over="ignore"):
        return field_rel_l2(pred, np.asarray(true, dtype=np.float64), w, np.ones(true.shape[1], dtype=bool))
