"""Gauss-Newton covariance of far-field positions from the sparse blocks (Cholesky / Woodbury)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import block_diag

from .._checks import check_choice
from ..robust import m_estimator_sigma2
from .model import _eliminate_positions, _flat, _normal_equations

Array = NDArray[np.float64]


def _rotation_generators(Z: Array) -> Array:
    """Orthonormal basis (d(m-1), g) of the infinitesimal rotations of z_2..z_m about z_1 = 0."""
    Zr = Z[1:]
    d = Z.shape[1]
    if d == 3:
        G = np.stack([np.cross(np.eye(3)[a], Zr).ravel() for a in range(3)], axis=1)
    else:
        G = np.stack([-Zr[:, 1], Zr[:, 0]], axis=1).ravel()[:, None]
    Q, R = np.linalg.qr(G)
    keep = np.abs(np.diag(R)) > 1e-12 * (np.abs(R).max() + 1e-300)
    return np.asarray(Q[:, keep])


def _reference_blocks(Hzn: Array, Hnn: Array) -> tuple[Array, Array, Array, Array]:
    """Split the free-offset blocks for the reference-offset estimator (``C_j = D_1j``).

    Returns the reference blocks ``Hzn`` (mz, k, d, q), ``Hnn`` (k, q, q) (q = d - 1 tangent
    coordinates) and the columns' noise-sharing vectors: ``Gz`` (mz, k, d) and ``gn`` (k, q),
    ``g_j = sum_{i >= 2} W_ij J_ij`` (the offset column of the free-offset normal equations), the
    direction in which row 1's noise ``e_1j`` enters every reduced entry of column j.
    """
    q = Hzn.shape[-1] - 1
    return Hzn[..., :q], Hnn[:, :q, :q], Hzn[..., q], Hnn[:, :q, q]


def _reference_sigma2(W: Array, r: Array, rank: int, A: Array, gn: Array, Gt: Array, SpG: Array,
                      dof_extra: int = 0) -> float:
    """Unbiased noise variance of the entries for the reference-offset estimator.

    The reduced entries ``D_ij - D_1j`` (i >= 2) have covariance ``sigma^2 (I + 1 1^T)`` per
    column, so ``E[RSS] = sigma^2 tr((I - P)(I + 1 1^T)) = sigma^2 (2 n - rank - sum_j g_j^T H^+ g_j)``
    (n reduced observations, P the hat matrix), with ``g^T H^+ g = g_n^T A g_n + gt^T S^+ gt``.
    """
    n_red = int((W[1:] > 0).sum())
    tr = float(np.einsum("kp,kpq,kq->", gn, A, gn) + np.sum(Gt * SpG))
    dof = 2.0 * n_red - rank - tr - dof_extra
    return float(np.sum(W * r**2)) / max(dof, 1.0)


def _shared_noise_directions(X: Array, Gz: Array, gn: Array) -> Array:
    """``gt_j = g_z,j - H_zn,j A_j g_n,j`` for every column, as the (mz d, k) matrix (positions'
    part of ``g_j`` after the column's own unknowns are profiled out)."""
    Gt = Gz - np.einsum("ijaq,jq->ija", X, gn)  # (mz, k, d)
    mz, k, d = Gt.shape
    return np.asarray(Gt.transpose(0, 2, 1).reshape(mz * d, k))


def position_covariance(
    D: Array, Z: Array, N: Array, C: Array, W: Array, *, free_offsets: bool, dof_extra: int = 0,
    method: str = "auto", loss: str = "linear", delta: float = 1.0,
) -> Array:
    """Gauss-Newton covariance of the positions at a least-squares solution: (m, d, d).

    ``sigma^2 [S^+]_ii`` with S the Schur complement of the direction/offset blocks in
    ``J^T W J`` (the positions' information with the directions and offsets profiled out)
    and ``sigma^2 = cost / (observations - parameters + rotations)``. With the paper's reference
    offsets (``free_offsets=False``, ``C = D[0]``) row 1's noise enters every entry of its column,
    so the reduced entries are correlated (``sigma^2 (I + 1 1^T)`` per column) and the covariance
    is the least-squares sandwich ``sigma^2 (S^+ + S^+ Gt Gt^T S^+)`` (``Gt``: the columns'
    shared-noise directions, :func:`_reference_blocks`) with ``sigma^2`` from the residuals'
    expected sum under that correlation (:func:`_reference_sigma2`). The pseudo-inverse puts
    the unobservable rotations (3 in space, 1 in a plane) in the minimum-norm gauge
    (z_1 = 0 fixes translation), so the covariances describe errors after the best rotation
    about the first position.

    Parameters
    ----------
    D, Z, N, C, W : data (m, k), positions (m, d), unit directions (k, d), offsets (k,),
        weights (m, k) (0 = unused entry).
    free_offsets : whether the C_j are estimated (adds one parameter per column).
    dof_extra : further parameters to subtract from the residual degrees of freedom.
    loss, delta : the fit's loss and scale; with a robust loss W must be the 0/1 mask of the
        entries it used and the variance factor is :func:`m_estimator_sigma2` (the M-estimator's
        sandwich) instead of ``sigma^2``.
    method : ``"dense"`` -- pseudo-inverse of the d(m-1) x d(m-1) Schur complement (SVD;
        the reference, O(m^3)); ``"schur"`` -- the same blocks without a pseudo-inverse,
        ``S^+ = (S + Q Q^T)^-1 - Q Q^T`` with Q the orthonormal rotation generators (the
        exact null space of S), the inverse's diagonal blocks from whichever side is
        smaller: a Cholesky inverse of ``S + QQ^T`` (d(m-1) <= p k) or, eliminating the
        positions, Woodbury's identity with the (p k + g) core
        ``[[-S_n, H_nz A^-1 Q], [Q^T A^-1 H_zn, I + Q^T A^-1 Q]]`` (A = the block-diagonal
        position information, S_n the directions' Schur complement), so the cost is
        O(m k min(dm, pk)) and memory O(m k); ``"auto"`` = ``"schur"``.

    Returns
    -------
    (m, d, d) covariance blocks (metres^2), the first one zero (the gauge origin).

    Notes
    -----
    ``"schur"`` and ``"dense"`` agree to rounding where S's numerical null space is exactly
    the rotations (every position seen by d independent directions); the tests check 1e-9.
    """
    check_choice(method, "method", ("auto", "dense", "schur"))
    D0 = np.where(W > 0, D, 0.0)
    reference = not free_offsets
    Hzz, Hzn, Hnn, _, _, _, r = _normal_equations(D0, Z, N, C, W, True)
    if reference:
        Hzn, Hnn, Gz, gn = _reference_blocks(Hzn, Hnn)
    mz, k, d, p = Hzn.shape
    Q = _rotation_generators(Z)
    g = Q.shape[1]
    n_obs = int((W > 0).sum())
    n_par = d * mz + p * k - g - dof_extra
    sigma2 = float(np.sum(W * r**2)) / max(n_obs - n_par, 1)
    if loss != "linear":
        sigma2 = m_estimator_sigma2(r, W > 0, loss, delta, n_par)
    idx = np.arange(mz)
    Hr = _flat(Hzn)
    Hnn_inv = np.linalg.pinv(Hnn)  # (k, p, p) blocks: cheap either way
    Gt = _shared_noise_directions(np.matmul(Hzn, Hnn_inv[None]), Gz, gn) if reference else None
    if method == "dense" or (method in ("auto", "schur") and not _eliminate_positions(mz, d, k, p)):
        X = np.matmul(Hzn, Hnn_inv[None])
        S = -(_flat(X) @ Hr.T)
        S4 = S.reshape(mz, d, mz, d)
        S4[idx, :, idx, :] += Hzz
        if method == "dense":
            cov = np.linalg.pinv(S, rcond=1e-10, hermitian=True)
        else:
            inv = _spd_inverse(S + Q @ Q.T)
            cov = np.linalg.pinv(S, rcond=1e-10, hermitian=True) if inv is None else inv - Q @ Q.T
        blocks = cov.reshape(mz, d, mz, d)[idx, :, idx, :]
        SpG = cov @ Gt if Gt is not None else None
    else:
        if np.min(np.linalg.eigvalsh(Hzz)[:, 0] / np.maximum(np.trace(Hzz, axis1=1, axis2=2), 1e-300)) < 1e-10:
            return position_covariance(D, Z, N, C, W, free_offsets=free_offsets, dof_extra=dof_extra,
                                       method="dense", loss=loss, delta=delta)  # a position is not seen by d directions
        A_inv = np.linalg.inv(Hzz)  # (mz, d, d): each position seen by >= d directions
        Qb = Q.reshape(mz, d, g)
        U = np.concatenate([Hr, Q], axis=1)  # (mz d, k p + g)
        Ub = U.reshape(mz, d, -1)
        Y = np.matmul(A_inv, Ub)  # A^-1 U, per position block: (mz, d, k p + g)
        Yf = Y.reshape(mz * d, -1)
        K = U.T @ Yf
        K[: k * p, : k * p] -= block_diag(*Hnn)
        K[k * p:, k * p:] += np.eye(g)
        YK = (Yf @ np.linalg.inv(K)).reshape(mz, d, -1)  # one (kp+g)^3 inverse, then BLAS
        blocks = A_inv - np.matmul(YK, Y.transpose(0, 2, 1)) - np.matmul(Qb, Qb.transpose(0, 2, 1))
        SpG = None
        if Gt is not None:  # S^+ Gt = A^-1 Gt - Y K^-1 Y^T Gt - Q Q^T Gt
            AG = np.matmul(A_inv, Gt.reshape(mz, d, -1)).reshape(mz * d, -1)
            SpG = AG - YK.reshape(mz * d, -1) @ (Yf.T @ Gt) - Q @ (Q.T @ Gt)
    if Gt is not None and SpG is not None and loss == "linear":
        sigma2 = _reference_sigma2(W, r, d * mz + p * k - g, Hnn_inv, gn, Gt, SpG, dof_extra)
        SG = SpG.reshape(mz, d, -1)
        blocks = blocks + np.matmul(SG, SG.transpose(0, 2, 1))
    blocks = sigma2 * 0.5 * (blocks + blocks.transpose(0, 2, 1))
    return np.concatenate([np.zeros((1, d, d)), blocks], axis=0)


def _spd_inverse(S: Array) -> Array | None:
    """Inverse of a symmetric positive definite matrix by Cholesky (LAPACK potrf / potri);
    None when S is not numerically positive definite (the caller falls back to a pseudo-inverse)."""
    import scipy.linalg as sla

    if not np.isfinite(S).all():
        return None
    try:
        c, _ = sla.cho_factor(S, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    inv, info = sla.lapack.dpotri(c, lower=1)
    if info != 0:
        return None
    inv = np.tril(inv) + np.tril(inv, -1).T
    d = np.diag(S)
    # a factor this close to singular means extra null directions beyond the rotations
    if np.max(np.abs(np.diag(inv)) * d) > 1e10:
        return None
    return np.asarray(inv)


def linear_position_covariance(D: Array, x: Array, u: Array, C: Array, W: Array, *,
                               scale_free: bool = True) -> Array:
    """Gauss-Newton covariance of a linear array's positions (the 1-D far-field model): (m, 1, 1).

    Model ``D_ij = x_i u_j + C_j`` with ``x_1 = 0`` (translation gauge), ``u_j`` the
    projection of direction j on the line and ``C_j`` free. The per-column unknowns
    ``(u_j, C_j)`` are eliminated by a Schur complement (2 x 2 blocks), leaving the
    (m-1) x (m-1) information ``S`` of the positions. With ``scale_free`` (the linear case:
    the data fix the positions only up to a scale, ``x -> a x``, ``u -> u / a``) ``S`` is
    singular along the scale motion ``x``; its pseudo-inverse projected onto the complement of
    that motion is the covariance of the errors that remain after the best scaling about the
    first position. Without it (parallel directions, ``u_j = +-1`` known) the ``u_j`` are not
    unknowns and ``S`` is regular. ``sigma^2 = RSS / (observations - unknowns + gauge)``.

    Parameters
    ----------
    D : (m, k) data (metres); x : (m,) or (m, 1) positions along the line, x_1 = 0;
    u : (k,) or (k, 1) projections; C : (k,) offsets (the residual uses the least-squares
    offsets for x and u, whichever C is given); W : (m, k) weights (0 = unused).
    scale_free : whether u is estimated (the scale gauge is then removed).

    Returns
    -------
    (m, 1, 1) variances of the positions (metres^2), the first zero.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = np.linspace(0.0, 0.3, 8); u = rng.uniform(-1, 1, 20); C = rng.normal(size=20)
    >>> D = np.outer(x, u) + C + 1e-3 * rng.standard_normal((8, 20))
    >>> cov = linear_position_covariance(D, x, u, C, np.ones((8, 20)))
    >>> cov.shape, bool(cov[0, 0, 0] == 0.0)
    ((8, 1, 1), True)
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(-1)
    C = np.asarray(C, dtype=float).reshape(-1)
    W = np.asarray(W, dtype=float)
    m, k = W.shape
    # residual at the least-squares offsets for these x, u (the reported C may be the paper's
    # reference offsets C_j = D_1j, whose residual carries the first row's noise twice)
    D0 = np.where(W > 0, D, 0.0)
    C = np.sum(W * (D0 - np.outer(x, u)), axis=0) / np.maximum(W.sum(axis=0), 1e-300)
    r = np.where(W > 0, D0 - np.outer(x, u) - C, 0.0)
    Wz = W[1:]
    # information blocks: positions (diagonal), columns (2 x 2 or 1 x 1), coupling
    Hxx = Wz @ (u**2)  # (m-1,)
    if scale_free:
        xs = x[1:]
        Hcc = np.empty((k, 2, 2))
        Hcc[:, 0, 0] = W.T @ (x**2)
        Hcc[:, 0, 1] = Hcc[:, 1, 0] = W.T @ x
        Hcc[:, 1, 1] = W.sum(axis=0)
        # d r_ij / d x_i = u_j couples to (u_j: x_i, C_j: 1); the residual term r_ij of the exact
        # Hessian is left out (Gauss-Newton)
        Hxc = np.stack([Wz * u[None, :] * xs[:, None], Wz * u[None, :]], axis=-1)  # (m-1, k, 2)
        Hinv = np.linalg.pinv(Hcc)
        T = np.einsum("ija,jab->ijb", Hxc, Hinv)
        S = np.diag(Hxx) - np.einsum("ija,lja->il", T, Hxc)
        n_par = (m - 1) + 2 * k - 1
    else:
        cnt = np.maximum(W.sum(axis=0), 1e-300)
        Hxc = Wz * u[None, :]  # (m-1, k)
        S = np.diag(Hxx) - (Hxc / cnt[None, :]) @ Hxc.T
        n_par = (m - 1) + k
    n_obs = int((W > 0).sum())
    sigma2 = float(np.sum(W * r**2)) / max(n_obs - n_par, 1)
    cov = np.linalg.pinv(S, rcond=1e-10, hermitian=True)
    if scale_free:
        g = x[1:] / max(float(np.linalg.norm(x[1:])), 1e-300)
        P = np.eye(m - 1) - np.outer(g, g)
        cov = P @ cov @ P
    out = np.zeros((m, 1, 1))
    out[1:, 0, 0] = sigma2 * np.diag(cov)
    return out


#: largest ``d (m - 1)`` for which :func:`direction_covariance` forms the positions' dense Schur
#: complement (its pseudo-inverse is O((d m)^3))
DIRECTION_COV_MAX = 1500


def direction_covariance(D: Array, Z: Array, N: Array, C: Array, W: Array, *, free_offsets: bool = True) -> Array:
    """Gauss-Newton covariance of each unit direction at a least-squares solution: (k, d, d).

    Block inverse of ``J^T W J`` with the positions profiled in: for column j,
    ``A_j + A_j X_j^T S^+ X_j A_j`` with ``A_j = Hnn_j^-1`` (its tangent coordinates and offset),
    ``X_j`` its coupling to the positions and ``S^+`` the pseudo-inverse of the positions' Schur
    complement (the gauge of :func:`position_covariance`: the best rotation about the first
    position); the tangent block mapped to the ambient frame (``T Sigma_v T^T``, T the tangent
    basis of the sphere / circle) and scaled by ``sigma^2 = RSS / (observations - parameters +
    rotations)``.

    Parameters
    ----------
    D, Z, N, C, W : data (m, k), positions (m, d) with ``Z[0] = 0``, unit directions (k, d), offsets
        (k,), weights (m, k) (0 = unused entry).
    free_offsets : whether the C_j are estimated; False: the paper's reference offsets
        ``C = D[0]``, whose shared row-1 noise is carried by the sandwich of
        :func:`position_covariance`.

    Returns
    -------
    (k, d, d) covariance of each direction (unitless^2 = rad^2 for small errors), in the frame of
    ``N``; its null direction is ``n_j`` itself.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> Z = rng.uniform(-0.1, 0.1, (8, 3)); Z[0] = 0
    >>> N = rng.normal(size=(12, 3)); N /= np.linalg.norm(N, axis=1, keepdims=True)
    >>> D = Z @ N.T + 1e-4 * rng.standard_normal((8, 12))
    >>> cov = direction_covariance(D, Z, N, np.zeros(12), np.ones((8, 12)))
    >>> cov.shape, bool(np.allclose(np.einsum("ja,jab->jb", N, cov), 0.0, atol=1e-15))
    ((12, 3, 3), True)
    """
    D0 = np.where(W > 0, D, 0.0)
    Hzz, Hzn, Hnn, _, _, T, r = _normal_equations(D0, Z, N, C, W, True)
    reference = not free_offsets
    if reference:
        Hzn, Hnn, Gz, gn = _reference_blocks(Hzn, Hnn)
    mz, k, d, p = Hzn.shape
    Q = _rotation_generators(Z)
    g = Q.shape[1]
    n_obs = int((W > 0).sum())
    n_par = d * mz + p * k - g
    sigma2 = float(np.sum(W * r**2)) / max(n_obs - n_par, 1)
    A = np.linalg.pinv(Hnn, hermitian=True)  # (k, p, p)
    X = np.matmul(Hzn, A[None])  # (mz, k, d, p): H_zn A, per column
    Hr = _flat(Hzn)
    S = -(_flat(X) @ Hr.T)
    idx = np.arange(mz)
    S4 = S.reshape(mz, d, mz, d)
    S4[idx, :, idx, :] += Hzz
    Sp = np.linalg.pinv(S, rcond=1e-10, hermitian=True)
    Y = _flat(X)  # (mz d, k p): the columns' couplings side by side
    SY = Sp @ Y  # one BLAS product
    # per column j: X_j^T S^+ X_j = (Y_j)^T (S^+ Y)_j, the (p, p) diagonal blocks of Y^T S^+ Y
    Yb = Y.reshape(mz * d, k, p)
    SYb = SY.reshape(mz * d, k, p)
    cov_v = A + np.einsum("akp,akq->kpq", Yb, SYb)
    if reference:
        # sandwich term: column j' moves with row 1's noise of every column j through the positions
        # (-X_j'^T S^+ gt_j) and of its own column (A_j' g_n,j')
        Gt = _shared_noise_directions(X, Gz, gn)
        SpG = Sp @ Gt
        Wm = -np.einsum("akp,al->kpl", Yb, SpG)  # (k, p, k)
        Wm[np.arange(k), :, np.arange(k)] += np.einsum("kpq,kq->kp", A, gn)
        cov_v = cov_v + np.einsum("kpl,kql->kpq", Wm, Wm)
        sigma2 = _reference_sigma2(W, r, d * mz + p * k - g, A, gn, Gt, SpG)
    q = d - 1
    cov_t = cov_v[:, :q, :q]
    cov = sigma2 * np.matmul(np.matmul(T, cov_t), T.transpose(0, 2, 1))
    return np.asarray(0.5 * (cov + cov.transpose(0, 2, 1)))


def direction_angle_std(N: Array, cov: Array) -> dict[str, Array]:
    """Angle standard deviations (degrees) of unit directions from their (k, d, d) covariance.

    ``angle``: the RMS angle between the estimated and the true direction, ``sqrt(trace cov)``
    (the small-angle cone half-angle of one standard deviation); in 3-D also ``azimuth``
    (``atan2(n_y, n_x)``) and ``elevation`` (``asin(n_z)``) in the frame of ``N``. Azimuth is
    undefined at the poles (inf there).

    Examples
    --------
    >>> import numpy as np
    >>> N = np.array([[1.0, 0.0, 0.0]])
    >>> cov = np.diag([0.0, 1e-4, 4e-4])[None]
    >>> {key: np.round(v, 3).tolist() for key, v in direction_angle_std(N, cov).items()}
    {'angle': [1.281], 'azimuth': [0.573], 'elevation': [1.146]}
    """
    N = np.asarray(N, dtype=float)
    cov = np.asarray(cov, dtype=float)
    deg = 180.0 / np.pi
    out = {"angle": deg * np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2), 0.0))}
    if N.shape[1] == 3:
        rho2 = N[:, 0] ** 2 + N[:, 1] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            g_az = np.column_stack([-N[:, 1], N[:, 0], np.zeros(len(N))]) / rho2[:, None]
            g_el = np.column_stack([np.zeros((len(N), 2)), 1.0 / np.sqrt(rho2)])
            v_az = np.einsum("ja,jab,jb->j", g_az, cov, g_az)
            v_el = np.einsum("ja,jab,jb->j", g_el, cov, g_el)
        out["azimuth"] = np.where(rho2 > 1e-24, deg * np.sqrt(np.maximum(v_az, 0.0)), np.inf)
        out["elevation"] = np.where(rho2 > 1e-24, deg * np.sqrt(np.maximum(v_el, 0.0)), np.inf)
    return out
