"""The embedding φ(q̃, X): a SIREN whose sine layers are shifted by a hypernetwork of the code q̃.

    h_0 = X,   h_l = sin(w0 · (W_l h_{l-1} + b_l + s_l(q̃))),   φ = W_out h_L + b_out,
    [s_1, …, s_L] = hypernet(q̃).

Besides the value, :meth:`ModulatedSiren.jet` returns exact derivatives from one batched
forward-mode pass (hand-derived Taylor propagation, no nested autograd):

- ``J = ∂φ/∂q̃``          (B, N, A, d)
- ``H = ∂²φ/∂q̃²``        (B, N, A, d, d)
- ``G = ∇_X φ``           (B, N, A, dim_B)
- ``GJ = ∂(∇_X φ)/∂q̃``   (B, N, A, dim_B, d)

Everything is plain differentiable torch, so backpropagating through a jet (the unrolled reduction in
training) gives exact parameter gradients of those derivatives.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import torch
from torch import Tensor, nn

from lnf.utils import NUMBER_RULES, require


@dataclass
class FieldJet:
    """φ and its requested derivatives at points X for codes q̃ (shapes in the module docstring)."""

    value: Tensor
    J: Optional[Tensor] = None
    H: Optional[Tensor] = None
    G: Optional[Tensor] = None
    GJ: Optional[Tensor] = None


class _Taylor:
    """Value, first derivatives along D directions, second derivatives along P direction pairs.

    value (B, *S); first (B, D, *S) or None; second (B, P, *S) or None: the direction axis is axis 1. Pairs are (i, j) indices into the D directions.
    """

    __slots__ = ("v", "d1", "d2")

    def __init__(self, v: Tensor, d1: Optional[Tensor], d2: Optional[Tensor]) -> None:
        self.v, self.d1, self.d2 = v, d1, d2


class _SinCos(torch.autograd.Function):
    """(sin x, cos x) with a backward that reuses both instead of recomputing them (torch's sin and cos each
    evaluate the other function of their saved input again); forward-mode (jvp) and vmap rules included, so
    torch.func transforms of a jet still work."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x: Tensor) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        return torch.sin(x), torch.cos(x)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Tensor], output: tuple[Tensor, Tensor]) -> None:
        sin, cos = output
        ctx.save_for_backward(sin, cos)
        ctx.save_for_forward(sin, cos)

    @staticmethod
    def backward(ctx: Any, grad_sin: Optional[Tensor], grad_cos: Optional[Tensor]) -> Tensor:  # type: ignore[override]
        sin, cos = ctx.saved_tensors
        grad = grad_sin * cos if grad_sin is not None else torch.zeros_like(cos)
        return grad if grad_cos is None else torch.addcmul(grad, grad_cos, sin, value=-1.0)

    @staticmethod
    def jvp(ctx: Any, tangent: Tensor) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        sin, cos = ctx.saved_tensors
        return cos * tangent, -sin * tangent


def _may_overwrite(t: Tensor) -> bool:
    """Whether an intermediate of values-only decoding may be updated in place: no autograd records it and no
    torch.func transform (vmap, jvp, grad) wraps it."""
    return not (torch.is_grad_enabled() and t.requires_grad) and not torch._C._are_functorch_transforms_active()


def _latent_pairs(d: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(d) for j in range(i, d)]


class ModulatedSiren(nn.Module):
    """Shift-modulated SIREN φ(q̃, X) with a hypernetwork q̃ ↦ shifts.

    Args:
        latent_dim: d, dimension of q̃ (≥ 1).
        in_dim: dim_B, dimension of material points X.
        out_dim: dim_A, dimension of the field value.
        width: features per sine layer.
        depth: number of sine layers (≥ 1).
        w0: SIREN frequency ν0; multiplies pre-activations and therefore also the shifts.
        hyper_width: width of the hypernetwork's hidden layers.
        hyper_depth: number of hidden tanh layers in the hypernetwork (0 = linear hypernetwork).
        hyper_init_scale: scale of the hypernetwork's output weights at initialisation (its bias is 0).
    """

    def __init__(
        self,
        latent_dim: int = 1,
        in_dim: int = 2,
        out_dim: int = 1,
        width: int = 256,
        depth: int = 2,
        w0: float = 30.0,
        hyper_width: int = 128,
        hyper_depth: int = 0,
        hyper_init_scale: float = 0.1,
    ) -> None:
        super().__init__()
        for name, value, low in [("latent_dim", latent_dim, 1), ("in_dim", in_dim, 1), ("out_dim", out_dim, 1),
                                 ("width", width, 1), ("depth", depth, 1), ("hyper_width", hyper_width, 1),
                                 ("hyper_depth", hyper_depth, 0)]:
            require(f"model.{name}", value, NUMBER_RULES.get(f"model.{name}", ("int", low, None, "")))
        require("model.w0", w0, (">", 0, None, "the SIREN frequency"))
        self.latent_dim, self.in_dim, self.out_dim = int(latent_dim), int(in_dim), int(out_dim)
        self.width, self.depth, self.w0 = int(width), int(depth), float(w0)

        self.layers = nn.ModuleList()
        for l in range(self.depth):
            fan_in = self.in_dim if l == 0 else self.width
            layer = nn.Linear(fan_in, self.width)
            # SIREN initialisation (Sitzmann et al. 2020) with w0 applied in every layer.
            bound = 1.0 / fan_in if l == 0 else math.sqrt(6.0 / fan_in) / self.w0
            nn.init.uniform_(layer.weight, -bound, bound)
            nn.init.uniform_(layer.bias, -1.0 / math.sqrt(fan_in), 1.0 / math.sqrt(fan_in))
            self.layers.append(layer)
        self.out = nn.Linear(self.width, self.out_dim)
        bound = math.sqrt(6.0 / self.width) / self.w0
        nn.init.uniform_(self.out.weight, -bound, bound)
        nn.init.zeros_(self.out.bias)

        hyper: list[nn.Linear] = []
        fan_in = self.latent_dim
        for _ in range(int(hyper_depth)):
            hyper.append(nn.Linear(fan_in, int(hyper_width)))
            fan_in = int(hyper_width)
        head = nn.Linear(fan_in, self.width * self.depth)
        with torch.no_grad():
            head.weight.mul_(hyper_init_scale)
            head.bias.zero_()
        hyper.append(head)
        self.hyper = nn.ModuleList(hyper)

    # ------------------------------------------------------------------ Taylor propagation helpers
    @staticmethod
    def _linear(x: _Taylor, layer: nn.Linear, weight: Optional[Tensor] = None, bias: Optional[Tensor] = None) -> _Taylor:
        weight = layer.weight if weight is None else weight
        bias = layer.bias if bias is None else bias
        v = torch.nn.functional.linear(x.v, weight, bias)
        d1 = None if x.d1 is None else x.d1 @ weight.T
        d2 = None if x.d2 is None else x.d2 @ weight.T
        return _Taylor(v, d1, d2)

    @staticmethod
    def _activate(x: _Taylor, f: Tensor, df: Tensor, d2f: Tensor, left: Tensor, right: Tensor) -> _Taylor:
        """Chain rule for an elementwise function with values f, f', f'' at x.v."""
        d1 = None if x.d1 is None else df.unsqueeze(1) * x.d1
        d2 = None
        if x.d2 is not None:
            d2 = d2f.unsqueeze(1) * x.d1[:, left] * x.d1[:, right] + df.unsqueeze(1) * x.d2
        return _Taylor(f, d1, d2)

    def _hyper_jet(self, codes: Tensor, order: int) -> _Taylor:
        """Shifts (B, L·W) with derivatives along the d latent directions (order ≥ 1) and latent pairs (2)."""
        d = self.latent_dim
        pairs = _latent_pairs(d)
        left = torch.tensor([p[0] for p in pairs], device=codes.device)
        right = torch.tensor([p[1] for p in pairs], device=codes.device)
        d1 = torch.eye(d, dtype=codes.dtype, device=codes.device).expand(codes.shape[0], d, d) if order >= 1 else None
        d2 = codes.new_zeros(codes.shape[0], len(pairs), d) if order >= 2 else None
        x = _Taylor(codes, d1, d2)
        for layer in self.hyper[:-1]:
            x = self._linear(x, layer)
            t = torch.tanh(x.v)
            dt = 1.0 - t * t
            x = self._activate(x, t, dt, -2.0 * t * dt, left, right)
        return self._linear(x, self.hyper[-1])

    # ------------------------------------------------------------------ public API
    def shifts(self, codes: Tensor) -> Tensor:
        """Hypernetwork output (..., depth·width)."""
        return self._hyper_jet(codes, 0).v

    def forward(self, codes: Tensor, points: Tensor) -> Tensor:
        """φ(q̃, X): codes (B, d), points (N, dim_B) or (B, N, dim_B) → values (B, N, dim_A)."""
        return self.jet(codes, points, order=0).value

    def jet(self, codes: Tensor, points: Tensor, order: int = 1, spatial: bool = False) -> FieldJet:
        """φ and its derivatives in one forward-mode pass.

        Args:
            codes: q̃, (B, d).
            points: X, (N, dim_B) shared by the batch or (B, N, dim_B) per batch element.
            order: 0 → value; 1 → + J; 2 → + J, H.
            spatial: also return G = ∇_X φ (and GJ = ∂G/∂q̃ when order ≥ 1).
        """
        if codes.ndim != 2 or codes.shape[-1] != self.latent_dim:
            raise ValueError(f"codes must have shape (B, {self.latent_dim}), got {tuple(codes.shape)}")
        if points.ndim not in (2, 3) or points.shape[-1] != self.in_dim or points.shape[-2] == 0:
            raise ValueError(
                f"points must have shape (N, {self.in_dim}) or (B, N, {self.in_dim}) with N ≥ 1, got {tuple(points.shape)}"
            )
        B, d, W, nb, L = codes.shape[0], self.latent_dim, self.width, self.in_dim, self.depth
        n_lat = d if order >= 1 else 0
        n_sp = nb if spatial else 0
        n_dirs = n_lat + n_sp
        # second-derivative pairs: latent×latent (for H) then spatial×latent (for GJ)
        pairs = _latent_pairs(d) if order >= 2 else []
        n_ll = len(pairs)
        if spatial and order >= 1:
            pairs = pairs + [(n_lat + k, i) for k in range(nb) for i in range(d)]
        left = torch.tensor([p[0] for p in pairs], device=codes.device, dtype=torch.long)
        right = torch.tensor([p[1] for p in pairs], device=codes.device, dtype=torch.long)
        n_pairs = len(pairs)

        # w0 multiplies every pre-activation: fold it into the (small) shifts, weights and biases once
        w0 = self.w0
        hyp = self._hyper_jet(codes, min(order, 2))
        s = w0 * hyp.v.view(B, L, W)
        ds = None if hyp.d1 is None else w0 * hyp.d1.view(B, d, L, W)
        dds = None if hyp.d2 is None else w0 * hyp.d2.view(B, -1, L, W)
        trivial_pairs = n_pairs == 1 and n_dirs == 1  # d = 1 without X-derivatives: no gather needed

        if points.ndim == 2:
            points = points.unsqueeze(0)
        x = _Taylor(points, None, None)
        for l, layer in enumerate(self.layers):
            weight, bias = w0 * layer.weight, w0 * layer.bias
            if l == 0:
                v = torch.nn.functional.linear(points, weight, bias) + s[:, None, 0]
                N = v.shape[1]
                d1 = d2 = None
                if n_dirs:  # first layer: ∂z/∂q̃_i = ∂s_0/∂q̃_i and ∂z/∂X_k = W_0[:, k], both constant in X
                    parts = []
                    if n_lat:
                        parts.append(ds[:, :, 0, None, :].expand(B, n_lat, N, W))
                    if n_sp:
                        parts.append(weight.T[None, :, None, :].expand(B, nb, N, W))
                    d1 = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
                if n_pairs:  # latent×latent from the hypernetwork; spatial×latent vanish (z is affine in X)
                    parts = []
                    if n_ll:
                        parts.append(dds[:, :, 0, None, :].expand(B, n_ll, N, W))
                    if n_pairs > n_ll:
                        parts.append(v.new_zeros(B, n_pairs - n_ll, N, W))
                    d2 = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
                z = _Taylor(v, d1, d2)
            else:
                if x.d1 is None and _may_overwrite(x.v):  # values only: bias and shift in one pass, in place
                    z = _Taylor(torch.matmul(x.v, weight.T).add_(s[:, None, l] + bias), None, None)
                else:
                    z = self._linear(x, layer, weight=weight, bias=bias)
                    z.v = z.v + s[:, None, l]
                if n_lat:
                    shift_d1 = ds[:, :, l, None, :]
                    z.d1 = torch.cat([z.d1[:, :n_lat] + shift_d1, z.d1[:, n_lat:]], dim=1) if n_sp else z.d1 + shift_d1
                if n_ll:
                    shift_d2 = dds[:, :, l, None, :]
                    z.d2 = torch.cat([z.d2[:, :n_ll] + shift_d2, z.d2[:, n_ll:]], dim=1) if n_pairs > n_ll else z.d2 + shift_d2
            if z.d1 is None:  # values only (decoding): no cosine; without autograd, sin in place (no new buffer)
                inplace = _may_overwrite(z.v)
                x = _Taylor(z.v.sin_() if inplace else torch.sin(z.v), None, None)
                continue
            sin_z, cos_z = _SinCos.apply(z.v)
            c = cos_z.unsqueeze(1)
            d1 = c * z.d1
            d2 = None
            if z.d2 is not None:  # (sin)'' = −sin: d2 = cos·z'' − sin·z'_i z'_j
                prod = z.d1 * z.d1 if trivial_pairs else z.d1[:, left] * z.d1[:, right]
                d2 = torch.addcmul(c * z.d2, sin_z.unsqueeze(1), prod, value=-1.0)
            x = _Taylor(sin_z, d1, d2)
        y = self._linear(x, self.out)

        out = FieldJet(value=y.v)
        if y.d1 is not None:
            d1 = y.d1.movedim(1, -1)  # (B, N, A, D)
            out.J = d1[..., :n_lat] if n_lat else None
            out.G = d1[..., n_lat:] if n_sp else None
        if y.d2 is not None:
            d2 = y.d2.movedim(1, -1)  # (B, N, A, P)
            if n_ll:
                idx = torch.empty(d, d, dtype=torch.long, device=d2.device)
                for k, (i, j) in enumerate(pairs[:n_ll]):
                    idx[i, j] = idx[j, i] = k
                out.H = d2[..., idx.reshape(-1)].reshape(*d2.shape[:-1], d, d)
            if n_pairs > n_ll:
                out.GJ = d2[..., n_ll:].reshape(*d2.shape[:-1], nb, d)
        return out
