"""The fitting options of one :func:`selfcal.toa.solve_toa` call, typed and named once.

:func:`~selfcal.toa.solve_toa` validates its keyword arguments and builds one frozen
:class:`ToaOptions`; every layer below it (the model choice
:func:`selfcal.toa.verdict.select.choose`, the per-model fit :func:`selfcal.toa.fit.finish`)
receives that object and reads each option by name, so an option such as ``noise`` is
followed from the CLI (``--noise``) to the outlier rule and the trust test by its attribute.
A variant is ``dataclasses.replace(opts, method="nls")``, never a copied dict. The model
(``dim``, ``offsets``) and the start (``init``) are not options: the model choice varies
them, so they travel as arguments of their own.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ToaOptions", "scores_only", "verdicts_enabled"]


@dataclass(frozen=True)
class ToaOptions:
    """How one TOA model is fitted: :func:`selfcal.toa.solve_toa`'s options, validated.

    Each field is the keyword argument of :func:`~selfcal.toa.solve_toa` of the same name,
    documented and given its default there (only there: the fields have none), after
    validation: ``rng`` a Generator, ``covariance`` as
    :func:`selfcal.toa.engine.covariance.normalize_covariance` returns it, ``speed``,
    ``f_scale`` and ``noise`` checked positive (the matrix's units).

    Examples
    --------
    >>> import dataclasses
    >>> opts = ToaOptions(speed=None, loss="auto", method="auto", rng=np.random.default_rng(0), f_scale=None,
    ...                   max_nfev=None, covariance=True, sweep=True, noise=0.01, budget=None)
    >>> dataclasses.replace(opts, method="nls").method, opts.noise
    ('nls', 0.01)
    """

    speed: float | None
    loss: str
    method: str
    rng: np.random.Generator = dataclasses.field(compare=False)
    f_scale: float | None
    max_nfev: int | None
    covariance: Any = dataclasses.field(compare=False)
    sweep: bool
    noise: float | None
    budget: int | None


# False inside a scores_only() block (None outside it is never stored: the default is True)
_VERDICTS: contextvars.ContextVar[bool] = contextvars.ContextVar("toa_verdicts", default=True)


@contextlib.contextmanager
def scores_only() -> Iterator[None]:
    """Within the block, fits are judged by steps 6-7 only: the trust test and the packaged result.

    For the candidates of a model choice (:func:`selfcal.toa.verdict.select.choose_offsets`),
    whose fits serve as starts and scores (their fit, outliers and trust test, which the
    choice reads) and are never returned: the determinacy and uniqueness tests and the outlier
    rule's breakdown and power notes, which only set a returned result's verdict, are not
    run. The fits themselves are the same as outside the block.

    Examples
    --------
    >>> with scores_only():
    ...     verdicts_enabled()
    False
    """
    token = _VERDICTS.set(False)
    try:
        yield
    finally:
        _VERDICTS.reset(token)


def verdicts_enabled() -> bool:
    """False inside a :func:`scores_only` block: the final fit's verdicts beyond the trust test are skipped.

    Examples
    --------
    >>> verdicts_enabled()
    True
    """
    return _VERDICTS.get()
