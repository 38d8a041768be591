"""Tabulated decoding: φ(q̃, X_j) on a fixed set of points as a Chebyshev interpolant in the codes.

On fixed evaluation points X_1…X_N the decoder q̃ ↦ φ(q̃, X_j) is a smooth map ℝ^d → ℝ^{N×A}. For a small
latent dimension d it is interpolated once on a tensor-product Chebyshev grid of a box of codes (n^d decodings,
:class:`lnf.tabulated.ChebyshevTable`); decoding a frame is then one product of its n^d basis values with the
table's coefficients, (B, n^d) @ (n^d, N·A), instead of a pass through the network on every point.

The table never decides a result silently: its error is measured against the exact decoder at check codes
(seeded, uniform in the box) when it is built, and the nodes per axis double until the largest error, relative
to the largest field on the box, is below `tol`. Codes outside the box are decoded exactly; a table that cannot
meet `tol` within `max_nodes` or `max_bytes` is not used (``DecodingTable.build`` returns None and says why).
Shapes: codes (B, d); decoded fields (B, N, A).
"""
from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch
from numpy.polynomial import chebyshev as C
from torch import Tensor

from lnf.tabulated import ChebyshevTable

log = logging.getLogger("lnf.decoding_table")

DECODINGS = ("auto", "exact", "tabulated")


def check_decoding(value: Any, key: str = "decoding") -> None:
    """Refuse a `key` (``decoding`` of lnf.evaluate, ``evaluation.decoding`` of a training run) not in DECODINGS."""
    if value not in DECODINGS:
        raise ValueError(f"{key} must be one of {', '.join(DECODINGS)}, got {value!r}")


def _in_chunks(fn: Callable[[Tensor], Tensor], codes: Tensor, chunk: int) -> Tensor:
    """fn over codes (B, d), `chunk` rows at a time, concatenated along the rows."""
    return torch.cat([fn(codes[i:i + chunk]) for i in range(0, len(codes), chunk)])


class DecodingTable:
    """φ on fixed points, tabulated in q̃ on the box [low, high]^d (see the module docstring).

    Args:
        decode: the exact decoder on the fixed points, codes (B, d) → fields (B, N, A).
        low, high: the box of codes (d,) each.
        like: a tensor of the decoder's dtype and device.
        nodes: Chebyshev nodes per axis (the table holds nodes^d decodings).

    ``info`` records nodes per axis, the measured error, its tolerance and the build time [s].
    """

    def __init__(self, decode: Callable[[Tensor], Tensor], low: Sequence[float], high: Sequence[float],
                 like: Tensor, nodes: int, check: Optional[tuple[Tensor, ...]] = None, chunk: int = 32,
                 jacobian: Optional[Callable[[Tensor], Tensor]] = None) -> None:
        start = time.perf_counter()
        self.decode_exact, self.jacobian_exact, self.chunk = decode, jacobian, int(chunk)
        self.derivatives = jacobian is not None
        self.low = np.asarray(low, dtype=np.float64).reshape(-1)
        self.high = np.asarray(high, dtype=np.float64).reshape(-1)
        self.d, self.n = len(self.low), int(nodes)
        x = C.chebpts1(self.n)
        axes = [lo + (hi - lo) * (x + 1) / 2 for lo, hi in zip(self.low, self.high)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.d)
        values = self._decode(torch.as_tensor(grid, dtype=like.dtype, device=like.device))  # (n^d, N, A[, 1 + d])
        self.field_shape = tuple(values.shape[1:3])
        f_nodes = values.reshape(*([self.n] * self.d), -1).double().cpu().numpy()
        # ∂φ/∂q̃ is interpolated from its own exact values at the nodes: the derivative of the interpolant of φ would
        # amplify φ's rounding by about n²
        self.table = ChebyshevTable(f_nodes, self.low, self.high, like.dtype, like.device, derivatives=False,
                                    keep_float64=False)
        self.error = math.nan if check is None else self.relative_error(*check)
        self.info: dict[str, Any] = {"decoding_table_nodes": self.n, "decoding_table_error": self.error,
                                     "decoding_table_seconds": time.perf_counter() - start}

    def _decode(self, codes: Tensor) -> Tensor:
        """φ at codes (B, d): (B, N, A); with the jacobian, φ and ∂φ/∂q̃ stacked: (B, N, A, 1 + d)."""
        def one(q: Tensor) -> Tensor:
            value = self.decode_exact(q)
            return value if self.jacobian_exact is None else torch.cat([value[..., None], self.jacobian_exact(q)], -1)

        return _in_chunks(one, codes, self.chunk)

    @staticmethod
    def table_bytes(nodes: int, d: int, n_points: int, channels: int) -> int:
        """Coefficients (float64 while built) of a table of `nodes` per axis on N points × `channels` values each."""
        return int(nodes) ** int(d) * int(n_points) * int(channels) * 8

    @classmethod
    def build(cls, decode: Callable[[Tensor], Tensor], low: Sequence[float], high: Sequence[float], like: Tensor,
              n_points: int, field_dim: int, tol: float = 1e-5, min_nodes: int = 16, max_nodes: int = 256,
              max_bytes: int = 512 * 2 ** 20, check_codes: int = 32, budget: Optional[int] = None,
              jacobian: Optional[Callable[[Tensor], Tensor]] = None) -> "Optional[DecodingTable]":
        """The table with the fewest nodes per axis (doubling from `min_nodes`) whose error at `check_codes` · d
        check codes is ≤ `tol` (floored at 20 rounding units of the decoder's dtype); None, with the reason logged,
        when none of at most `max_nodes` per axis and `max_bytes` of coefficients meets it, or when building would
        cost more than `budget` decodings (e.g. the frames it would replace).

        `jacobian` (codes (B, d) → ∂φ/∂q̃ (B, N, A, d)): also tabulate the derivatives in the codes (interpolated
        from their exact values at the nodes), and hold them to `tol` as well, relative to the largest of them."""
        low_a, high_a = np.asarray(low, dtype=np.float64).reshape(-1), np.asarray(high, dtype=np.float64).reshape(-1)
        d = len(low_a)
        if not (np.isfinite(low_a).all() and np.isfinite(high_a).all() and (high_a > low_a).all()):
            log.info("tabulated decoding: no finite box of codes (low=%s, high=%s); decoding exactly",
                     low_a.tolist(), high_a.tolist())
            return None
        tol = max(float(tol), 20 * torch.finfo(like.dtype).eps)
        gen = torch.Generator().manual_seed(0)
        u = torch.rand(int(check_codes) * d, d, generator=gen, dtype=torch.float64).numpy()
        codes = torch.as_tensor(low_a + (high_a - low_a) * u, dtype=like.dtype, device=like.device)
        spent, n, table = len(codes), int(min_nodes), None
        check = None
        channels = field_dim * (1 + d) if jacobian is not None else field_dim  # φ, and ∂φ/∂q̃ beside it
        while n <= int(max_nodes) and cls.table_bytes(n, d, n_points, channels) <= int(max_bytes):
            if budget is not None and spent + n ** d > int(budget):
                log.info("tabulated decoding: a table of %d^%d nodes costs more decodings than the %d frames it would "
                         "replace; decoding exactly", n, d, budget)
                return None
            if check is None:
                check = (codes, _in_chunks(decode, codes, 32))
                if jacobian is not None:
                    check += (_in_chunks(jacobian, codes, 32),)
            table = cls(decode, low_a, high_a, like, n, check=check, jacobian=jacobian)
            spent += n ** d
            if table.error <= tol:
                return table
            n *= 2
        last = "" if table is None else f" (the largest, {table.n} nodes per axis, reached {table.error:.2g})"
        log.info("tabulated decoding: no table within %d nodes per axis and %d MB meets the tolerance %.2g%s; "
                 "decoding exactly", max_nodes, int(max_bytes) >> 20, tol, last)
        return None

    def relative_error(self, codes: Tensor, exact: Tensor, exact_jacobian: Optional[Tensor] = None) -> float:
        """max over `codes` of ‖table − φ‖₂, relative to the largest ‖φ‖₂ among them (and the same of ∂φ/∂q̃, when
        the table has derivatives and `exact_jacobian` is given: the larger of the two)."""
        def rel(approx: Tensor, ref: Tensor) -> float:
            diff = (approx.double() - ref.double()).flatten(1).norm(dim=-1).max()
            return float(diff / ref.double().flatten(1).norm(dim=-1).max().clamp_min(torch.finfo(torch.float64).tiny))

        if not self.derivatives:
            return rel(self.interpolate(codes), exact)
        value, jac = self.interpolate_jet(codes)
        return max(rel(value, exact), rel(jac, exact_jacobian) if exact_jacobian is not None else 0.0)

    def inside(self, codes: Tensor) -> Tensor:
        """(B,) whether each code lies in the box."""
        lo = torch.as_tensor(self.low, dtype=codes.dtype, device=codes.device)
        hi = torch.as_tensor(self.high, dtype=codes.dtype, device=codes.device)
        return ((codes >= lo) & (codes <= hi)).all(-1)

    def interpolate(self, codes: Tensor) -> Tensor:
        """The interpolant at codes inside the box (B, d) → (B, N, A) (clamped to the box)."""
        if self.derivatives:
            return self.interpolate_jet(codes)[0]
        return self.table(codes).reshape(codes.shape[0], *self.field_shape)

    def interpolate_jet(self, codes: Tensor) -> tuple[Tensor, Tensor]:
        """The interpolant and its derivatives in the codes at codes inside the box (B, d): (B, N, A) and
        (B, N, A, d). Only for a table built with derivatives."""
        if not self.derivatives:
            raise ValueError("this decoding table holds no derivatives in the codes (build it with a jacobian)")
        out = self.table(codes).reshape(codes.shape[0], *self.field_shape, 1 + self.d)
        return out[..., 0], out[..., 1:]

    def __call__(self, codes: Tensor) -> Tensor:
        """φ at codes (B, d) → (B, N, A): from the table inside the box, exactly outside it."""
        inside = self.inside(codes)
        if bool(inside.all()):
            return self.interpolate(codes)
        out = torch.empty((codes.shape[0], *self.field_shape), dtype=self.table.coef.dtype, device=codes.device)
        if bool(inside.any()):
            out[inside] = self.interpolate(codes[inside])
        out[~inside] = self.decode_exact(codes[~inside])
        return out


def code_box(codes: Tensor, *more: Tensor, margin: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The box [low, high] (d,) of the finite rows of `codes` (B, d) and of any `more` ranges, widened by `margin`
    of its width on each side (at least 1e-6 when the codes do not vary)."""
    rows = [c.reshape(-1, codes.shape[-1]).double() for c in (codes, *more)]
    stack = torch.cat([r[torch.isfinite(r).all(-1)] for r in rows])
    if stack.numel() == 0:
        return np.full(codes.shape[-1], np.nan), np.full(codes.shape[-1], np.nan)
    low, high = stack.min(0).values.cpu().numpy(), stack.max(0).values.cpu().numpy()
    pad = np.maximum(margin * (high - low), 1e-6)
    return low - pad, high + pad


class TabulatedField:
    """φ on the fixed points of a :class:`DecodingTable` built with derivatives, in the interface of the
    embedding that :func:`lnf.reduction.reduce` iterates on (``latent_dim``, ``__call__``, ``jet`` of order ≤ 1):
    the reduction ρ̃ of many frames on the same points reads φ and ∂φ/∂q̃ from the table instead of a network jet.
    Codes outside the box get the exact jet (`exact_jet`)."""

    def __init__(self, table: DecodingTable, points: Tensor, exact_jet: Callable[[Tensor], tuple[Tensor, Tensor]]
                 ) -> None:
        if not table.derivatives:
            raise ValueError("TabulatedField needs a decoding table built with derivatives (a jacobian)")
        self.table, self.points, self.exact_jet = table, points, exact_jet
        self.latent_dim = table.d

    def _check(self, points: Tensor) -> None:
        if points is not self.points and (points.shape != self.points.shape or not torch.equal(points, self.points)):
            raise ValueError(f"this tabulated field holds φ on its {tuple(self.points.shape)} points only, got points "
                             f"{tuple(points.shape)}")

    def __call__(self, codes: Tensor, points: Tensor) -> Tensor:
        return self.jet(codes, points).value

    def jet(self, codes: Tensor, points: Tensor, order: int = 1, spatial: bool = False) -> Any:
        from lnf.siren import FieldJet

        if order > 1 or spatial:
            raise ValueError("a tabulated field has first derivatives in the codes only (order ≤ 1, spatial=False)")
        self._check(points)
        inside = self.table.inside(codes)
        if bool(inside.all()):
            value, jac = self.table.interpolate_jet(codes)
        else:
            value = torch.empty((codes.shape[0], *self.table.field_shape), dtype=codes.dtype, device=codes.device)
            jac = torch.empty((*value.shape, self.latent_dim), dtype=codes.dtype, device=codes.device)
            if bool(inside.any()):
                value[inside], jac[inside] = self.table.interpolate_jet(codes[inside])
            value[~inside], jac[~inside] = self.exact_jet(codes[~inside])
        return FieldJet(value=value, J=jac if order >= 1 else None)
