"""Tabulated reduced dynamics: the pulled-back M̃(q̃) and Ṽ(q̃) as Chebyshev interpolants on a box of codes.

The reduced Lagrangian L̃ = ½ q̃̇ᵀ M̃(q̃) q̃̇ − Ṽ(q̃) of a conservative scene depends on the codes through
M̃ and Ṽ only, two smooth functions of d numbers. For small d they can be interpolated once, offline,
on a tensor-product Chebyshev grid of the box [low, high]^d (the "offline/online" split of model-order
reduction), and a rollout then evaluates a polynomial instead of φ and its jet at every quadrature point.

The interpolants of M̃ and Ṽ define a Lagrangian system of their own (the derivatives ∂M̃/∂q̃, ∂Ṽ/∂q̃ are
those of the interpolating polynomials, not separately fitted), so symplectic integrators keep their
bounded energy error; its distance to the exact pullback is the interpolation error, which the table
measures at check points when it is built and drives below `tol` by doubling the nodes per axis.

Outside the box (a state the training codes never reached) the exact pullback is evaluated for those rows,
so the result never depends on the box, only the speed does. A scene with damping or loads is tabulated where its
force is separated (``GeneralizedForce.separated()``: f = −c(X) u̇ + Σ_k a_k(t) s_k(X)): then the reduced force
τ̃ = −D̃(q̃) q̃̇ + Σ_k a_k(t) ∂W_k/∂q̃ has parts that depend on q̃ alone, and the table holds D̃ and W_k beside M̃, Ṽ.
Shapes: q̃, q̃̇, p̃ (B, d).
"""
from __future__ import annotations

import contextlib
import logging
import math
import time
from typing import Any, Iterator, Optional, Sequence

import numpy as np
import torch
from numpy.polynomial import chebyshev as C
from torch import Tensor

from lnf.dynamics import ReducedDynamics
from lnf.dynamics_kind import TABULATED
from lnf.reduction import solve_mass

log = logging.getLogger(__name__)

#: the table's box: the training codes' range widened by this fraction of its span on each side (``dynamics.margin``)
TABLE_MARGIN = 0.25
#: a rollout that reads more than this share of its rows off the box (from the exact pullback) says why, and how far
TABLE_OFF_BOX_WARN = 0.02
#: a table whose relative error at its check points stays above this (its nodes capped by dynamics.max_nodes or
#: dynamics.max_table_points) is not used: the model rolls out on the exact pullback (LagrangianNeuralField.dynamics).
#: The soft body's d = 4 table (16⁴ nodes, when every axis grew alike) was 11 % off and 13 of 16 test rollouts
#: diverged at step 2; the d = 3, 4 tables of the cantilevers (1.4e-5 … 1.5e-3) roll out as the exact pullback does
TABLE_MAX_ERROR = 1e-2
#: a table still more than TABLE_MAX_ERROR off at dynamics.max_table_points may grow to this many times as many
#: nodes (within dynamics.max_nodes) before the model leaves it, where the exact pullback costs a jet per step (when
#: every axis grew alike, the soft body's d = 3 table was 1.7 % off at 32³ and 1.0e-3 off at 64³)
TABLE_ROUGH_GROWTH = 4
#: from this d on a table is evaluated as one matrix product on the tensor-product basis (rows × Π_i n_i, at most
#: TENSOR_BASIS_ELEMENTS at a time) instead of axis by axis: at d = 3 (32³ nodes, 160 rows) 3× faster on one CPU
#: thread, at d = 4 (16⁴) 5× (python -m experiments.bench_table); at d = 2 not steadily faster: it keeps its rounding
TENSOR_BASIS_FROM_DIM, TENSOR_BASIS_ELEMENTS = 3, 1 << 22
#: a table that misses its tolerance doubles the nodes of each axis whose coefficient tail is at least this share of
#: the worst axis's (ChebyshevTable.axis_tails): the others are resolved already, and more nodes there only cost
TABLE_REFINE_SHARE = 0.1
#: the nodes per axis start at dynamics.min_nodes, halved (not below 4) while they would leave less than this factor
#: of room under dynamics.max_table_points: at d = 4, 16⁴ is the whole cap, and the soft body needs 128 nodes along
#: one axis and 8 along the others (its d = 4 table was 11 % off at 16⁴)
TABLE_START_ROOM = 8
#: once built, each axis's series is cut after its last coefficient weighing at least one of these shares of the
#: table's error (or tolerance), the largest share whose cut table stays within it: an evaluation costs Π_i n_i per
#: row, and the soft body's d = 3 table needs 8 nodes on its narrow axes to be built, fewer to be read
TABLE_TRIM_SHARES = (1e-2, 1e-3, 1e-4)
#: a table above its tolerance (still within TABLE_MAX_ERROR) may be cut if its error grows by at most this fraction:
#: the soft body's d = 4 table, 4.1e-6 off at 128 × 8³ nodes against a tolerance of 1.2e-6, was read whole
TABLE_TRIM_SLACK = 0.1
#: a build that has taken longer than this [s] logs each round (the soft body's d = 4 table: minutes)
TABLE_LOG_SECONDS = 10.0


def force_separates(scene: Any) -> bool:
    """Whether `scene`'s forces let a table hold its reduced dynamics: none (conservative), or a generalized force
    whose ``separated()`` gives a :class:`lnf.scenes.base.SeparatedForce`."""
    if scene.is_conservative:
        return True
    from lnf.quadrature import Quadrature

    centre = torch.tensor([[(lo + hi) / 2 for lo, hi in scene.bounds]], dtype=torch.float64)
    force = scene.generalized_force(Quadrature(centre, torch.ones(1, dtype=torch.float64)))
    separate = getattr(force, "separated", None)
    return force is None or (separate is not None and separate() is not None)


def start_nodes(min_nodes: int, d: int, max_table_points: int) -> int:
    """The nodes per axis a table of d codes starts from: `min_nodes`, halved (not below 4) while they would leave
    less than :data:`TABLE_START_ROOM` × room under `max_table_points` to grow."""
    start = min_nodes
    while start > 4 and start ** d * TABLE_START_ROOM > max_table_points:
        start //= 2
    return start


def shape_text(nodes: Sequence[int], unit: str = "nodes") -> str:
    """'64 nodes per axis', or '128 × 8 × 8 nodes' where the axes differ."""
    if len(set(nodes)) == 1:
        return f"{nodes[0]} {unit} per axis"
    return " × ".join(map(str, nodes)) + f" {unit}"


def _symmetric_pairs(d: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(d) for j in range(i, d)]


class ChebyshevTable:
    """Tensor-product Chebyshev interpolant of vector-valued f: [low, high]^d → ℝ^c, with all first derivatives.

    Built from values `f_nodes` (n_1, …, n_d, c) at Chebyshev points of the first kind
    (``numpy.polynomial.chebyshev.chebpts1``), n_i on axis i (``nodes``; an axis along which f varies slowly needs
    fewer); :meth:`__call__` returns (B, 1 + d, c): the values and ∂f/∂q_i (i = 1…d) of the interpolating
    polynomial at q (B, d); (B, 1, c), the values only, when built with ``derivatives=False``.
    ``keep_float64=False`` keeps no float64 copy of the coefficients.
    """

    def __init__(self, f_nodes: np.ndarray, low: Sequence[float], high: Sequence[float],
                 dtype: torch.dtype = torch.float64, device: "torch.device | str" = "cpu",
                 derivatives: bool = True, keep_float64: bool = True) -> None:
        d = len(low)
        if f_nodes.ndim != d + 1 or min(f_nodes.shape[:d]) < 1:
            raise ValueError(f"f_nodes must have shape (n_1, …, n_{d}, c) for a box of {d} axes, got {f_nodes.shape}")
        lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        if not np.all(hi > lo):
            raise ValueError(f"table box needs high > low on every axis, got low={lo.tolist()}, high={hi.tolist()}")
        coef = np.asarray(f_nodes, dtype=np.float64)
        for axis, n in enumerate(f_nodes.shape[:d]):  # values at the nodes → coefficients, axis by axis
            inv_vander = np.linalg.inv(C.chebvander(C.chebpts1(n), n - 1))
            coef = np.moveaxis(np.tensordot(inv_vander, coef, axes=([1], [axis])), 0, axis)
        self._set_coefficients(coef, lo, hi, dtype, device, derivatives, keep_float64)

    def _set_coefficients(self, coef: np.ndarray, lo: np.ndarray, hi: np.ndarray, dtype: torch.dtype,
                          device: "torch.device | str", derivatives: bool, keep_float64: bool) -> None:
        """Hold the Chebyshev coefficients `coef` (n_1, …, n_d, c) of the values and those of their derivatives."""
        d = len(lo)
        self.d, self.channels, self._build = d, coef.shape[-1], (lo, hi, dtype, device, derivatives, keep_float64)
        #: coefficients per axis (the nodes it was built from, or fewer once cut: :meth:`truncated`); n: the most on
        #: any axis; size: their product (an evaluation's cost per channel)
        self.nodes = tuple(int(s) for s in coef.shape[:d])
        self.n, self.size = max(self.nodes), math.prod(self.nodes)
        blocks = [coef]
        for axis in range(d if derivatives else 0):  # ∂/∂q_axis = chebder along that axis × dx/dq
            der = C.chebder(coef, axis=axis) * (2.0 / (hi[axis] - lo[axis]))  # n_i − 1 terms (1, zero, for n_i = 1)
            pad = [(0, 0)] * coef.ndim
            pad[axis] = (0, self.nodes[axis] - der.shape[axis])
            blocks.append(np.pad(der, pad))
        packed = np.stack(blocks, axis=-2)  # (n_1, …, n_d, 1 + d, c), or (n_1, …, n_d, 1, c) without derivatives
        self.coef = torch.as_tensor(packed, dtype=dtype, device=device)
        self.coef64 = torch.as_tensor(packed, dtype=torch.float64, device=device) if keep_float64 else None
        self.center = torch.as_tensor((hi + lo) / 2, dtype=dtype, device=device)
        self.half = torch.as_tensor((hi - lo) / 2, dtype=dtype, device=device)
        self.k = torch.arange(self.n, dtype=dtype, device=device)

    def truncated(self, terms: Sequence[int]) -> "ChebyshevTable":
        """The interpolant with its values' series cut to the first `terms`[i] coefficients along axis i, its
        derivatives those of the cut series (so a table of M̃, Ṽ stays a Lagrangian system). Needs the float64
        coefficients (``keep_float64``)."""
        if self.coef64 is None:
            raise ValueError("truncated() needs the table's float64 coefficients (built with keep_float64=True)")
        cut = self.coef64[tuple(slice(0, max(1, int(t))) for t in terms)][..., 0, :].cpu().numpy()
        table = ChebyshevTable.__new__(ChebyshevTable)
        table._set_coefficients(cut, *self._build)
        return table

    def axis_profiles(self, weights: Optional[Tensor] = None) -> list[Tensor]:
        """Per axis i, (n_i,): the largest |coefficient| × `weights` (1 + d, c) at each degree k_i of that axis, over
        the other axes' degrees, the values and the derivatives (default weights: 1 / the largest of each column). A
        smooth f's coefficients decay with the degree: where an axis's profile ends far below its start, more nodes
        on it gain nothing, and its last degrees can be cut (:meth:`truncated`)."""
        coef = (self.coef64 if self.coef64 is not None else self.coef.double()).abs()
        if weights is None:
            scale = coef.amax(dim=tuple(range(self.d)), keepdim=True)  # per column; a column of round-off: none
            weights = 1.0 / scale.clamp_min(1e-8 * float(scale.max()) + 1e-300)
        magnitude = (coef * weights.to(coef)).flatten(self.d).amax(-1)  # (n_1, …, n_d)
        return [magnitude.amax(dim=tuple(a for a in range(self.d) if a != axis)) if self.d > 1 else magnitude
                for axis in range(self.d)]

    def axis_tails(self, weights: Optional[Tensor] = None) -> list[float]:
        """How well each axis is resolved: the top of its :meth:`axis_profiles` over the upper half of its degrees
        (k_i ≥ n_i / 2)."""
        return [float(profile[len(profile) // 2:].max()) for profile in self.axis_profiles(weights)]

    def scaled(self, q: Tensor) -> Tensor:
        """x ∈ [−1, 1]^d inside the box (B, d)."""
        return (q - self.center.to(q)) / self.half.to(q)

    def __call__(self, q: Tensor) -> Tensor:
        return self.evaluate(q, self.coef)

    def evaluate(self, q: Tensor, coef: Tensor) -> Tensor:
        return self.evaluate_scaled(self.scaled(q), coef)

    def evaluate_scaled(self, x: Tensor, coef: Tensor) -> Tensor:
        """The interpolant at scaled points x (B, d) (clamped to [−1, 1]): (B, 1 + d, c)."""
        x = x.clamp(-1.0, 1.0)
        basis = torch.cos(torch.acos(x).unsqueeze(-1) * self.k.to(x))  # T_k(x) = cos(k arccos x): (B, d, n)
        axes = [basis[:, axis, :n] for axis, n in enumerate(self.nodes)]  # (B, n_i) each
        if self.d == 1:
            return (axes[0] @ coef.reshape(self.nodes[0], -1)).reshape(x.shape[0], *coef.shape[1:])
        if self.d >= TENSOR_BASIS_FROM_DIM:
            flat, rows = coef.reshape(self.size, -1), max(1, TENSOR_BASIS_ELEMENTS // self.size)
            parts = []
            for start in range(0, x.shape[0], rows):  # Π_axis T_k(x_axis) over the nodes, in coef's row-major order
                weights = axes[0][start:start + rows]
                for axis in range(1, self.d):
                    weights = (weights[:, :, None] * axes[axis][start:start + rows, None, :]).reshape(len(weights), -1)
                parts.append(weights @ flat)
            return torch.cat(parts).reshape(x.shape[0], *coef.shape[self.d:])
        out = torch.einsum("bk,k...->b...", axes[0], coef)
        for axis in range(1, self.d):
            out = torch.einsum("bk,bk...->b...", axes[axis], out)
        return out  # (B, 1 + d, c)


class TabulatedDynamics:
    """The pulled-back dynamics of `exact` with M̃ and Ṽ read from a Chebyshev table on [low, high]^d.

    Args:
        exact: the :class:`ReducedDynamics` to tabulate (its jet, scene and quadrature); evaluated off the box.
            A scene with damping or loads needs a separated force (:class:`lnf.scenes.base.SeparatedForce`).
        builder: the same dynamics in the precision the table is built from (default `exact`; a float64
            copy keeps the derivatives of the interpolant clean of float32 rounding).
        low, high: the box of codes (d,) each, e.g. the training codes' range widened by a margin.
        tol: target relative interpolation error of M̃ and of g̃ = ∂Ṽ/∂q̃ (and of a force's D̃ and ∂W/∂q̃) at check
            points (relative to their largest magnitude on the box), floored at 10 rounding units of the rollout's dtype (1.2e-6 for
            float32); the nodes of the axes that need them double (:data:`TABLE_REFINE_SHARE`) from `min_nodes`
            (fewer from d = 4: :data:`TABLE_START_ROOM`) until it is met; then each axis's series is cut to the
            terms the tolerance needs (:data:`TABLE_TRIM_SHARES`).
        min_nodes, max_nodes: nodes per axis (the table holds Π_i n_i evaluations of the exact pullback).
        max_table_points: refuse tables larger than this (d ≥ 3 grows as nodes^d); use the exact dynamics.
            A table still more than :data:`TABLE_MAX_ERROR` off there grows up to :data:`TABLE_ROUGH_GROWTH` times.

    ``info`` records the nodes per axis, the achieved error and the build time [s].
    """

    kind = TABULATED
    #: rollouts run on one torch thread: an evaluation is a few hundred numbers (lnf.threads.one_torch_thread)
    small_tensors = True
    #: the table is built in batches of at most this many (code, quadrature point) pairs
    CHUNK_POINTS = 1 << 17

    def __init__(self, exact: ReducedDynamics, low: Sequence[float], high: Sequence[float], tol: float = 1e-7,
                 min_nodes: int = 16, max_nodes: int = 256, max_table_points: int = 65536, chunk: int = 256,
                 builder: Optional[ReducedDynamics] = None) -> None:
        separate = getattr(exact.force_fn, "separated", None)  # GeneralizedForce.separated, if the force has one
        self.separated = separate() if separate is not None else None
        if exact.force_fn is not None and self.separated is None:
            raise ValueError(f"dynamics=tabulated needs a conservative scene or a separated force; "
                             f"{type(exact.scene).__name__}'s damping or loads ({type(exact.force_fn).__name__}) do not "
                             "say how they separate (GeneralizedForce.separated() gives None). Use dynamics=lagrangian")
        low_t = torch.as_tensor(low, dtype=torch.float64).flatten()
        high_t = torch.as_tensor(high, dtype=torch.float64).flatten()
        if not (torch.isfinite(low_t).all() and torch.isfinite(high_t).all()):
            raise ValueError(f"the table box must be finite, got low={low_t.tolist()}, high={high_t.tolist()} "
                             "(a checkpoint saved before lnf tracked its training codes has no box: retrain it, "
                             "or pass low/high)")
        if not tol > 0:
            raise ValueError(f"dynamics.tol must be > 0, got {tol!r}")
        if int(min_nodes) < 2 or int(max_nodes) < int(min_nodes):
            raise ValueError(f"need 2 ≤ dynamics.min_nodes ≤ dynamics.max_nodes, got {min_nodes!r}, {max_nodes!r}")
        self.exact = exact
        self.builder = builder if builder is not None else exact
        self.d = int(low_t.numel())
        if int(min_nodes) ** self.d > int(max_table_points):
            raise ValueError(f"a table of latent dimension d = {self.d} needs at least {int(min_nodes) ** self.d} "
                             f"pullback evaluations (> dynamics.max_table_points = {max_table_points}); "
                             "use dynamics=lagrangian for this model")
        # codes per batch of exact evaluations: at most `chunk`, and at most CHUNK_POINTS codes × quadrature points
        # (a jet holds a few hundred numbers per code and point: 256 codes on a 16³ rule took 22 GB)
        self.chunk = max(1, min(int(chunk), self.CHUNK_POINTS // max(1, int(self.builder.density_weights.numel()))))
        self.controls: Optional[Tensor] = None  # per-trajectory load parameters (B, c) of a separated force
        ref = exact.density_weights
        self.dtype, self.device = ref.dtype, ref.device  # of the rollout
        build_dtype = self.builder.density_weights.dtype
        self.low, self.high = low_t.tolist(), high_t.tolist()
        self.pairs = _symmetric_pairs(self.d)
        m = len(self.pairs)
        loads = 0 if self.separated is None else int(self.separated.shapes.shape[0])
        #: the table's channels: M̃'s upper triangle (m), Ṽ, then for a separated force D̃'s upper triangle and W_k
        self.channels = m + 1 + (0 if self.separated is None else m + loads)
        self._damping = slice(m + 1, 2 * m + 1)
        self._loads = slice(2 * m + 1, 2 * m + 1 + loads)
        channel = {pair: c for c, pair in enumerate(self.pairs)}
        self.symmetric_index = torch.tensor([channel[(min(a, b), max(a, b))] for a in range(self.d) for b in range(self.d)],
                                            device=self.device)  # M̃_ab's channel, row-major (d²,)
        self._damping_index = self._damping.start + self.symmetric_index  # D̃_ab's channel, row-major (d²,)
        self._continue_off_box = False  # continued_off_box(): rows off the box read its edge, not the exact pullback
        self.fallback_rows = 0  # rows evaluated exactly because they left the box (diagnostics)
        self.evaluated_rows = 0
        start = time.perf_counter()
        # below ~10 rounding units of the rollout's precision the table cannot matter (nor be measured: the
        # builder's constants, e.g. a float32 model's quadrature, carry that rounding)
        tol = max(float(tol), 10 * torch.finfo(self.dtype).eps, 100 * torch.finfo(build_dtype).eps)
        check = self._check_points(64 * self.d, build_dtype)
        exact_check = self._exact_channels(check, self.builder)
        weights = self._weights(exact_check)
        nodes, error = [start_nodes(int(min_nodes), self.d, int(max_table_points))] * self.d, math.inf
        while True:
            self.table = ChebyshevTable(self._node_values(nodes), self.low, self.high, self.dtype, self.device)
            error = self._relative_error(check, exact_check)
            if time.perf_counter() - start > TABLE_LOG_SECONDS:  # a slow build says how it goes
                log.info("table of the reduced dynamics: %s, %.1e off the exact pullback (tol %.0e), %.0f s so far",
                         shape_text(nodes), error, tol, time.perf_counter() - start)
            cap = int(max_table_points) * (TABLE_ROUGH_GROWTH if error > TABLE_MAX_ERROR else 1)
            grown = [] if error <= tol else self._refined(nodes, int(max_nodes), cap, weights)
            if not grown:
                break
            nodes = grown
        built = list(self.table.nodes)
        self.table, error = self._trimmed(check, exact_check, error, tol, weights)
        if self.d == 1 and not (self._last_nodes[..., 0] > 0).all():  # M̃ at the nodes
            raise ValueError(f"M̃ is not positive on the table box {self.low}..{self.high} (φ is not an immersion "
                             "there); use dynamics=lagrangian or a smaller dynamics.margin")
        if self.d == 1 and self.separated is None:  # the scalar fast path: columns (M̃, Ṽ, ½ ∂M̃/∂q̃, ∂Ṽ/∂q̃), x = (q̃ − c) / h
            n = self.table.n
            coef = self.table.coef.reshape(n, 4)
            self._coef1 = torch.stack([coef[:, 0], coef[:, 1], 0.5 * coef[:, 2], coef[:, 3]], -1)
            self._center1, self._inv_half1 = float(self.table.center[0]), 1.0 / float(self.table.half[0])
            self._k1 = self.table.k
        self.info: dict[str, Any] = {"table_nodes": max(built), "table_shape": built, "table_points": math.prod(built),
                                     "table_terms": self.table.size, "table_terms_shape": list(self.table.nodes),
                                     "table_error": error, "table_tol": tol,
                                     "table_seconds": time.perf_counter() - start,
                                     "table_low": self.low, "table_high": self.high}
        if error > tol:
            log.warning(self._roughness_message(error, tol))

    def _trimmed(self, check: Tensor, exact: Tensor, error: float, tol: float,
                 weights: Tensor) -> tuple[ChebyshevTable, float]:
        """The table with each axis's series cut after its last coefficient of weight ≥ share × the target
        max(`tol`, (1 + :data:`TABLE_TRIM_SLACK`) × `error`) (`weights`: as :meth:`_relative_error` measures), for the
        first share of :data:`TABLE_TRIM_SHARES` whose error at the check points stays within the target; else the
        table as built, and its `error`."""
        target = max(tol, (1.0 + TABLE_TRIM_SLACK) * error)
        profiles = self.table.axis_profiles(weights)
        for share in TABLE_TRIM_SHARES:
            terms = []
            for profile in profiles:
                kept = (profile >= share * target).nonzero()
                terms.append(max(2, int(kept.max()) + 1) if len(kept) else 2)
            if tuple(terms) == self.table.nodes:
                break
            table = self.table.truncated(terms)
            cut_error = self._relative_error(check, exact, table)
            if cut_error <= target:
                return table, cut_error
        return self.table, error

    def _refined(self, nodes: list[int], max_nodes: int, cap: int, weights: Tensor) -> list[int]:
        """The next nodes per axis: doubled on every axis whose coefficient tail (:meth:`ChebyshevTable.axis_tails`)
        is within :data:`TABLE_REFINE_SHARE` of the worst axis's, the worst first, as far as `max_nodes` per axis
        and `cap` nodes in all allow; [] when no axis can grow. Where M̃ and Ṽ vary alike along every axis, all
        double (an isotropic table); the soft body's d = 3 codes span 6.7 along the first axis and 0.02–0.2 along
        the others, where degree 5 is enough: there only the first grows."""
        tails = self.table.axis_tails(weights)
        grown = list(nodes)
        for axis in sorted(range(self.d), key=lambda a: -tails[a]):
            if tails[axis] < TABLE_REFINE_SHARE * max(tails):
                break
            trial = grown[:axis] + [2 * grown[axis]] + grown[axis + 1:]
            if trial[axis] <= max_nodes and math.prod(trial) <= cap:
                grown = trial
        return grown if grown != nodes else []

    def _roughness_message(self, error: float, tol: float) -> str:
        """Why a table that misses its tolerance matters: φ's pullback wiggles in q̃; for d = 1, the range of the
        stiffness Ṽ''/M̃ on the box (by finite differences of the table's Ṽ') and how often it changes sign."""
        msg = (f"the pulled-back M̃ and Ṽ are not smooth in q̃: a Chebyshev table of "
               f"{shape_text(self.info['table_shape'])} reaches a "
               f"relative error of {error:.1e} (dynamics.tol {tol:.0e}). Rollouts read its interpolant; a pullback "
               "that wiggles in q̃ (an embedding that learned fine detail across its codes) often has regions of "
               "negative stiffness where rollouts diverge")
        if self.d == 1:
            q = np.linspace(self.low[0], self.high[0], 1025)
            with torch.no_grad():
                out = self.table(torch.as_tensor(q[:, None], dtype=self.dtype, device=self.device)).double().cpu()
            stiffness = np.gradient(out[:, 1, 1].numpy(), q)
            omega2 = stiffness / out[:, 0, 0].numpy()
            changes = int((np.diff(np.sign(stiffness)) != 0).sum())
            msg += (f"; on the box the stiffness Ṽ''/M̃ ranges over {omega2.min():.3g} … {omega2.max():.3g} 1/s² "
                    f"and changes sign {changes} times")
        return msg

    @contextlib.contextmanager
    def continued_off_box(self) -> Iterator[None]:
        """Within it, rows off the box read the table at the nearest point of the box (M̃, its slope and ∂Ṽ/∂q̃ held
        there: forces continue constant) instead of the exact pullback: no jet, and wrong off the box. For searches
        that try many rollouts and only need them to be bad there (the closure's shooting), not for results."""
        self._continue_off_box = True
        try:
            yield
        finally:
            self._continue_off_box = False

    def off_box_text(self, q: Tensor, fraction: float) -> str:
        """Why a rollout through states q (..., d) read `fraction` of its rows from the exact pullback: how far it
        ran past the box along each code, and what widens the box."""
        reach = self.table.scaled(q.reshape(-1, self.d).to(self.table.center)).abs().nan_to_num(0.0).amax(0).tolist()
        past = ", ".join(f"{r:.2g} along code {i + 1}" for i, r in enumerate(reach) if r > 1.0)
        where = (f"the rollout's codes reached, in half-widths of the box from its centre, {past}" if past else
                 "the rollout's recorded codes stayed in the box: its implicit solves' trial states left it")
        return (f"dynamics=tabulated: {fraction:.0%} of the rollout's evaluations lay off the table's box and were "
                f"read from the exact pullback (a jet each, slower): {where}. A wider box (dynamics.margin, a "
                f"fraction of the training codes' span added on each side) holds them at the cost of a larger table; "
                f"codes far past the training range are where the embedding was not trained")

    def __repr__(self) -> str:
        return (f"TabulatedDynamics(d={self.d}, {shape_text(self.table.nodes, 'terms')} of "
                f"{shape_text(self.info['table_shape'])}, "
                f"error={self.info['table_error']:.1e}, box={self.low}..{self.high})")

    # -- building ------------------------------------------------------------------------------------
    def _exact_channels(self, q: Tensor, dynamics: ReducedDynamics) -> Tensor:
        """(B, c + d + K d) of the exact pullback: the table's channels (M̃'s upper triangle, Ṽ, for a separated
        force D̃'s upper triangle and W_k), then g̃, then ∂W_k/∂q̃ (row-major (K, d))."""
        out = []
        a, b = zip(*self.pairs)
        with torch.no_grad():
            for i in range(0, q.shape[0], self.chunk):
                rows = q[i:i + self.chunk]
                mass, potential, gravity = dynamics.static_terms(rows)
                parts, tail = [mass[:, a, b], potential[:, None]], [gravity]
                if self.separated is not None:
                    damping, work, work_grad = dynamics.separated_terms(rows)
                    parts += [damping[:, a, b], work]
                    tail.append(work_grad.reshape(len(rows), -1))
                out.append(torch.cat(parts + tail, -1))
        return torch.cat(out, 0)

    def _node_values(self, nodes: Sequence[int]) -> np.ndarray:
        axes = [lo + (hi - lo) * (C.chebpts1(n) + 1) / 2 for n, lo, hi in zip(nodes, self.low, self.high)]
        mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.d)
        points = torch.as_tensor(mesh, dtype=self.builder.density_weights.dtype, device=self.device)
        values = self._exact_channels(points, self.builder)[:, : self.channels]
        self._last_nodes = values.double().cpu().numpy().reshape(*nodes, -1)
        return self._last_nodes

    def _check_points(self, count: int, dtype: torch.dtype) -> Tensor:
        gen = torch.Generator().manual_seed(0)
        u = torch.rand(count, self.d, generator=gen, dtype=torch.float64)
        lo, hi = torch.tensor(self.low, dtype=torch.float64), torch.tensor(self.high, dtype=torch.float64)
        return (lo + (hi - lo) * u).to(dtype).to(self.device)

    def _weights(self, exact: Tensor) -> Tensor:
        """(1 + d, c): 1 / the scale each part of the table is measured against in :meth:`_relative_error` (M̃'s
        entries, g̃ = ∂Ṽ/∂q̃, a force's D̃ entries and ∂W_k/∂q̃), from the exact values `exact` at the check points;
        0 for the parts it does not measure (Ṽ itself, ∂M̃/∂q̃, follow from them)."""
        m, c = len(self.pairs), self.channels
        weights = torch.zeros(1 + self.d, c, dtype=torch.float64)

        def inverse(part: Tensor, floor: float = 1e-20) -> float:  # the floors of _relative_error
            return 1.0 / max(float(part.abs().max()), floor)

        weights[0, :m] = inverse(exact[:, :m], 1e-300)
        weights[1:, m] = inverse(exact[:, c:c + self.d])
        if self.separated is not None:
            weights[0, self._damping] = inverse(exact[:, self._damping])
            weights[1:, self._loads] = inverse(exact[:, c + self.d:])
        return weights

    def _relative_error(self, q: Tensor, exact: Tensor, table: Optional[ChebyshevTable] = None) -> float:
        """max over M̃ entries and g̃ (and a force's D̃ entries and ∂W_k/∂q̃) of |table − exact| / max|exact| at the
        check points (in the table's float64; `table`: this one's by default)."""
        m, c = len(self.pairs), self.channels
        table = self.table if table is None else table

        def error(table: Tensor, truth: Tensor, floor: float = 1e-300) -> Tensor:
            return (table - truth).abs().max() / truth.abs().max().clamp_min(floor)

        out = table.evaluate(q.double(), table.coef64)
        # a flat Ṽ (|g̃| ≲ 1e-20): absolute
        errors = [error(out[:, 0, :m], exact[:, :m]), error(out[:, 1:, m], exact[:, c:c + self.d], 1e-20)]
        if self.separated is not None:
            work_grad = exact[:, c + self.d:].reshape(len(q), -1, self.d)  # (B, K, d)
            errors += [error(out[:, 0, self._damping], exact[:, self._damping], 1e-20),
                       error(out[:, 1:, self._loads].transpose(1, 2), work_grad, 1e-20)]
        return float(max(errors))

    # -- evaluation ----------------------------------------------------------------------------------
    def _raw(self, q: Tensor) -> Tensor:
        """(B, 1 + d, c) from the table (values, then ∂/∂q̃_i), from the exact pullback for rows off the box."""
        x = self.table.scaled(q)
        out = self.table.evaluate_scaled(x, self.table.coef)
        outside = (x.abs() > 1.0).any(-1)
        self.evaluated_rows += q.shape[0]
        if bool(outside.any()) and not self._continue_off_box:
            rows = outside.nonzero().flatten()
            self.fallback_rows += int(rows.numel())
            out = out.index_copy(0, rows, self._exact_parts(q[rows]).to(out))
        return out

    def _scalar(self, q: Tensor) -> Optional[Tensor]:
        """d = 1 inside the box: (B, 4) columns (M̃, Ṽ, ½ M̃', Ṽ') in few operations (a rollout's hot path);
        None if a row is off the box (the caller takes the general path). M̃ > 0 on the box was checked."""
        x = (q - self._center1) * self._inv_half1
        if float(x.abs().max()) > 1.0:
            return None
        self.evaluated_rows += q.shape[0]
        # the basis of ChebyshevTable.evaluate_scaled without its clamp and reshapes: x is inside [−1, 1] here,
        # and this runs several times per step (through evaluate_scaled it measured 32 µs instead of 23 µs)
        return torch.cos(torch.acos(x) * self._k1) @ self._coef1

    def _parts(self, q: Tensor, out: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(M̃ (B, d, d), ∂M̃/∂q̃_k (B, k, d, d), Ṽ (B,), ∂Ṽ/∂q̃ (B, d)), from the table's `out` where given."""
        out = self._raw(q) if out is None else out
        m = len(self.pairs)
        full = out[:, :, self.symmetric_index].reshape(*out.shape[:2], self.d, self.d)
        return full[:, 0], full[:, 1:], out[:, 0, m], out[:, 1:, m]

    def _force(self, out: Tensor, v: Tensor, t: float) -> Tensor:
        """τ̃ = −D̃ q̃̇ + Σ_k a_k(t) ∂W_k/∂q̃ (B, d) of a separated force, from the table's `out` at q̃."""
        damping = out[:, 0, self._damping_index].reshape(-1, self.d, self.d)
        amplitudes = self.separated.amplitudes(t, self.controls, v.shape[0]).to(v)  # (B, K)
        return (-torch.einsum("bij,bj->bi", damping, v)
                + torch.einsum("bik,bk->bi", out[:, 1:, self._loads], amplitudes))

    def _exact_parts(self, q: Tensor) -> Tensor:
        """The table's layout (B, 1 + d, c) from the exact pullback (its values and ∂M̃/∂q̃ from
        :meth:`ReducedDynamics.static_terms_with_mass_slope`)."""
        with torch.no_grad():
            mass, potential, gravity, slope = self.exact.static_terms_with_mass_slope(q)
            a, b = zip(*self.pairs)
            value = torch.cat([mass[:, a, b], potential[:, None]], -1)
            rows = torch.cat([slope[:, :, a, b], gravity[:, :, None]], -1)  # (B, d, m + 1)
            if self.separated is not None:  # D̃'s slope is never read: zeros
                damping, work, work_grad = self.exact.separated_terms(q)
                value = torch.cat([value, damping[:, a, b], work], -1)
                rows = torch.cat([rows, torch.zeros_like(rows[..., :len(a)]), work_grad.transpose(1, 2)], -1)
        return torch.cat([value[:, None], rows], 1)

    def _solve(self, mass: Tensor, rhs: Tensor) -> Tensor:
        """M̃⁻¹ rhs (B, d), NaN where M̃ is singular (a division for d = 1)."""
        if self.d == 1:
            m = mass[:, :, 0]
            return torch.where(m > 0, rhs / m, torch.full_like(rhs, float("nan")))
        return solve_mass(mass, rhs)

    def mass_matrix(self, q: Tensor) -> Tensor:
        return self._parts(q)[0]

    def potential_energy(self, q: Tensor) -> Tensor:
        return self._parts(q)[2]

    def momentum(self, q: Tensor, v: Tensor) -> Tensor:
        return torch.einsum("bij,bj->bi", self.mass_matrix(q), v)

    def velocity(self, q: Tensor, p: Tensor) -> Tensor:
        return self._solve(self.mass_matrix(q), p)

    def acceleration(self, q: Tensor, v: Tensor, t: float = 0.0, extra_force: Optional[Tensor] = None) -> Tensor:
        """q̃̈ = M̃⁻¹(−c̃ − g̃ [+ τ̃] [+ `extra_force` (B, d)]), c̃_i = Σ_jk (∂_k M̃_ij − ½ ∂_i M̃_jk) q̃̇_j q̃̇_k (B, d)."""
        if self.separated is not None:
            out = self._raw(q)
            force = self._force(out, v, t)
            extra_force = force if extra_force is None else force + extra_force
            return self._general_acceleration(q, v, extra_force, out)
        if self.d == 1:  # q̃̈ = −(½ M̃' q̃̇² + Ṽ') / M̃
            cols = self._scalar(q)
            if cols is not None:
                rhs = torch.addcmul(cols[:, 3:], cols[:, 2:3], v * v)
                return (-rhs if extra_force is None else extra_force - rhs) / cols[:, :1]
            out = self._raw(q)
            mass, rhs = out[:, :1, :1], -0.5 * out[:, 1, :1] * v * v - out[:, 1, 1:]
        else:
            return self._general_acceleration(q, v, extra_force)
        return self._solve(mass, rhs if extra_force is None else rhs + extra_force)

    def _general_acceleration(self, q: Tensor, v: Tensor, extra_force: Optional[Tensor],
                              out: Optional[Tensor] = None) -> Tensor:
        mass, dmass, _, grad = self._parts(q, out)
        dm_v = torch.einsum("bkij,bj->bik", dmass, v)  # Σ_j ∂_k M̃_ij v_j
        rhs = -torch.einsum("bik,bk->bi", dm_v, v) + 0.5 * torch.einsum("bijk,bj,bk->bi", dmass, v, v) - grad
        return self._solve(mass, rhs if extra_force is None else rhs + extra_force)

    def hamiltonian_derivatives(self, q: Tensor, p: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        """(q̃̇ = M̃⁻¹p̃, −∂H/∂q̃ [+ τ̃] = ½ q̃̇ᵀ ∂_k M̃ q̃̇ − ∂_k Ṽ [+ τ̃]) (B, d) each."""
        if self.separated is not None:
            out = self._raw(q)
            mass, dmass, _, grad = self._parts(q, out)
            v = self._solve(mass, p)
            return v, 0.5 * torch.einsum("bkij,bi,bj->bk", dmass, v, v) - grad + self._force(out, v, t)
        if self.d == 1:
            cols = self._scalar(q)
            if cols is not None:
                v = p / cols[:, :1]
                return v, torch.addcmul(-cols[:, 3:], cols[:, 2:3], v * v)
            out = self._raw(q)
            v = self._solve(out[:, :1, :1], p)
            return v, 0.5 * out[:, 1, :1] * v * v - out[:, 1, 1:]
        mass, dmass, _, grad = self._parts(q)
        v = self._solve(mass, p)
        return v, 0.5 * torch.einsum("bkij,bi,bj->bk", dmass, v, v) - grad

    def energies(self, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """(T̃, Ṽ) of the tabulated system, each (...,) for q̃, q̃̇ (..., d)."""
        shape = q.shape[:-1]
        q2, v2 = q.reshape(-1, self.d), v.reshape(-1, self.d)
        mass, _, potential, _ = self._parts(q2)
        kinetic = 0.5 * torch.einsum("bi,bij,bj->b", v2, mass, v2)
        return kinetic.reshape(shape), potential.reshape(shape)
