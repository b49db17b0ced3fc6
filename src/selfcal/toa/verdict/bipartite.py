"""The bipartite generalised inverse of the range model's normal equations.

``N = J^T J`` of the TOA model couples each receiver block only with source blocks (a range
touches one of each): a Schur complement on the smaller node set gives a generalised
inverse in ``O(min(I, J)^3)`` instead of the dense ``O((I + J)^3)``. Used by
:class:`selfcal.toa.verdict.leverage.NormalEquations` (leverages, the determinacy test's
Fisher blocks, the final fit's covariance) where its bounds certify it; the dense path
(:func:`selfcal.toa.verdict.leverage.lifted_inverse`) decides otherwise.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # the caller's type, one module up (no import at run time)
    from .leverage import NormalEquations

__all__ = ["BipartiteInverse"]

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]


#: the bipartite inverse is used while a lower bound on the smallest eigenvalue of every
#: block it inverts (one over the largest absolute row sum of the inverse) stays this many
#: times above 1e-12 of ``trace(N)`` (an upper bound on N's largest eigenvalue): the cut of
#: the dense path (:func:`_normal_pinv`) with its margin; otherwise the dense path decides
_BLOCK_MARGIN = 1e3


class BipartiteInverse:
    """A generalised inverse ``G`` of ``N = J^T J`` from the bipartite structure of the TOA model.

    A range touches one receiver block ``[r_i, d_i]`` (row ``a_ij = [u_ij, 1]``) and one
    source block ``[s_j, o_j]`` (row ``b_ij = [-u_ij, 1]``), so ``N = [[A, B], [B^T, D]]``
    with ``A`` and ``D`` block diagonal (one ``p x p`` block per node). The side with more
    unknowns is eliminated (its blocks ``A_e = L_e L_e^T`` inverted one by one) and the
    Schur complement ``S = D - B^T A^-1 B = D - V^T V`` (``V = L^-1 B``) of the other side is
    formed; ``S`` is singular along the kept side's share of the gauge (Q's rows there,
    orthonormalised: ``Q_k``), so ``S^- = (S + c Q_k Q_k^T)^-1`` (``c`` S's largest diagonal
    entry) is a generalised inverse of it, and Rohde's formula ``G = [[A^-1 + A^-1 B S^- B^T
    A^-1, -A^-1 B S^-], [-S^- B^T A^-1, S^-]]`` one of N (Rohde 1965). Every quantity the
    checks take from ``(J^T J)^+`` is invariant to the choice of generalised inverse: the
    leverages ``j^T G j`` (the hat matrix ``J G J^T`` is the orthogonal projector onto the
    range of J for any of them; Searle, *Linear Models*, 1971, sec. 1.5) and the Fisher
    blocks after the S-transformation, which removes the gauge part in which two generalised
    inverses differ (:func:`selfcal.toa.verdict.determinacy.fisher_blocks`).

    Cost: ``O(m p^2 + n_e p^3)`` for the blocks, two products ``(n_k p)^2 (n_e p)`` and one
    Cholesky + inverse of ``n_k p`` (480 at 120 units) instead of the Cholesky + inverse of
    the whole ``n`` (960): 120 units, 36-54 ms against 116-137 ms for the dense lifted
    inverse in the same process (load 3). Tested against it (``tests/toa/test_postsolve_cost.py``).

    References
    ----------
    C. A. Rohde, "Generalized inverses of partitioned matrices", J. SIAM 13 (1965) 1033-1035.
    """

    swap: bool  # the sources' side eliminated (else the receivers')
    Linv: Array  # (nE, pe, pe) inverse Cholesky factors of the eliminated blocks
    Ainv: Array  # (nE, pe, pe) their inverses
    W: Array  # (nE pe, nK pk) L^-1 B S^-
    W4: Array  # the same, (nE, pe, nK, pk)
    V: Array  # (nE pe, nK pk) L^-1 B
    Sg: Array  # (nK pk, nK pk) S^-, Fortran-ordered, its upper triangle only (zeros below)
    Sg_top: float  # the largest absolute row sum of S^-
    Ke: Array  # (nE, pe, pe) V_e S^- V_e^T
    Sd: Array  # (nK, pk, pk) diagonal blocks of S^-
    info_e: Array  # (nE, pe, pe) information blocks of the eliminated side
    info_k: Array  # (nK, pk, pk) of the kept side
    idx_e: NDArray[np.intp]  # (nE, pe) their places in the parameter vector
    idx_k: NDArray[np.intp]  # (nK, pk)
    rows_r: Array  # (I, J, pr) receiver parts of the Jacobian rows (zero where unobserved)
    rows_s: Array  # (I, J, ps) source parts
    nE: int
    nK: int
    pe: int
    pk: int

    def __init__(self, **parts: Any) -> None:
        for name in self.__annotations__:
            setattr(self, name, parts[name])

    @classmethod
    def build(cls, ne: NormalEquations) -> BipartiteInverse | None:
        """From a :class:`NormalEquations`; None when a block is singular or too ill-conditioned."""
        import scipy.linalg

        pat = ne.pattern
        I, J = pat.shape
        d = ne.dim
        has_r, has_s = ne.offsets in ("receivers", "both"), ne.offsets in ("sources", "both")
        r, s = ne.theta[:I * d].reshape(I, d), ne.theta[I * d:(I + J) * d].reshape(J, d)  # toa_jacobian's layout
        U = r[:, None, :] - s[None, :, :]
        nrm = np.linalg.norm(U, axis=2, keepdims=True)
        U = np.divide(U, nrm, out=np.zeros_like(U), where=nrm > 0) * pat[..., None]
        w = pat[..., None].astype(float)
        rows_r = np.concatenate([U, w], axis=2) if has_r else U  # (I, J, pr)
        rows_s = np.concatenate([-U, w], axis=2) if has_s else -U  # (I, J, ps)
        k = (I + J) * d
        idx_r = [np.arange(I)[:, None] * d + np.arange(d)]
        idx_s = [I * d + np.arange(J)[:, None] * d + np.arange(d)]
        if has_r:
            idx_r.append((k + np.arange(I))[:, None])
            k += I
        if has_s:
            idx_s.append((k + np.arange(J))[:, None])
        ir, js = np.concatenate(idx_r, axis=1), np.concatenate(idx_s, axis=1)
        swap = J * rows_s.shape[2] > I * rows_r.shape[2]  # keep the side with fewer unknowns
        if swap:  # eliminate the receivers' side: e = sources ... as written for e = receivers
            Ae, Bk = rows_s.transpose(1, 0, 2), rows_r.transpose(1, 0, 2)
            idx_e, idx_k = js, ir
        else:
            Ae, Bk = rows_r, rows_s
            idx_e, idx_k = ir, js
        nE, nK, pe = Ae.shape
        pk = Bk.shape[2]
        info_e = np.matmul(Ae.transpose(0, 2, 1), Ae)  # the eliminated nodes' information blocks
        info_k = np.matmul(Bk.transpose(1, 2, 0), Bk.transpose(1, 0, 2))
        trace = float(np.einsum("epp->", info_e) + np.einsum("kpp->", info_k))
        if not trace > 0:
            return None
        floor = _BLOCK_MARGIN * 1e-12 * trace
        try:
            Linv = np.linalg.inv(np.linalg.cholesky(info_e))  # (nE, pe, pe)
        except np.linalg.LinAlgError:
            return None
        Ainv = np.matmul(Linv.transpose(0, 2, 1), Linv)
        if not np.all(np.isfinite(Ainv)) or 1.0 / np.max(np.abs(Ainv).sum(axis=2)) <= floor:
            return None
        Cc = np.matmul(Ae, Linv.transpose(0, 2, 1))  # L_e^-1 a_ek
        V4 = np.empty((nE, pe, nK, pk))  # the rank-one blocks (L_e^-1 a_ek) b_ek^T, written in place
        np.multiply(Cc.transpose(0, 2, 1)[:, :, :, None], Bk[:, None, :, :], out=V4)
        V = V4.reshape(nE * pe, nK * pk)
        # S = D - V^T V in the upper triangle of a Fortran-ordered array (all that potrf and potri
        # read and write there: no transposed copies, no symmetrisation of the 480 x 480 inverse);
        # its transpose, a C-ordered view, holds the same matrix in its lower triangle
        Sf = scipy.linalg.blas.dsyrk(-1.0, V.T, trans=0, lower=0)
        S4 = Sf.T.reshape(nK, pk, nK, pk)
        S4[np.arange(nK), :, np.arange(nK), :] += info_k
        U_q, sv, _ = np.linalg.svd(ne.Q[idx_k.ravel()], full_matrices=False)
        if sv.size < ne.Q.shape[1] or sv[-1] <= 1e-8 * sv[0]:
            return None  # part of the gauge does not reach the kept side: not this path
        c = float(np.max(np.diag(Sf)))
        if not c > 0:
            return None
        Sf = scipy.linalg.blas.dsyrk(c, U_q, beta=1.0, c=Sf, trans=0, lower=0, overwrite_c=1)  # + c Q_k Q_k^T
        Rf, info = scipy.linalg.lapack.dpotrf(Sf, lower=0, clean=1, overwrite_a=1)  # R^T R, R upper
        if info != 0:
            return None
        Sg, info = scipy.linalg.lapack.dpotri(Rf, lower=0, overwrite_c=1)  # S^-: upper triangle, zeros below
        if info != 0:
            return None
        # the largest absolute row sum of the symmetric S^- from its triangle: rows plus columns
        Sa = np.abs(Sg)
        top = float(np.max(Sa.sum(axis=1) + Sa.sum(axis=0) - np.diag(Sa)))
        if not (np.isfinite(top) and top > 0 and 1.0 / top > floor):
            return None
        W = scipy.linalg.blas.dsymm(1.0, Sg, V.T, side=0, lower=0).T  # L^-1 B S^-, (nE pe, nK pk), C-ordered
        W4 = W.reshape(nE, pe, nK, pk)
        Ke = np.matmul(W.reshape(nE, pe, nK * pk), V.reshape(nE, pe, nK * pk).transpose(0, 2, 1))  # V_e S^- V_e^T
        kk = np.arange(nK)[:, None] * pk + np.arange(pk)
        Sd = Sg[kk[:, :, None], kk[:, None, :]]  # (nK, pk, pk), their upper triangles
        Sd = Sd + np.triu(Sd, 1).transpose(0, 2, 1)
        return cls(swap=swap, Linv=Linv, Ainv=Ainv, W=W, W4=W4, V=V, Sg=Sg, Sg_top=top, Ke=Ke, Sd=Sd,
                   info_e=info_e, info_k=info_k, idx_e=idx_e, idx_k=idx_k, rows_r=rows_r, rows_s=rows_s,
                   nE=nE, nK=nK, pe=pe, pk=pk)

    def hat(self, ii: NDArray[np.intp], jj: NDArray[np.intp], a: Array, b: Array) -> Array:
        """``j^T G j`` for the Jacobian rows of entries (ii, jj): receiver part ``a`` (m, pr), source part ``b`` (m, ps)."""
        e, k, ae, bk = (jj, ii, b, a) if self.swap else (ii, jj, a, b)
        c = np.einsum("mpq,mq->mp", self.Linv[e], ae)
        return (np.einsum("mp,mp->m", c, c) + np.einsum("mp,mpq,mq->m", c, self.Ke[e], c)
                - 2.0 * np.einsum("mp,mpq,mq->m", c, self.W4[e, :, k, :], bk)
                + np.einsum("mp,mpq,mq->m", bk, self.Sd[k], bk))

    def pattern_hat(self, pattern: Mask) -> Array:
        """Leverages of the fitted entries, row-major order of ``pattern``."""
        if not pattern.all():
            ii, jj = np.nonzero(pattern)
            return self.hat(ii, jj, self.rows_r[ii, jj], self.rows_s[ii, jj])
        # complete: the same four terms on the (eliminated, kept) grid, without gathers
        ae, bk = ((self.rows_s.transpose(1, 0, 2), self.rows_r.transpose(1, 0, 2)) if self.swap
                  else (self.rows_r, self.rows_s))  # (nE, nK, pe), (nE, nK, pk)
        c = np.matmul(ae, self.Linv.transpose(0, 2, 1))  # L_e^-1 a_ek
        h = (np.einsum("ekp,ekp->ek", c, c) + np.einsum("ekp,ekp->ek", np.matmul(c, self.Ke), c)
             - 2.0 * np.einsum("ekq,ekq->ek", np.einsum("ekp,epkq->ekq", c, self.W4), bk)
             + np.einsum("ekq,ekq->ek", np.einsum("ekp,kpq->ekq", bk, self.Sd), bk))
        return (h.T if self.swap else h).ravel()

    def diagonal_blocks(self) -> tuple[Array, Array, Array, Array]:
        """The nodes' diagonal blocks of G and of N: (G_receivers (I, pr, pr), G_sources (J, ps, ps),
        N_receivers, N_sources)."""
        Ge = self.Ainv + np.matmul(np.matmul(self.Linv.transpose(0, 2, 1), self.Ke), self.Linv)
        return (self.Sd, Ge, self.info_k, self.info_e) if self.swap else (Ge, self.Sd, self.info_e, self.info_k)

    def newton_step(self, F: Array, Q: Array) -> Array:
        """The Gauss-Newton step ``N^+ J^T f`` off the gauge ``Q`` (n, g) for residuals ``F`` (I, J)
        (0 where unobserved), in the parameter order of :func:`selfcal.toa.engine.nls.toa_jacobian`."""
        n = self.idx_e.size + self.idx_k.size
        g = np.zeros(n)
        F = np.where(np.isfinite(F), F, 0.0)
        g[(self.idx_k if self.swap else self.idx_e).ravel()] = np.einsum("ijp,ij->ip", self.rows_r, F).ravel()
        g[(self.idx_e if self.swap else self.idx_k).ravel()] = np.einsum("ijp,ij->jp", self.rows_s, F).ravel()
        dx = self.apply(g[:, None])[:, 0]
        return dx - Q @ (Q.T @ dx)

    def norm_bound(self) -> float:
        """An upper bound on ``|G|_2``: the norms of its blocks, ``|G| <= |G_ee| + |G_kk| + 2 |G_ek|``
        with ``G_ee = L^-T (I + V S^- V^T) L^-1``, ``G_ek = -L^-T W``, ``G_kk = S^-`` (spectral
        norms of the block-diagonal factors, Frobenius norms of the dense ones, the largest
        absolute row sum of ``S^-``)."""
        lin = float(np.max(np.linalg.norm(self.Linv, ord=2, axis=(1, 2)))) ** 2  # |L^-1|^2
        ainv = float(np.max(np.linalg.norm(self.Ainv, ord=2, axis=(1, 2))))
        w, v = float(np.linalg.norm(self.W)), float(np.linalg.norm(self.V))
        sg = self.Sg_top
        return ainv + lin * w * v + sg + 2.0 * np.sqrt(lin) * w

    def _sym(self, X: Array) -> Array:
        """``S^- X`` from the triangle :attr:`Sg` holds (BLAS ``symm``)."""
        import scipy.linalg

        return np.asarray(scipy.linalg.blas.dsymm(1.0, self.Sg, X, side=0, lower=0))

    def apply(self, X: Array) -> Array:
        """``G X`` for X (n, g) in the parameter order of :func:`selfcal.toa.engine.nls.toa_jacobian`."""
        nE, pe = self.nE, self.pe
        g = X.shape[1]
        xe = X[self.idx_e.ravel()]  # (nE pe, g), block order
        xk = X[self.idx_k.ravel()]
        ye = np.einsum("epq,eqg->epg", self.Linv, xe.reshape(nE, pe, g)).reshape(nE * pe, g)  # L^-1 x_e
        # G_ee x_e = A^-1 x_e + L^-T W V^T L^-1 x_e ; G_ek x_k = -L^-T W x_k
        # G_ke x_e = -W^T L^-1 x_e                 ; G_kk x_k = S^- x_k
        inner = (self.W @ (self.V.T @ ye - xk)).reshape(nE, pe, g)
        out_e = (np.einsum("epq,eqg->epg", self.Ainv, xe.reshape(nE, pe, g))
                 + np.einsum("eqp,eqg->epg", self.Linv, inner)).reshape(nE * pe, g)
        out_k = self._sym(xk) - self.W.T @ ye
        out = np.empty_like(X, dtype=float)
        out[self.idx_e.ravel()] = out_e
        out[self.idx_k.ravel()] = out_k
        return out
