"""POD-Galerkin: the linear special case of our model, φ(q̃, X) = m(X) + Φ(X) q̃ (docs/method.md §7.3), and its
quadratic-manifold extension φ = m + Φ q̃ + Ψ(X)[q̃, q̃] (``quadratic=true``).

The mean m and the k modes Φ are L²-orthonormal functions of X, stored as coefficients in a tensor
basis of normalised Legendre polynomials on the box B (so they can be evaluated, and differentiated in
X, anywhere: the model is as discretization-agnostic as ours). They come from an SVD of the training
snapshots: each masked training frame is first fitted in that basis by (ridge) least squares on its
observed points; because the basis is L²-orthonormal, the SVD of the coefficient matrix is the POD of
the fields in L². The reduction ρ is the exact least-squares projection on the observed points, and the
dynamics are the same pulled-back :class:`lnf.dynamics.ReducedDynamics` as ours (J = Φ, H = 0).

With ``quadratic=true`` the embedding also has a symmetric quadratic term Ψ(X)[q̃, q̃], fitted by ridge least squares
to what the k modes leave of each training frame, as a function of its POD coordinates (a quadratic manifold). That
residual is L²-orthogonal to the modes, so Ψ is too, and ρ stays the projection onto Φ; the pulled-back dynamics see
the curvature (J = Φ + 2Ψ[q̃, ·], H = 2Ψ): the intrusive quadratic-manifold reduced model of geometrically
nonlinear structures, with the scene's own Lagrangian.
"""
from __future__ import annotations

import logging
from typing import Optional

import numpy as np
import torch
from numpy.polynomial import legendre
from torch import Tensor, nn

from lnf.quadrature import QuadratureRule
from lnf.reduced_model import ReducedModel, as_field
from lnf.reduction import project_velocity
from lnf.scenes.base import Scene
from lnf.siren import FieldJet
from lnf.utils import require

log = logging.getLogger("lnf.pod")


class LegendreBasis:
    """Tensor products of L²-normalised Legendre polynomials of degree ≤ `degree` per axis on `bounds`.

    ``values(points)`` → (..., N, n_basis); ``gradients(points)`` → (..., N, n_basis, dim_B); float64 numpy.
    """

    def __init__(self, bounds: list[list[float]], degree: int) -> None:
        require("model.degree", degree)
        self.bounds = np.asarray(bounds, dtype=np.float64)
        self.degree = int(degree)
        self.dim = len(self.bounds)
        n = np.arange(self.degree + 1)
        width = self.bounds[:, 1] - self.bounds[:, 0]
        # ∫_lo^hi (c P_n(t(x)))² dx = 1  with t = 2(x − lo)/(hi − lo) − 1
        self.scale = np.sqrt((2 * n + 1) / 2.0)[None, :] * np.sqrt(2.0 / width)[:, None]  # (dim, p+1)
        # column n of `deriv` holds the Legendre coefficients of P_n'
        self.deriv = np.zeros((self.degree + 1, self.degree + 1))
        for k in range(1, self.degree + 1):
            self.deriv[:k, k] = legendre.legder(np.eye(self.degree + 1)[k])[:k]

    @property
    def size(self) -> int:
        return (self.degree + 1) ** self.dim

    def multi_indices(self) -> np.ndarray:
        """(n_basis, dim) polynomial degrees of each basis function, in the order of :meth:`values`."""
        grids = np.meshgrid(*[np.arange(self.degree + 1)] * self.dim, indexing="ij")
        return np.stack([g.reshape(-1) for g in grids], axis=-1)

    def _axes(self, points: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        t = 2.0 * (points - lo) / (hi - lo) - 1.0
        vals, ders = [], []
        for k in range(self.dim):
            V = legendre.legvander(t[..., k], self.degree)  # (..., N, p+1)
            vals.append(V * self.scale[k])
            ders.append((V @ self.deriv) * self.scale[k] * (2.0 / (hi[k] - lo[k])))
        return vals, ders

    @staticmethod
    def _outer(factors: list[np.ndarray]) -> np.ndarray:
        out = factors[0]
        for f in factors[1:]:
            out = (out[..., :, None] * f[..., None, :]).reshape(*out.shape[:-1], -1)
        return out

    def values(self, points: np.ndarray) -> np.ndarray:
        return self._outer(self._axes(np.asarray(points, dtype=np.float64))[0])

    def gradients(self, points: np.ndarray) -> np.ndarray:
        vals, ders = self._axes(np.asarray(points, dtype=np.float64))
        return np.stack([self._outer([ders[j] if j == k else vals[j] for j in range(self.dim)])
                         for k in range(self.dim)], axis=-1)


class LinearEmbedding(nn.Module):
    """φ(q̃, X) = Σ_b B_b(X) (m_b + Σ_i A_bi q̃_i): the mean `mean` (n_basis, A) and modes `modes` (n_basis, A, d)
    are buffers (set by :meth:`PODGalerkin.fit_to_observations`). Same call and ``jet`` signature as
    :class:`lnf.siren.ModulatedSiren`; J = Φ(X), H = 0. With a quadratic part `quad` (n_basis, A, d, d), symmetric in
    its last two axes (zero unless set), φ gains Ψ(X)[q̃, q̃]: J = Φ + 2Ψ q̃, H = 2Ψ."""

    #: its modes have equal L² norms: a unit of any code is the same size of field (ReducedModel.code_span_floor)
    commensurate_codes = True

    def __init__(self, bounds: list[list[float]], latent_dim: int, out_dim: int, degree: int) -> None:
        super().__init__()
        self.basis = LegendreBasis(bounds, degree)
        self.latent_dim, self.out_dim, self.in_dim = int(latent_dim), int(out_dim), len(bounds)
        self.register_buffer("mean", torch.zeros(self.basis.size, out_dim))
        self.register_buffer("modes", torch.zeros(self.basis.size, out_dim, latent_dim))
        self.register_buffer("quad", torch.zeros(self.basis.size, out_dim, latent_dim, latent_dim))
        self._register_load_state_dict_pre_hook(_zero_quadratic_part, with_module=True)
        self._cache: dict = {}
        self._active: Optional[tuple] = None

    def __getstate__(self) -> dict:
        """A copy or pickle leaves the basis cache behind (it may hold tensors a torch.func transform wrapped, which
        cannot be copied: ``copy.deepcopy`` of a tabulated model failed on them)."""
        state = dict(super().__getstate__())
        state["_cache"], state["_active"] = {}, None
        return state

    @torch.no_grad()
    def set_subspace(self, mean: "np.ndarray | Tensor", modes: "np.ndarray | Tensor",
                     quad: "np.ndarray | Tensor | None" = None) -> None:
        """The mean (n_basis, A), modes (n_basis, A, d) and quadratic part (n_basis, A, d, d) or None (zero), in the
        Legendre basis."""
        self.mean.copy_(torch.as_tensor(mean))
        self.modes.copy_(torch.as_tensor(modes))
        self.quad.copy_(torch.as_tensor(quad) if quad is not None else torch.zeros_like(self.quad))
        self._cache.clear()

    def project(self, points: Tensor, values: Tensor, density: Tensor) -> Tensor:
        """argmin_q̃ Σ_j ω0(X_j) ‖m(X_j) + Φ(X_j) q̃ − q_j‖²: the least-squares codes (B, d) of `values` (B, N, A) at
        `points`, ω0 = `density` (N,) or (B, N) (on the modes alone: the quadratic part is orthogonal to them)."""
        zero = values.new_zeros(values.shape[0], self.latent_dim)
        jet = self.jet(zero, points, order=1)
        weights = density.expand(jet.value.shape[:2]) / points.shape[-2]
        return project_velocity(jet.J, weights, values - jet.value)

    @staticmethod
    def _plain(points: Tensor) -> Tensor:
        """`points` itself where a torch.func transform wrapped it (``points.to(codes)`` under ``jvp``, as the
        tabulated pullback's derivatives do): the basis is constant in the codes. A batched (vmapped) set of points,
        whose unwrapped shape differs, is refused rather than read whole."""
        from torch._C import _functorch

        plain = points
        while _functorch.is_functorch_wrapped_tensor(plain):
            plain = _functorch.get_unwrapped(plain)
        if plain.shape != points.shape:
            raise ValueError(f"the POD basis cannot be evaluated on points batched by a torch.func transform "
                             f"(shape {tuple(points.shape)} inside, {tuple(plain.shape)} outside)")
        return plain

    def _coefficients(self) -> tuple[LegendreBasis, Tensor, Tensor, Optional[Tensor]]:
        """(basis, mean, modes, quadratic part or None where it is zero) on the basis up to the highest degree any
        coefficient uses: the per-frame fits cap the degree (a 3-D body's degree-12 basis of 2197 functions held
        coefficients up to degree 4, 125 functions), and the rest are zero to rounding (below 1e-10 of the largest).
        Recomputed when a buffer changes (set_subspace, load_state_dict)."""
        tensors = (self.mean, self.modes, self.quad)
        try:
            key = tuple((t.data_ptr(), t._version, t.dtype, t.device) for t in tensors)
        except RuntimeError:  # inference tensors have no version counter: recompute
            key = None
        if key is None or self._active is None or self._active[0] != key:
            # plain tensors even under a torch.func transform (the tabulated pullback's jvp): cached, and copyable
            with torch.no_grad(), torch._C._DisableFuncTorch():
                size = torch.cat([t.reshape(self.basis.size, -1) for t in tensors], 1).abs().amax(1)
                used = (size > 1e-10 * size.max()).cpu().numpy()
                indices = self.basis.multi_indices()
                degree = int(indices[used].max()) if used.any() else 0
                columns = torch.as_tensor(np.flatnonzero((indices <= degree).all(1)), device=self.mean.device)
                quad = self.quad[columns] if bool(self.quad.any()) else None
                active = (self.mean[columns], self.modes[columns], quad)
            basis = self.basis if degree == self.basis.degree else LegendreBasis(self.basis.bounds.tolist(), degree)
            self._active = (key, basis, *active)
        return self._active[1:]

    def _basis(self, points: Tensor, spatial: bool, basis: LegendreBasis) -> tuple[Tensor, Optional[Tensor]]:
        """`basis` (N, n_basis) and its spatial gradients (N, n_basis, dim_B) or None at `points`, cached."""
        points = self._plain(points)
        try:  # inference tensors have no version counter
            version = None if points.is_inference() else points._version
            key = (points.data_ptr(), tuple(points.shape), version, points.dtype, spatial, basis.degree)
        except RuntimeError:
            key = None
        if key is None or key not in self._cache:
            with torch._C._DisableFuncTorch():  # under a transform even detach() would wrap the points again
                pts = points.detach().double().cpu().numpy()
            B = torch.as_tensor(basis.values(pts), dtype=self.mean.dtype, device=self.mean.device)
            dB = (torch.as_tensor(basis.gradients(pts), dtype=self.mean.dtype, device=self.mean.device)
                  if spatial else None)
            if len(self._cache) > 8:
                self._cache.clear()
            if key is None:
                return B, dB
            # the entry holds the points too: while it lives, no other tensor can take their address (a stale hit)
            self._cache[key] = (B, dB, points)
        return self._cache[key][:2]

    def forward(self, codes: Tensor, points: Tensor) -> Tensor:
        return self.jet(codes, points, order=0).value

    def jet(self, codes: Tensor, points: Tensor, order: int = 1, spatial: bool = False) -> FieldJet:
        """Shapes as :meth:`lnf.siren.ModulatedSiren.jet`; points (N, dim_B) or (B, N, dim_B)."""
        if codes.ndim != 2 or codes.shape[-1] != self.latent_dim:
            raise ValueError(f"codes must have shape (B, {self.latent_dim}), got {tuple(codes.shape)}")
        B, d = codes.shape
        legendre_basis, mean, modes, quad = self._coefficients()
        basis, grad = self._basis(points, spatial, legendre_basis)
        basis = basis.to(codes.dtype)
        mean, modes = mean.to(codes.dtype), modes.to(codes.dtype)
        J = torch.einsum("...nb,bai->...nai", basis, modes)  # (N, A, d) or (B, N, A, d)
        J = J.expand(B, *J.shape[-3:]) if J.ndim == 3 else J
        value = torch.einsum("...nb,ba->...na", basis, mean) + torch.einsum("bnai,bi->bna", J, codes)
        value = value.expand(B, *value.shape[-2:]) if value.ndim == 2 else value
        curved = quad is not None
        if curved:  # Ψ[q̃, q̃] and its derivatives: J += 2Ψq̃, H = 2Ψ
            H = 2.0 * torch.einsum("...nb,baij->...naij", basis, quad.to(codes.dtype))
            H = H.expand(B, *H.shape[-4:]) if H.ndim == 4 else H
            Hq = torch.einsum("bnaij,bj->bnai", H, codes)
            value = value + 0.5 * torch.einsum("bnai,bi->bna", Hq, codes)
            J = J + Hq
        jet = FieldJet(value=value)
        if order >= 1:
            jet.J = J
        if order >= 2:
            jet.H = H if curved else J.new_zeros(*J.shape, d)
        if spatial:  # G = ∇m + ∇Φ q̃ + ∇Ψ[q̃, q̃], GJ = ∇Φ + 2∇Ψ q̃
            grad = grad.to(codes.dtype)
            GJ = torch.einsum("...nbk,bai->...naki", grad, modes)
            GJ = GJ.expand(B, *GJ.shape[-4:]) if GJ.ndim == 4 else GJ
            G = torch.einsum("...nbk,ba->...nak", grad, mean)
            G = G.expand(B, *G.shape[-3:]) if G.ndim == 3 else G
            slope = GJ
            if curved:
                GH = 2.0 * torch.einsum("...nbk,baij->...nakij", grad, quad.to(codes.dtype))
                GHq = torch.einsum("bnakij,bj->bnaki", GH.expand(B, *GH.shape[-5:]) if GH.ndim == 5 else GH, codes)
                slope, GJ = GJ + 0.5 * GHq, GJ + GHq
            jet.G = G + torch.einsum("bnaki,bi->bnak", slope, codes)
            if order >= 1:
                jet.GJ = GJ
        return jet


def _zero_quadratic_part(module: LinearEmbedding, state_dict: dict[str, Tensor], prefix: str, *args: object) -> None:
    """Checkpoints written before the quadratic part existed load as linear embeddings (Ψ = 0)."""
    state_dict.setdefault(prefix + "quad", torch.zeros_like(module.quad))


class PODGalerkin(ReducedModel):
    """POD modes + Galerkin projection of the scene's Lagrangian: our model with a linear embedding.

    Args:
        scene: the scene.
        latent_dim: k, the number of POD modes.
        degree: Legendre degree per axis of the basis the snapshots and modes are represented in.
        ridge: Tikhonov weight of the per-frame snapshot fits, relative to the mean diagonal of PᵀP.
        max_condition: largest condition number of a per-frame fit (it caps the degree used).
        quadratic: add the quadratic part Ψ[q̃, q̃] (a quadratic manifold, :func:`fit_quadratic_part`).
        quadratic_ridge: its Tikhonov weight, relative to the mean diagonal of the normal matrix.
        quadrature: rule of the reduced dynamics (as for our model).
    """

    trainable = False
    collapse_advice = ("Try more modes (model.latent_dim), or more trajectories or observed points: the fields lie "
                       "outside the span of the training observations' POD modes (the 'POD:' log line gives the "
                       "variance they capture and the Legendre degree the observed points allowed)")

    def __init__(self, scene: Scene, latent_dim: int = 1, degree: int = 12, ridge: float = 1e-12,
                 max_condition: float = 1e3, quadratic: bool = False, quadratic_ridge: float = 1e-6,
                 quadrature: Optional[QuadratureRule] = None) -> None:
        super().__init__(scene, quadrature)
        require("model.latent_dim", latent_dim, ("int", 1, None, "the number of POD modes"))
        if not ridge >= 0:
            raise ValueError(f"model.ridge must be ≥ 0, got {ridge!r}")
        if not max_condition >= 1:
            raise ValueError(f"model.max_condition must be ≥ 1, got {max_condition!r}")
        if not quadratic_ridge >= 0:
            raise ValueError(f"model.quadratic_ridge must be ≥ 0, got {quadratic_ridge!r}")
        self.ridge, self.max_condition = float(ridge), float(max_condition)
        self.quadratic, self.quadratic_ridge = bool(quadratic), float(quadratic_ridge)
        self.field = LinearEmbedding(scene.bounds, int(latent_dim), scene.field_dim, degree)
        self.register_buffer("singular_values", torch.zeros(int(latent_dim)))
        self.register_buffer("fitted", torch.tensor(False))

    def reduce(self, points: Tensor, values: Tensor, steps: Optional[int] = None) -> Tensor:
        """ρ(q) = argmin_q̃ Σ_j ω0 ‖m(X_j) + Φ(X_j) q̃ − q_j‖²: exact least squares (B, N, A) → (B, d)."""
        self._check_fitted()
        values = as_field(self.as_model(values))
        points = self.as_model(points)
        self._check_observation(points, values, "values")
        return self.field.project(points, values, self._density(points))

    def dynamics(self, quadrature=None):
        self._check_fitted()
        return super().dynamics(quadrature)

    def _check_fitted(self) -> None:
        if not bool(self.fitted):
            raise RuntimeError("PODGalerkin has no modes yet: call fit_to_observations (python -m lnf.train does)")

    @torch.no_grad()
    def fit_to_observations(self, points: Tensor, values: Tensor) -> dict[str, float]:
        """Modes from training observations: points (n, Nobs, dim_B), values (n, T, Nobs, A) (:func:`fit_pod`)."""
        coefficients = frame_coefficients(self.field.basis, points, values, self.ridge, self.max_condition)
        mean, modes, s, info = fit_pod(self.field.basis, self.latent_dim, coefficients)
        quad = None
        if self.quadratic:
            quad, explained = fit_quadratic_part(coefficients[0], mean, modes, self.quadratic_ridge)
            info.update(explained)
        self.field.set_subspace(mean, modes, quad)
        self.singular_values.copy_(torch.as_tensor(s))
        self.fitted.fill_(True)
        return info

    def extra_repr(self) -> str:
        return (f"{super().extra_repr()}, modes={self.latent_dim}, degree={self.field.basis.degree}"
                + (", quadratic" if self.quadratic else ""))


def frame_coefficients(basis: LegendreBasis, points: "Tensor | np.ndarray", values: "Tensor | np.ndarray",
                       ridge: float, max_condition: float) -> tuple[np.ndarray, int]:
    """Each training frame fitted in the Legendre basis on its own observed points: points (n, Nobs, dim_B), values
    (n, T, Nobs, A) → coefficients (n·T, n_basis·A) and the degree p_eff used.

    The fits are (ridge, weight `ridge` relative to the mean diagonal of PᵀP) least squares up to the largest degree
    p_eff ≤ the basis's whose basis matrix on every trajectory's points has a condition number ≤ `max_condition`
    (higher degrees would amplify noise, even float32 rounding)."""
    pts = np.asarray(points, dtype=np.float64)
    vals = np.asarray(values, dtype=np.float64)
    if pts.ndim != 3 or vals.ndim != 4 or vals.shape[0] != pts.shape[0] or vals.shape[2] != pts.shape[1]:
        raise ValueError(f"POD fit needs points (n, Nobs, dim_B) and values (n, T, Nobs, A), got {pts.shape} and "
                         f"{vals.shape}")
    n, T, n_obs, A = vals.shape
    full = np.stack([basis.values(pts[i]) for i in range(n)])  # (n, Nobs, n_basis)
    p_eff = -1
    # the largest degree the observed points determine well, searched upwards: the columns of degree p are among
    # those of p + 1, and a matrix's condition number is at least any of its column subsets', so the first degree
    # that fails ends the search (from the top, a 3-D body paid SVDs of up to 2 197 columns first)
    for p in range(basis.degree + 1):
        cols = np.flatnonzero((basis.multi_indices() <= p).all(-1))
        if len(cols) > n_obs or max(np.linalg.cond(full[i][:, cols]) for i in range(n)) > max_condition:
            break
        p_eff = p
    if p_eff < 0:
        raise ValueError(f"POD fit: {n_obs} observed points per frame are too few to fit any field")
    keep = np.flatnonzero((basis.multi_indices() <= p_eff).all(-1))
    coeffs = np.zeros((n, T, basis.size, A))
    for i in range(n):
        P = full[i][:, keep]  # (Nobs, nb')
        gram = P.T @ P
        gram += ridge * np.trace(gram) / len(keep) * np.eye(len(keep))
        rhs = P.T @ vals[i].transpose(1, 0, 2).reshape(n_obs, T * A)
        coeffs[i][:, keep] = np.linalg.solve(gram, rhs).reshape(len(keep), T, A).transpose(1, 0, 2)
    return coeffs.reshape(n * T, basis.size * A), p_eff


def fit_pod(basis: LegendreBasis, k: int, coefficients: tuple[np.ndarray, int]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
    """The mean (n_basis, A), the first `k` L²-orthonormal modes (n_basis, A, k) and their singular values (k,) of
    the training frames' coefficients and degree (:func:`frame_coefficients`); and what they capture.

    Because the basis is L²-orthonormal, the SVD of the frames' coefficients gives the mean and the modes."""
    S, p_eff = coefficients
    A = S.shape[1] // basis.size
    mean = S.mean(0)
    _, s, Vt = np.linalg.svd(S - mean, full_matrices=False)
    if len(s) < k:
        raise ValueError(f"POD fit: only {len(s)} snapshots for {k} modes")
    captured = float((s[:k] ** 2).sum() / max((s**2).sum(), 1e-300))
    log.info("POD: %d modes capture %.6f of the snapshot variance (degree %d of %d per axis, %d snapshots)",
             k, captured, p_eff, basis.degree, len(S))
    modes = Vt[:k].reshape(k, basis.size, A).transpose(1, 2, 0).copy()
    return mean.reshape(basis.size, A), modes, s[:k], {"pod_energy_captured": captured, "pod_degree": float(p_eff)}


def fit_quadratic_part(coefficients: np.ndarray, mean: np.ndarray, modes: np.ndarray, ridge: float
                       ) -> tuple[np.ndarray, dict[str, float]]:
    """Ψ (n_basis, A, k, k), symmetric in its last two axes, of the quadratic manifold m + Φq + Ψ[q, q]: the ridge
    least-squares fit of what the modes leave of each frame, coefficients (n·T, n_basis·A) minus m and its projection
    Φq, by the products q_i q_j (i ≤ j) of its POD coordinates q. `ridge` is relative to the mean diagonal of the
    products' normal matrix. Also the share of that residual (in L²) the fit explains."""
    nb, A, k = modes.shape
    centred = coefficients - mean.reshape(1, -1)
    flat = modes.reshape(nb * A, k)
    q = centred @ flat  # (nT, k): the modes are orthonormal in these coefficients
    residual = centred - q @ flat.T
    rows, cols = np.triu_indices(k)
    products = q[:, rows] * q[:, cols]  # (nT, k(k+1)/2)
    gram = products.T @ products
    gram += ridge * np.trace(gram) / len(rows) * np.eye(len(rows))
    fitted = np.linalg.solve(gram, products.T @ residual)  # (k(k+1)/2, nb·A)
    upper = np.zeros((nb * A, k, k))
    upper[:, rows, cols] = fitted.T
    quad = 0.5 * (upper + upper.transpose(0, 2, 1))  # Σ_{i≤j} c_ij q_i q_j = Σ_ij Ψ_ij q_i q_j with Ψ symmetric
    left = residual - products @ fitted
    explained = 1.0 - float((left ** 2).sum() / max((residual ** 2).sum(), 1e-300))
    log.info("quadratic manifold: Ψ explains %.4f of what the %d modes leave (ridge %.0e)", explained, k, ridge)
    return quad.reshape(nb, A, k, k), {"quadratic_explained": explained}
