"""Validation of SLAC logs (``docs/slac_log_format.md``) before a run, one named field per error.

:func:`validate_log_arrays` checks the arrays of an ``.npz`` log the way recordings are
checked: shapes against each other, dtypes, NaN / inf anywhere, physical signs (``T > 0``,
``bandwidth > 0``, noise densities >= 0), links (no node linked to itself, indices in range),
``ports >= 1``, at least one step, and positive-definite initial covariances. Every failure is
an :class:`~selfcal.errors.InputError` whose message names the file and the field.

:func:`check_simulation_request` refuses a ``slac simulate`` whose log would not fit in memory
(or whose SNR / length is not a number) before anything is allocated.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["validate_log_arrays", "check_simulation_request", "LOG_ROWS_PER_STEP", "STEP_SECONDS"]

#: Snapshot rows per step of the 3-anchor / 4-rover replica (docs/slac_log_format.md: R = 42).
LOG_ROWS_PER_STEP = 42
#: Largest |SNR| (dB) of a simulated log: complex64 snapshots resolve ~150 dB, so more is meaningless.
MAX_SNR_DB = 200.0
#: Step of the replica (s).
STEP_SECONDS = 0.1


def _field(z: Mapping[str, Any], key: str, label: str) -> np.ndarray:
    if key not in z:
        raise InputError(f"{label}: field {key!r} is missing")
    return np.asarray(z[key])


def _numeric(a: np.ndarray, key: str, label: str, *, complex_ok: bool = False, integer: bool = False) -> None:
    kinds = "iu" if integer else ("fiuc" if complex_ok else "fiu")
    if a.dtype.kind not in kinds:
        want = "integers" if integer else ("numbers" if complex_ok else "real numbers")
        raise InputError(f"{label}: field {key!r} has dtype {a.dtype}; expected {want}")
    if a.dtype.kind in "fc" and not np.isfinite(a).all():
        bad = np.argwhere(~np.isfinite(a))[0]
        raise InputError(f"{label}: field {key!r} has NaN or inf (first at index {tuple(int(i) for i in bad)})")


def _scalar(z: Mapping[str, Any], key: str, label: str, *, positive: bool = False,
            nonnegative: bool = False, optional: bool = False) -> float | None:
    if key not in z and optional:
        return None
    a = _field(z, key, label)
    if a.size != 1 or a.dtype.kind not in "fiu":
        raise InputError(f"{label}: field {key!r} must be one real number, got shape {a.shape} dtype {a.dtype}")
    v = float(a.reshape(-1)[0])
    if optional and np.isnan(v):
        return None
    if not np.isfinite(v):
        raise InputError(f"{label}: field {key!r} is {v} (must be finite)")
    if positive and v <= 0:
        raise InputError(f"{label}: field {key!r} = {v:g} must be > 0")
    if nonnegative and v < 0:
        raise InputError(f"{label}: field {key!r} = {v:g} is negative (a noise level must be >= 0)")
    return v


def validate_log_arrays(z: Mapping[str, Any], label: str = "log") -> None:
    """Check the arrays of a SLAC log (format v1); raise :class:`InputError` naming the field.

    Parameters
    ----------
    z:
        Mapping key -> array, as loaded from the ``.npz`` (``selfcal.io.load_npz``).
    label:
        The file name, used in messages.

    Raises
    ------
    InputError
        A missing field, wrong dtype or shape, NaN / inf, ``T <= 0``, ``bandwidth <= 0``,
        negative noise densities, ``ports < 1``, a link from a node to itself or to a node
        that does not exist, zero steps / links / subcarriers, a non-positive-definite
        ``init_cov``, or signals whose shape does not match the links.

    Examples
    --------
    >>> validate_log_arrays({"version": np.array(1)}, "x.npz")
    Traceback (most recent call last):
    ...
    selfcal.errors.InputError: x.npz: field 'anchors' is missing
    """
    anchors = _field(z, "anchors", label)
    _numeric(anchors, "anchors", label)
    if anchors.ndim != 2 or anchors.shape[1] != 2 or anchors.shape[0] < 1:
        raise InputError(f"{label}: field 'anchors' has shape {anchors.shape}; expected (A, 2) with A >= 1")
    A = anchors.shape[0]
    ports = _field(z, "ports", label)
    _numeric(ports, "ports", label, integer=True)
    if ports.ndim != 1 or ports.size < 1:
        raise InputError(f"{label}: field 'ports' has shape {ports.shape}; expected (n,) with n >= 1 agents")
    if (ports < 1).any():
        i = int(np.argmax(ports < 1))
        raise InputError(f"{label}: field 'ports' of agent {i} is {int(ports[i])}; every agent has >= 1 antenna port")
    n = ports.size
    mmax = int(ports.max())
    shapes = {}
    for key in ("G_em", "G_chamber"):
        G = _field(z, key, label)
        _numeric(G, key, label, complex_ok=True)
        if G.ndim != 3 or G.shape[0] != n or G.shape[1] < mmax or G.shape[2] < 1:
            raise InputError(f"{label}: field {key!r} has shape {G.shape}; expected ({n}, >= {mmax}, U)")
        shapes[key] = G.shape
    if shapes["G_em"] != shapes["G_chamber"]:
        raise InputError(f"{label}: fields 'G_em' {shapes['G_em']} and 'G_chamber' {shapes['G_chamber']} differ in shape")
    controls = _field(z, "controls", label)
    _numeric(controls, "controls", label)
    if controls.ndim != 3 or controls.shape[1:] != (n, 2):
        raise InputError(f"{label}: field 'controls' has shape {controls.shape}; expected (S, {n}, 2)")
    S = controls.shape[0]
    if S < 1:
        raise InputError(f"{label}: field 'controls' has zero steps; a log needs at least one step")
    rx, tx = _field(z, "rx", label), _field(z, "tx", label)
    for key, a in (("rx", rx), ("tx", tx)):
        _numeric(a, key, label, integer=True)
        if a.ndim != 1 or a.size < 1:
            raise InputError(f"{label}: field {key!r} has shape {a.shape}; expected (L,) with L >= 1 links")
    if rx.shape != tx.shape:
        raise InputError(f"{label}: fields 'rx' {rx.shape} and 'tx' {tx.shape} differ in length")
    if ((rx < 0) | (rx >= n)).any():
        l = int(np.argmax((rx < 0) | (rx >= n)))
        raise InputError(f"{label}: field 'rx' link {l} names node {int(rx[l])}; receivers are agents 0..{n - 1}")
    if ((tx < 0) | (tx >= n + A)).any():
        l = int(np.argmax((tx < 0) | (tx >= n + A)))
        raise InputError(f"{label}: field 'tx' link {l} names node {int(tx[l])}; nodes are 0..{n + A - 1}")
    if (rx == tx).any():
        l = int(np.argmax(rx == tx))
        raise InputError(f"{label}: link {l} connects node {int(rx[l])} to itself (fields 'rx', 'tx')")
    probe = _field(z, "probe", label)
    _numeric(probe, "probe", label, complex_ok=True)
    if probe.ndim != 1 or probe.size < 1:
        raise InputError(f"{label}: field 'probe' has shape {probe.shape}; expected (N,) with N >= 1 subcarriers")
    if not np.any(probe != 0):
        raise InputError(f"{label}: field 'probe' is all zeros")
    _scalar(z, "T", label, positive=True)
    _scalar(z, "bandwidth", label, positive=True)
    _scalar(z, "carrier", label, positive=True, optional=True)
    _scalar(z, "sigma_v", label, nonnegative=True)
    _scalar(z, "sigma_omega", label, nonnegative=True)
    x0 = _field(z, "init_poses", label)
    _numeric(x0, "init_poses", label)
    if x0.shape != (n, 3):
        raise InputError(f"{label}: field 'init_poses' has shape {x0.shape}; expected ({n}, 3)")
    P0 = _field(z, "init_cov", label)
    _numeric(P0, "init_cov", label)
    if P0.shape != (n, 3, 3):
        raise InputError(f"{label}: field 'init_cov' has shape {P0.shape}; expected ({n}, 3, 3)")
    for i in range(n):
        P = P0[i].astype(float)
        if not np.allclose(P, P.T, rtol=1e-8, atol=1e-12 * max(1.0, float(np.abs(P).max()))):
            raise InputError(f"{label}: field 'init_cov' of agent {i} is not symmetric")
        try:
            np.linalg.cholesky(P)
        except np.linalg.LinAlgError:
            raise InputError(f"{label}: field 'init_cov' of agent {i} is not positive definite") from None
    sig = _field(z, "signals", label)
    rows = int(ports[rx].sum())
    if sig.ndim != 3 or sig.shape != (S, rows, probe.size):
        raise InputError(f"{label}: field 'signals' has shape {sig.shape}; expected {(S, rows, probe.size)} "
                         f"(steps, sum of receiver ports over the links, subcarriers)")
    _numeric(sig, "signals", label, complex_ok=True)
    if "names" in z:
        names = np.asarray(z["names"])
        if names.dtype.kind not in "US" or names.shape != (n,):
            raise InputError(f"{label}: field 'names' has shape {names.shape} dtype {names.dtype}; expected ({n},) strings")
    for key, shape in (("true_states", (S + 1, n, 3)), ("true_biases", (n + A,)),
                       ("true_G_true", shapes["G_em"])):
        if key in z:
            a = np.asarray(z[key])
            _numeric(a, key, label, complex_ok=key == "true_G_true")
            if a.shape != shape:
                raise InputError(f"{label}: field {key!r} has shape {a.shape}; expected {shape}")


def check_simulation_request(minutes: Any, subcarriers: Any, snr_db: Any, *, limit: float | None = None) -> None:
    """Refuse a ``slac simulate`` request up front: not-a-number SNR / length, or a log too large.

    The log stores every snapshot: ``8 S R N`` bytes (complex64) with ``S = minutes * 60 / T``
    steps and ``R = 42`` rows (docs/slac_log_format.md), twice that while it is compressed.

    Raises
    ------
    InputError
        Naming the option and, for sizes, the memory the log would need.
    """
    from .._checks import check_float, check_int, guard_size

    m = check_float(minutes, "--minutes", positive=True, allow_none=False)
    N = check_int(subcarriers, "--subcarriers", minimum=8)
    snr = check_float(snr_db, "--snr-db", allow_none=False)
    assert snr is not None
    if abs(snr) > MAX_SNR_DB:
        raise InputError(f"--snr-db {snr:g} is beyond +-{MAX_SNR_DB:g} dB; the complex64 snapshots hold about "
                         f"150 dB of dynamic range")
    assert m is not None and N is not None
    steps = m * 60.0 / STEP_SECONDS
    need = 2.0 * 8.0 * steps * LOG_ROWS_PER_STEP * N
    guard_size(need, f"a {m:g}-minute log with {N} subcarriers ({steps:.3g} steps)", limit=limit)
