"""The assembled patch model: FE matrices on the free DOFs, an optional fixed Ritz basis, and the maps to
discrete systems, process noise and measurements (docs/spec/model.md §2–§4).

Generalised coordinates: the displacement of the free DOFs is ``c = V q`` with ``V`` the identity (full
model) or a fixed Ritz basis (reduced model, spec §3.5), normalised so that ``V^T M0 V = vol I`` (then ``q`` is
in metres). The kinematic state is ``x = [q; q']`` of size ``2 r``.
"""

from __future__ import annotations

from dataclasses import dataclass
import logging

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .config import MAX_FULL_DOF, ConfigError, ModelConfig
from .discretise import DiscreteSystem, discretise
from .fem import FEMatrices, assemble
from .geometry import PatchMesh, build_mesh
from .params import lame

__all__ = ["PatchModel", "Observation", "build_model", "MAX_FULL_DOF"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Observation:
    """Linear measurement of surface points: ``y_j = X_ref_j + r(t) + H_j x + v_j``.

    Attributes
    ----------
    H : ndarray of shape (3 P, 2 r)
        Acts on the kinematic state ``[q; q']`` (zero velocity block).
    reference : ndarray of shape (P, 3)
        Reference (undeformed) positions in the patch frame, m.
    param : ndarray of shape (P, 3)
        ``(s, t, d)`` of each point.
    """

    H: np.ndarray
    reference: np.ndarray
    param: np.ndarray

    @property
    def n_points(self) -> int:
        return self.reference.shape[0]


@dataclass(frozen=True)
class PatchModel:
    """A built patch model (see :func:`build_model`)."""

    config: ModelConfig
    mesh: PatchMesh
    fe: FEMatrices
    free_dofs: np.ndarray  # (n_free_dof,) indices into 3*n_nodes
    basis: np.ndarray | None  # (n_free_dof, r) or None for the identity
    K_lambda: np.ndarray  # (r, r) generalised
    K_mu: np.ndarray
    M0: np.ndarray
    loads: np.ndarray  # (r, n_u) generalised load columns per unit input

    # -- sizes -------------------------------------------------------------------------------
    @property
    def r(self) -> int:
        return self.M0.shape[0]

    @property
    def state_dim(self) -> int:
        return 2 * self.r

    @property
    def n_free_nodes(self) -> int:
        return int((~self.mesh.rim_nodes).sum())

    @property
    def input_names(self) -> tuple:
        return self.config.input_names

    # -- parameter-dependent matrices --------------------------------------------------------
    def matrices(self, theta):
        """Generalised ``M(theta)``, ``K(theta)`` (r, r) for ``theta = [rho, alpha1, alpha2, E, nu]``."""
        theta = _check_theta(theta)
        lam, mu = lame(theta[3], theta[4])
        return theta[0] * self.M0, lam * self.K_lambda + mu * self.K_mu

    def system(self, theta, dt=None, method=None) -> DiscreteSystem:
        """Exact (by default modal) first-order-hold discretisation for one ``theta``."""
        theta = _check_theta(theta)
        M, K = self.matrices(theta)
        return discretise(M, K, theta[1], theta[2], self.loads, self.config.dt if dt is None else dt,
                          method or self.config.method)

    def continuous(self, theta):
        """``(Fc, Gc)`` of ``x' = Fc x + Gc u``."""
        from .discretise import continuous

        theta = _check_theta(theta)
        M, K = self.matrices(theta)
        return continuous(M, K, theta[1], theta[2], self.loads)

    def static_state(self, theta, u) -> np.ndarray:
        """Equilibrium kinematic state ``[K^-1 F u; 0]`` for input ``u`` (n_u,)."""
        _, K = self.matrices(theta)
        q = sla.solve(K, self.loads @ np.asarray(u, float), assume_a="pos")
        return np.concatenate([q, np.zeros_like(q)])

    def process_noise(self, theta=None, dt=None) -> np.ndarray:
        """Discrete process-noise covariance ``Q_l`` (2r, 2r) of the configured kind.

        ``diagonal``: ``diag(position_std^2 I, velocity_std^2 I)`` per step (the paper's form);
        ``acceleration``: white acceleration noise of PSD ``accel_psd`` (m^2/s^3) on every free DOF,
        projected on the basis and integrated exactly over ``dt`` (Van Loan) at ``theta``.
        """
        nz = self.config.noise
        r = self.r
        if nz.process_kind == "diagonal":
            return np.diag(np.r_[np.full(r, nz.position_std**2), np.full(r, nz.velocity_std**2)])
        theta = self.config.theta if theta is None else theta
        dt = self.config.dt if dt is None else dt
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: positive time step expected, got {dt}")
        Fc, _ = self.continuous(theta)
        W = self._accel_projection()
        Qc = np.zeros((2 * r, 2 * r))
        Qc[r:, r:] = nz.accel_psd * (W @ W.T)
        return integrated_noise(Fc, Qc, dt)

    def _accel_projection(self) -> np.ndarray:
        if self.basis is None:
            return np.eye(self.r)
        M0f = self.fe.M0[self.free_dofs][:, self.free_dofs]
        return sla.solve(self.M0, (M0f @ self.basis).T, assume_a="pos")

    def initial_covariance(self) -> np.ndarray:
        """Prior covariance of the kinematic state around equilibrium (2r, 2r)."""
        nz = self.config.noise
        return np.diag(np.r_[np.full(self.r, nz.initial_position_std**2),
                             np.full(self.r, nz.initial_velocity_std**2)])

    # -- boundary lifting ---------------------------------------------------------------------
    def lifting(self, theta) -> np.ndarray:
        """Quasi-static lifting ``R = -K_ff^-1 K_fb`` (n_free_dof, n_rim_dof) on the full mesh."""
        theta = _check_theta(theta)
        lam, mu = lame(theta[3], theta[4])
        K = (lam * self.fe.K_lambda + mu * self.fe.K_mu).tocsc()
        fixed = np.setdiff1d(np.arange(K.shape[0]), self.free_dofs)
        Kff = K[self.free_dofs][:, self.free_dofs]
        Kfb = K[self.free_dofs][:, fixed]
        return -spla.splu(Kff.tocsc()).solve(Kfb.toarray())

    # -- displacements and measurements --------------------------------------------------------
    def free_displacement(self, q) -> np.ndarray:
        """Free-DOF displacements ``V q`` for generalised coordinates q (..., r) -> (..., n_free_dof)."""
        q = np.asarray(q, float)
        return q if self.basis is None else q @ self.basis.T

    def node_displacements(self, x, translation=None) -> np.ndarray:
        """Node displacements (..., n_nodes, 3) from kinematic states x (..., 2r), plus a rigid translation."""
        x = np.asarray(x, float)
        c = self.free_displacement(x[..., : self.r])
        out = np.zeros(x.shape[:-1] + (3 * self.mesh.n_nodes,))
        out[..., self.free_dofs] = c
        out = out.reshape(x.shape[:-1] + (self.mesh.n_nodes, 3))
        if translation is not None:
            out = out + np.asarray(translation, float)[..., None, :]
        return out

    def shape_matrix(self, param) -> sp.csr_matrix:
        """Trilinear shape-function matrix N (P, n_nodes) at material points ``(s, t, d)`` (P, 3)."""
        param = np.atleast_2d(np.asarray(param, float))
        axes = self.mesh.axes
        idx, frac = [], []
        for a, (coord, ax) in enumerate(zip(param.T, axes)):
            lo, hi = ax[0], ax[-1]
            tol = 1e-9 * (hi - lo)
            if ((coord < lo - tol) | (coord > hi + tol)).any():
                bad = int(np.flatnonzero((coord < lo - tol) | (coord > hi + tol))[0])
                raise ValueError(
                    f"point {bad}: parameter coordinate {'std'[a]}={coord[bad]:.6g} m outside the patch "
                    f"[{lo:.6g}, {hi:.6g}]"
                )
            h = ax[1] - ax[0]
            i = np.clip(np.floor((coord - lo) / h).astype(int), 0, len(ax) - 2)
            idx.append(i)
            frac.append(np.clip((coord - ax[i]) / h, 0.0, 1.0))
        rows, cols, vals = [], [], []
        P = param.shape[0]
        for di in (0, 1):
            for dj in (0, 1):
                for dk in (0, 1):
                    w = ((frac[0] if di else 1 - frac[0]) * (frac[1] if dj else 1 - frac[1])
                         * (frac[2] if dk else 1 - frac[2]))
                    node = self.mesh.node_index[idx[0] + di, idx[1] + dj, idx[2] + dk]
                    rows.append(np.arange(P))
                    cols.append(node)
                    vals.append(w)
        N = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(P, self.mesh.n_nodes))
        N.eliminate_zeros()
        return N

    def observation(self, param) -> Observation:
        """Measurement model of material points ``(s, t, d)`` (P, 3)."""
        param = np.atleast_2d(np.asarray(param, float))
        N = self.shape_matrix(param)
        Hfull = sp.kron(N, sp.identity(3), format="csr")  # (3P, 3 n_nodes)
        Hf = Hfull[:, self.free_dofs]
        Hq = Hf.toarray() if self.basis is None else np.asarray(Hf @ self.basis)
        H = np.hstack([Hq, np.zeros_like(Hq)])
        ref = self.mesh.geometry.to_patch(param[:, 0], param[:, 1], param[:, 2])
        return Observation(H, ref, param)

    def default_points(self) -> np.ndarray:
        """Material points ``(s, t, d)`` (P, 3) observed by default (config ``observation``)."""
        obs = self.config.observation
        mesh = self.mesh
        if obs["points"] == "epicardial_nodes":
            mask = mesh.epicardial_nodes & ~mesh.rim_nodes
            nodes = mesh.node_index[:, :, 0].T.ravel()  # ordered t-major for readability
            nodes = nodes[mask[nodes]]
            return mesh.param[nodes].copy()
        g = mesh.geometry
        ns, nt = obs["grid"]
        m = obs["margin"]
        s = np.linspace(-(0.5 - m) * g.length, (0.5 - m) * g.length, ns) if ns > 1 else np.zeros(1)
        t = np.linspace(-(0.5 - m) * g.width, (0.5 - m) * g.width, nt) if nt > 1 else np.zeros(1)
        S, T = np.meshgrid(s, t, indexing="xy")
        return np.stack([S.ravel(), T.ravel(), np.zeros(S.size)], axis=1)

    def frequencies_hz(self, theta, count=5) -> np.ndarray:
        """Lowest undamped natural frequencies (Hz) for ``theta``."""
        M, K = self.matrices(theta)
        w2 = sla.eigh(K, M, eigvals_only=True, subset_by_index=[0, min(count, self.r) - 1])
        return np.sqrt(w2) / (2 * np.pi)

    def info(self) -> dict:
        mesh = self.mesh
        return {
            "name": self.config.name,
            "nodes": int(mesh.n_nodes),
            "elements": int(mesh.elements.shape[0]),
            "free_nodes": self.n_free_nodes,
            "free_dofs": int(self.free_dofs.size),
            "reduced": self.basis is not None,
            "basis_size": int(self.r),
            "state_dim": int(self.state_dim),
            "observed_points": int(self.default_points().shape[0]),
            "observed_rows": int(3 * self.default_points().shape[0]),
            "inputs": list(self.input_names),
            "frame_rate_hz": self.config.frame_rate,
            "method": self.config.method,
            "frequencies_hz": [float(f) for f in self.frequencies_hz(self.config.theta)],
            "theta": dict(zip(("rho", "alpha1", "alpha2", "E", "nu"), map(float, self.config.theta))),
            "estimated": list(self.config.estimation.estimate),
        }


def integrated_noise(Fc, Qc, dt) -> np.ndarray:
    """``Q = int_0^dt e^{Fc s} Qc e^{Fc^T s} ds`` (Van Loan), stable for stiff ``Fc``.

    Van Loan's block exponential contains ``e^{-Fc h}``, which overflows for stiff damped modes, so it is
    evaluated on ``h = dt / 2^k`` with ``||Fc h|| <= 1`` and doubled back: ``Q(2h) = Q(h) + A(h) Q(h) A(h)^T``,
    a sum of PSD terms.
    """
    n = Fc.shape[0]
    k = max(0, int(np.ceil(np.log2(max(np.linalg.norm(Fc, 1) * dt, 1.0)))))
    h = dt / 2**k
    Z = np.zeros((2 * n, 2 * n))
    Z[:n, :n] = -Fc
    Z[:n, n:] = Qc
    Z[n:, n:] = Fc.T
    E = sla.expm(Z * h)
    A = E[n:, n:].T
    Q = A @ E[:n, n:]
    for _ in range(k):
        Q = Q + A @ Q @ A.T
        A = A @ A
    return 0.5 * (Q + Q.T)


def _check_theta(theta) -> np.ndarray:
    th = np.asarray(theta, float).reshape(-1)
    if th.shape != (5,):
        raise ValueError(f"theta: shape (5,) expected [rho, alpha1, alpha2, E, nu], got {th.shape}")
    if not np.isfinite(th).all() or th[0] <= 0 or th[3] <= 0 or th[1] < 0 or th[2] < 0 or not 0 < th[4] < 0.5:
        raise ValueError(f"theta out of the physical range: {th}")
    return th


def _load_columns(fe: FEMatrices, cfg: ModelConfig) -> np.ndarray:
    cols = []
    if cfg.inputs.pressure != "none":
        cols.append(fe.f_pressure)
    if cfg.inputs.active_tension is not None:
        cols.append(fe.f_active)
    if not cols:
        return np.zeros((fe.f_pressure.size, 0))
    return np.stack(cols, axis=1)


def _ritz_basis(fe, free, loads, theta, modes, static_nu, volume):
    Kl = fe.K_lambda[free][:, free].tocsc()
    Km = fe.K_mu[free][:, free].tocsc()
    M0 = fe.M0[free][:, free].tocsc()
    nu0 = theta[4]
    lam0, mu0 = lame(1.0, nu0)
    K0 = (lam0 * Kl + mu0 * Km).tocsc()
    k = min(modes, K0.shape[0] - 2)
    # fixed start vector: ARPACK otherwise starts from a random one and the basis differs per build
    _, vecs = spla.eigsh(K0, k=k, M=M0, sigma=0.0, which="LM", v0=np.ones(K0.shape[0]))
    cols = [vecs]
    for nu in static_nu:
        lam, mu = lame(1.0, nu)
        lu = spla.splu((lam * Kl + mu * Km).tocsc())
        cols.append(lu.solve(loads) if loads.size else np.zeros((K0.shape[0], 0)))
    V = np.hstack(cols)
    norm2 = np.einsum("ij,ij->j", V, M0 @ V)
    nonzero = norm2 > 1e-24 * norm2.max()  # a load with no static response here (active tension on a flat patch)
    V = V[:, nonzero] / np.sqrt(norm2[nonzero])
    for tol in (1e-12, 0.0):  # M0-orthonormalise twice ("twice is enough"); drop dependent statics once
        G = V.T @ (M0 @ V)
        w, U = np.linalg.eigh(0.5 * (G + G.T))
        keep = w > tol * w.max()
        V = V @ (U[:, keep] / np.sqrt(w[keep]))
    return V * np.sqrt(volume)


def build_model(cfg: ModelConfig) -> PatchModel:
    """Mesh, assemble, eliminate the clamped rim and (if configured) project on a Ritz basis.

    A configuration from :func:`~heartcv.tracker.config.model_config_from_dict` builds, or the build raises
    :class:`~heartcv.tracker.config.ConfigError` naming the field to change (a mesh too large for the full model,
    a UKF ``kappa`` too negative for the state dimension, a mesh whose matrices are numerically singular).
    """
    ns, nt, nd = cfg.geometry.grid
    n_free = 3 * (ns - 2) * (nt - 2) * nd
    if cfg.reduction is None and n_free > MAX_FULL_DOF:  # checked before anything is allocated
        raise ConfigError("geometry.grid", f"the model has {n_free} free DOFs; the full model allows at most "
                                           f"{MAX_FULL_DOF}. Add a 'reduction' section (a fixed Ritz basis, "
                                           "docs/model.md §5) or use a coarser grid")
    mesh = build_mesh(cfg.geometry)
    fe = assemble(mesh)
    free_nodes = np.flatnonzero(~mesh.rim_nodes)
    free = (3 * free_nodes[:, None] + np.arange(3)).ravel()
    loads_full = _load_columns(fe, cfg)[free]
    if cfg.reduction is None:
        sub = np.ix_(free, free)
        Kl = fe.K_lambda[sub].toarray()
        Km = fe.K_mu[sub].toarray()
        M0 = fe.M0[sub].toarray()
        model = PatchModel(cfg, mesh, fe, free, None, Kl, Km, M0, loads_full)
    else:
        try:
            V = _ritz_basis(fe, free, loads_full, cfg.theta, cfg.reduction["modes"], cfg.reduction["static_nu"],
                            fe.volume)
        except (RuntimeError, ValueError, np.linalg.LinAlgError, spla.ArpackError) as exc:
            # ArpackNoConvergence is an ArpackError; splu raises RuntimeError for a singular matrix
            raise ConfigError("geometry", f"the reduced basis cannot be computed on this mesh ({exc}); check the "
                                          "geometry's proportions and reduction.modes") from None
        sub = np.ix_(free, free)

        def project(A):
            return np.asarray(V.T @ (A[sub] @ V))

        Kl, Km, M0 = project(fe.K_lambda), project(fe.K_mu), project(fe.M0)
        sym = lambda A: 0.5 * (A + A.T)  # noqa: E731
        model = PatchModel(cfg, mesh, fe, free, V, sym(Kl), sym(Km), sym(M0), V.T @ loads_full)
    _check_built(model)
    return model


def _check_built(model: PatchModel) -> None:
    """Refuse a built model whose matrices are not finite or whose mass matrix is not positive definite, and a UKF
    ``kappa`` that leaves no positive spread for this state dimension (``alpha^2 (n + kappa) > 0``)."""
    cfg = model.config
    for name, A in (("mass", model.M0), ("stiffness", model.K_lambda), ("stiffness", model.K_mu),
                    ("load", model.loads)):
        if not np.isfinite(A).all():
            raise ConfigError("geometry", f"the {name} matrix of this mesh has non-finite entries; check the "
                                          "geometry's proportions")
    try:
        np.linalg.cholesky(model.M0)
    except np.linalg.LinAlgError:
        raise ConfigError("geometry", "the mass matrix of this mesh is numerically singular; check the geometry's "
                                      "proportions (element sizes along s, t and d)") from None
    n = model.state_dim + len(cfg.estimation.estimate)
    kappa = cfg.estimation.ukf["kappa"]
    if n + kappa <= 0:
        raise ConfigError("estimation.ukf.kappa", f"must exceed -n = {-n} (n: the joint state dimension of this "
                                                  f"model), got {kappa}")
