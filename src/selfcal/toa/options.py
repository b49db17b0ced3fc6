"""The fitting options of one :func:`selfcal.toa.solve_toa` call, typed and named once.

:func:`~selfcal.toa.solve_toa` validates its keyword arguments and builds one frozen
:class:`ToaOptions`; every layer below it (the model choice
:func:`selfcal.toa.verdict.select.choose`, the per-model fit :func:`selfcal.toa.fit.finish`)
receives that object and reads each option by name, so an option such as ``noise`` is
followed from the CLI (``--noise``) to the outlier rule and the trust test by its attribute.
The model (``dim``, ``offsets``) and the start (``init``) are not options: the model choice
varies them, so they travel as arguments of their own.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ToaOptions"]


@dataclass(frozen=True)
class ToaOptions:
    """How one TOA model is fitted (validated; the matrix's units).

    The fields are the keyword arguments of :func:`selfcal.toa.solve_toa` of the same names,
    documented there, with its defaults (a test ties the two), after validation.

    Attributes
    ----------
    speed : float or None
        Propagation speed, m/s (the matrix holds seconds), or None (metres).
    loss : str
        "auto", "linear", "huber", "soft_l1" or "cauchy".
    method : str
        "auto" (the search), "nls" (one start, one refinement) or "rank3".
    rng : numpy.random.Generator
        The randomised initialisers' generator.
    f_scale : float or None
        Robust-loss scale in the matrix's units (None: estimated from the data).
    max_nfev : int or None
        Iteration cap of each full refinement.
    covariance : bool or tuple
        The covariance blocks asked for, as
        :func:`selfcal.toa.engine.covariance.normalize_covariance` returns them.
    sweep : bool
        Run the search's plane moves.
    noise : float or None
        Measurement noise std in the matrix's units (enables the chi-square test).
    budget : int or None
        Maximal refinements of the search (None: :func:`selfcal.toa.search.default_budget`).

    Examples
    --------
    >>> opts = ToaOptions(noise=0.01)
    >>> opts.loss, opts.noise, opts.with_(method="nls").method
    ('auto', 0.01, 'nls')
    """

    speed: float | None = None
    loss: str = "auto"
    method: str = "auto"
    rng: np.random.Generator = dataclasses.field(default_factory=np.random.default_rng, compare=False)
    f_scale: float | None = None
    max_nfev: int | None = None
    covariance: Any = dataclasses.field(default=True, compare=False)
    sweep: bool = True
    noise: float | None = None
    budget: int | None = None

    def with_(self, **changes: Any) -> ToaOptions:
        """A copy with ``changes`` (field names only; the same generator object is shared)."""
        return dataclasses.replace(self, **changes)
