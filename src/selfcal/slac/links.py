"""Link bookkeeping of the SLAC filter: which state entries each received snapshot depends on, and
the likelihood of all links with its gradient and Fisher information in state coordinates.

* Range model (paper 002, eq. 1): the snapshot that agent i receives back from node j has
  round-trip range ``rho = |p_j - p_i| - delta_i - delta_j``; DoA in i's body frame (eq. 2):
  ``phi = atan2(y_j - y_i, x_j - x_i) - psi_i``.
* Links are grouped by the receiver's port count M; a :class:`LinkLayout` holds a group's
  static index arrays (cached per link pattern, so a step with the same links reuses them) and
  a :class:`LinkGroup` the snapshots of one update.
* :meth:`LinkModel.neg_loglik` is the negative sum of the concentrated log-likelihoods
  (eqs. 18/19, 24-25) with its gradient (eq. 26); :meth:`LinkModel.information` the Fisher
  information ``sum_l J_l^T F_l J_l`` of all links (first-estimates g part, optionally).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .likelihood import DelayExpansion, delay_expansion, fisher_blocks, link_loglik, unpack_g
from .state import StateLayout

__all__ = ["LinkLayout", "LinkGroup", "LinkModel"]

FArray = NDArray[np.float64]
CArray = NDArray[np.complex128]
IArray = NDArray[np.int64]


@dataclass(eq=False)
class LinkLayout:
    """Static index arrays of the links whose receiver has M ports, for one link pattern.

    Index arrays point into the state extended by one dummy slot (index D) that holds 0, so
    that anchors (fixed positions) and unestimated biases need no branches.

    Attributes
    ----------
    M : int
        Port count of the receivers.
    sel : (L,) int array
        Positions of these links in the update's link list.
    rx, tx : (L,) int arrays
        Receiving agent and transmitting node (agents 0..n-1, then anchors).
    prx, ptx : (L, 2) int arrays
        State indices of the receiver's and transmitter's x, y (D for an anchor).
    psi : (L,) int array
        State index of the receiver's heading.
    brx, btx : (L,) int arrays
        State indices of the two biases (D where not estimated).
    gidx : (L, 2 M U) int array or None
        State indices of the receiver's packed sampling matrix (SLAC mode, M > 1).
    tx_agent : (L, 1) bool array
        Whether the transmitter is an agent.
    anchor_pos : (L, 2) array
        The transmitting anchor's position (m; unused for agents).
    Xbuf : (L, M, N) complex array
        Work buffer of ``X = R * conj(s)`` (reused by every update with this pattern).
    exp_work : tuple of complex arrays
        Work buffers of :func:`~selfcal.slac.likelihood.delay_expansion`.
    info_index : int array
        Flat scatter indices of the group's information blocks into the (D+1, D+1) matrix.
    receivers : list of (int, int array)
        Per receiver with a sampling-matrix state: its first g index and its links.
    scatter, gscatter : int arrays or None
        Scatter indices of the gradient without / with the g part (filled on first use).
    """

    M: int
    sel: IArray
    rx: IArray
    tx: IArray
    prx: IArray
    ptx: IArray
    psi: IArray
    brx: IArray
    btx: IArray
    gidx: IArray | None
    tx_agent: NDArray[np.bool_]
    anchor_pos: FArray
    Xbuf: CArray
    exp_work: tuple[CArray, CArray]
    info_index: IArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    receivers: list[tuple[int, IArray]] = field(default_factory=list)
    scatter: IArray | None = None
    gscatter: IArray | None = None


@dataclass(frozen=True, eq=False)
class LinkGroup:
    """The snapshots of one update on the links of one :class:`LinkLayout`.

    Attributes
    ----------
    layout : LinkLayout
    X : (L, M, N) complex array
        ``R * conj(s)`` per link (a view of ``layout.Xbuf`` unless copied).
    var : (L,) array
        Noise variance per bin and port.
    exp : DelayExpansion or None
        Delay series of X around the predicted ranges (``delay_series``).
    """

    layout: LinkLayout
    X: CArray
    var: FArray
    exp: DelayExpansion | None


class LinkModel:
    """The likelihood of a set of links as a function of the state (module docstring).

    Parameters
    ----------
    anchors : (A, 2) array
        Anchor positions, m.
    ports : (n,) int array
        Port count per agent.
    G_prior : sequence of (M_i, U) complex arrays or None
        Prior sampling matrices (used where G is not a state).
    probe : (N,) complex array
        The known OFDM spectrum.
    k : float
        Range wavenumber (:func:`~selfcal.slac.signals.range_wavenumber`), rad/m per bin.
    state : StateLayout
    calibrate : bool
        SLAC mode (G and biases are states).
    delay_series, first_estimates : bool
        See :class:`~selfcal.slac.filter.SlacConfig`.
    """

    def __init__(self, anchors: FArray, ports: IArray, G_prior: Sequence[CArray | None], probe: CArray, k: float,
                 state: StateLayout, *, calibrate: bool, delay_series: bool, first_estimates: bool) -> None:
        self.anchors = anchors
        self.ports = ports
        self.n = int(ports.size)
        self.G_prior = list(G_prior)
        self.probe = probe
        self.N = probe.size
        self.k = k
        self.probe_power = np.abs(probe) ** 2
        self.S = float(np.sum(self.probe_power))
        self.state = state
        self.calibrate = calibrate
        self.delay_series = delay_series
        self.first_estimates = first_estimates
        self.cache: dict[tuple[bytes, bytes], list[LinkLayout]] = {}

    def layout(self, rx: IArray, tx: IArray) -> list[LinkLayout]:
        """Static per-group index arrays for this link pattern, cached while it is unchanged.

        One group per port count M; also holds the scatter indices of the information matrix
        and the work buffer of the group's ``X = R * conj(s)``.
        """
        key = (rx.tobytes(), tx.tobytes())
        cached = self.cache.get(key)
        if cached is not None:
            return cached
        st = self.state
        D = st.D
        W = D + 1
        layout = []
        for M in np.unique(self.ports[rx]):
            sel = np.flatnonzero(self.ports[rx] == M)
            r, t = rx[sel], tx[sel]
            prx = np.stack([3 * r, 3 * r + 1], axis=1)
            ptx = np.where((t < self.n)[:, None], np.stack([3 * t, 3 * t + 1], axis=1), D)
            brx = np.where(st.bias_index[r] >= 0, st.bias_index[r], D)
            btx = np.where(st.bias_index[t] >= 0, st.bias_index[t], D)
            gidx = None
            if M > 1 and self.calibrate:
                gidx = np.stack([st.g_index[int(i)] for i in r])
            lay = LinkLayout(
                M=int(M), sel=sel, rx=r, tx=t, prx=prx, ptx=ptx, psi=3 * r + 2, brx=brx, btx=btx, gidx=gidx,
                tx_agent=(t < self.n)[:, None], anchor_pos=self.anchors[np.clip(t - self.n, 0, None)],
                Xbuf=np.empty((sel.size, int(M), self.N), dtype=complex),
                exp_work=(np.empty((sel.size, self.N), dtype=complex),
                          np.empty((sel.size, int(M), self.N), dtype=complex)),
            )
            idx = np.column_stack([prx, ptx, brx, btx])
            if M > 1:
                idx = np.column_stack([idx, 3 * r + 2])
            parts = [(idx[:, :, None] * W + idx[:, None, :]).ravel()]
            if gidx is not None:
                lg = idx[:, :, None] * W + gidx[:, None, :]
                gl = gidx[:, :, None] * W + idx[:, None, :]
                parts += [lg.ravel(), gl.ravel()]
                for i in np.unique(r):
                    lay.receivers.append((int(st.g_index[int(i)][0]), np.flatnonzero(r == i)))
            lay.info_index = np.concatenate(parts).astype(np.int64)
            layout.append(lay)
        if len(self.cache) >= 8:
            self.cache.pop(next(iter(self.cache)))
        self.cache[key] = layout
        return layout

    def groups(self, rx: IArray, tx: IArray, snaps: Sequence[CArray], noise_var: FArray,
               x: FArray) -> list[LinkGroup]:
        """The update's link groups: ``X = R * conj(s)`` per link, its noise and delay series at x.

        Parameters
        ----------
        rx, tx : (L,) int arrays
        snaps : L complex arrays (M_rx, N)
        noise_var : (L,) array
        x : (D,) array
            State at which the delay series is centred (the prediction).
        """
        groups = []
        pc = self.probe.conj()
        for lay in self.layout(rx, tx):
            X = lay.Xbuf
            for j, l in enumerate(lay.sel):
                np.multiply(np.atleast_2d(snaps[l]), pc, out=X[j])
            exp = None
            if self.delay_series:
                rho0 = self.geometry(np.append(x, 0.0), lay)[2]
                exp = delay_expansion(X, rho0, self.k, work=lay.exp_work)
            groups.append(LinkGroup(layout=lay, X=X, var=noise_var[lay.sel], exp=exp))
        return groups

    @staticmethod
    def geometry(xe: FArray, lay: LinkLayout) -> tuple[FArray, ...]:
        """``(diff (L, 2), d (L,), rho (L,), phi (L,))`` at the extended state ``xe`` (eqs. 1-2)."""
        pr = xe[lay.prx]
        pt = np.where(lay.tx_agent, xe[lay.ptx], lay.anchor_pos)
        diff = pt - pr
        d = np.maximum(np.hypot(diff[:, 0], diff[:, 1]), 1e-6)  # nodes may pass each other
        rho = d - xe[lay.brx] - xe[lay.btx]
        phi = np.arctan2(diff[:, 1], diff[:, 0]) - xe[lay.psi]
        return diff, d, rho, phi

    def G_of(self, xe: FArray, lay: LinkLayout) -> CArray:
        """Sampling matrices (L, M, U) of the group's receivers: the state's, or the prior."""
        r = lay.rx
        if lay.gidx is not None and self.calibrate:
            U = self.G_prior[int(r[0])].shape[1]  # type: ignore[union-attr]
            return unpack_g(xe[lay.gidx], lay.M, U)
        return np.stack([self.G_prior[int(i)] for i in r])  # type: ignore[misc]

    def _terms(self, xe: FArray, grp: LinkGroup, *, want_grad: bool) -> tuple[Any, ...]:
        """``(layout, diff, d, phi, G, LinkTerms)`` of one group at the extended state ``xe``."""
        lay = grp.layout
        diff, d, rho, phi = self.geometry(xe, lay)
        G = self.G_of(xe, lay) if lay.M > 1 else None
        terms = link_loglik(grp.X, rho, grp.var, self.k, self.S, phi=phi if lay.M > 1 else None, G=G,
                            want_grad=want_grad, expansion=grp.exp)
        return lay, diff, d, phi, G, terms

    @staticmethod
    def _grad_index(lay: LinkLayout, with_g: bool) -> IArray:
        """Where each value :meth:`neg_loglik` produces for the group goes (fixed per pattern)."""
        parts = [lay.prx.ravel(), lay.ptx.ravel(), lay.brx, lay.btx]
        if lay.M > 1:
            parts += [lay.prx.ravel(), lay.ptx.ravel(), lay.psi]
            if with_g:
                assert lay.gidx is not None
                parts.append(lay.gidx.ravel())
        return np.concatenate(parts).astype(np.int64)

    def neg_loglik(self, x: FArray, groups: list[LinkGroup]) -> tuple[float, FArray]:
        """Negative log-likelihood of all links at x (eq. 24) and its gradient (D,) (eq. 26)."""
        xe = np.append(x, 0.0)
        idx_parts: list[IArray] = []
        val_parts: list[FArray] = []
        total = 0.0
        for grp in groups:
            lay, diff, d, phi, _, terms = self._terms(xe, grp, want_grad=True)
            M = lay.M
            total -= float(terms.value.sum())
            u = diff / d[:, None]
            gr = terms.d_rho  # minus the gradient of the NLL
            vals = [(gr[:, None] * u).ravel(), (-gr[:, None] * u).ravel(), gr, gr]
            with_g = False
            if M > 1:
                gp = terms.d_phi
                dphi = np.stack([-diff[:, 1], diff[:, 0]], axis=1) / (d**2)[:, None]
                vals += [(gp[:, None] * dphi).ravel(), (-gp[:, None] * dphi).ravel(), gp]
                if lay.gidx is not None and self.calibrate and terms.d_G is not None:
                    with_g = True
                    v = np.swapaxes(terms.d_G, 1, 2).reshape(d.size, -1)
                    vals.append(-np.concatenate([v.real, v.imag], axis=1).ravel())
            # one index vector per group and link pattern, reused by every call
            if with_g:
                if lay.gscatter is None:
                    lay.gscatter = self._grad_index(lay, True)
                idx_parts.append(lay.gscatter)
            else:
                if lay.scatter is None:
                    lay.scatter = self._grad_index(lay, False)
                idx_parts.append(lay.scatter)
            val_parts.append(np.concatenate(vals))
        ge = np.asarray(np.bincount(np.concatenate(idx_parts), weights=np.concatenate(val_parts),
                                    minlength=x.size + 1), dtype=float)
        return total, ge[:-1]

    def information(self, x: FArray, groups: list[LinkGroup], fej: bool = True) -> FArray:
        """Fisher information (D, D) of all links at x (eqs. 18-19 mapped by the range model, eqs. 1-2).

        Per link, ``J^T F J`` with the (rho, phi) Jacobian J in the pose / bias coordinates and
        the identity for g, from :func:`~selfcal.slac.likelihood.fisher_blocks`; scattered with
        the cached index arrays of :meth:`layout`. With ``fej`` (and ``first_estimates``) the
        g part is evaluated at the prior G (first-estimates Jacobian).
        """
        D = x.size
        xe = np.append(x, 0.0)
        if fej and self.first_estimates and self.calibrate:
            for i, gi in self.state.g_index.items():
                xe[gi] = self.state.g_prior_packed[i]
        W = D + 1
        idx_parts: list[IArray] = []
        val_parts: list[FArray] = []
        gg_blocks: list[tuple[int, FArray]] = []
        pp = self.probe_power
        for grp in groups:
            lay, diff, d, phi, G, terms = self._terms(xe, grp, want_grad=False)
            M = lay.M
            fb = fisher_blocks(terms, grp.var, self.k, pp, phi=phi if M > 1 else None, G=G)
            L_ = d.size
            u = diff / d[:, None]
            J = 6 if M == 1 else 7
            jr = np.zeros((L_, J))
            jr[:, 0:2] = -u
            jr[:, 2:4] = u
            jr[:, 4:6] = -1.0
            Hll = fb.rho_rho[:, None, None] * jr[:, :, None] * jr[:, None, :]
            idx_parts.append(lay.info_index)
            if M == 1:
                val_parts.append(Hll.ravel())
                continue
            dphi = np.stack([-diff[:, 1], diff[:, 0]], axis=1) / (d**2)[:, None]
            jp = np.zeros((L_, J))
            jp[:, 0:2] = -dphi
            jp[:, 2:4] = dphi
            jp[:, 6] = -1.0
            Hll += fb.phi_phi[:, None, None] * jp[:, :, None] * jp[:, None, :]
            val_parts.append(Hll.ravel())
            if lay.gidx is not None and self.calibrate:
                assert fb.phi_g is not None
                # (rho, phi) -> (pose, bias) block and its coupling with the identity-mapped g block
                Hlg = jp[:, :, None] * fb.phi_g[:, None, :]
                val_parts += [Hlg.ravel(), np.swapaxes(Hlg, 1, 2).ravel()]
                # every link of one receiver adds to the same contiguous g block: sum first
                for g0, links in lay.receivers:
                    gg_blocks.append((g0, fb.gg_sum(links)))
        H = np.asarray(np.bincount(np.concatenate(idx_parts), weights=np.concatenate(val_parts),
                                   minlength=W * W), dtype=float).reshape(W, W)
        for g0, blk_g in gg_blocks:
            H[g0 : g0 + blk_g.shape[0], g0 : g0 + blk_g.shape[0]] += blk_g
        return H[:-1, :-1]
