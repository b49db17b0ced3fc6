"""The result convention every solver's result follows.

A result is a frozen dataclass that inherits :class:`Result`::

    @dataclass(frozen=True, repr=False)   # repr=False keeps the short Result.__repr__
    class XxxResult(Result):
        positions: Array
        converged: bool
        ...

and gets, without further code,

* ``status`` / ``success`` / ``message`` in the style of SciPy's ``OptimizeResult``:
  ``status`` is a :class:`~selfcal.errors.Status` (an ``IntEnum``, 0 = success),
  ``success`` is ``status == Status.SUCCESS`` and ``message`` says why in one line. The
  default diagnosis reads the conventional fields ``degeneracy``, ``converged`` and
  ``fit`` (a residual test with ``passed``); a class refines it by overriding
  :meth:`Result._diagnose`, or stores ``status`` / ``success`` / ``message`` as fields of
  its own (then those are used everywhere, e.g. per-problem arrays of a batch).
* a short ``__repr__`` (arrays shown by shape, never dumped) and :meth:`Result.summary`, a
  text table of every field;
* ``to_dict()`` that is JSON-safe by construction: whatever a subclass's own ``to_dict``
  returns goes through :func:`jsonable` (arrays -> lists, NaN / inf -> None, NumPy scalars
  -> Python, enums -> values, nested results / dataclasses -> dicts) and gains the
  ``status`` / ``success`` / ``message`` keys. A subclass without its own ``to_dict``
  serialises all its fields. The returned dict is always a fresh copy, so editing it
  never mutates the (frozen) result.

A step that adds to another method's result (the user frame, a recipe) returns a
:class:`WrappedResult`: the wrapped ``result`` plus its own fields, every attribute of the
wrapped result readable directly, and the wrapped result's status.

Names: covariances end in ``_cov``, standard deviations in ``_std``; a noise level the
user gave is ``noise``, one the method estimated ``noise_estimate``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import PurePath
from typing import Any, ClassVar

import numpy as np

from .errors import Status

__all__ = ["Result", "Status", "WrappedResult", "json_float", "jsonable", "replace_fields"]


def json_float(x: float) -> float | None:
    """A float for JSON: ``float(x)``, or None for NaN / inf.

    Examples
    --------
    >>> json_float(2), json_float(float("nan"))
    (2.0, None)
    """
    x = float(x)
    return x if math.isfinite(x) else None


def jsonable(obj: Any, *, strict: bool = False) -> Any:
    """Convert ``obj`` to plain JSON-safe Python (strict JSON: no NaN, no inf).

    Parameters
    ----------
    obj : Any
        Result objects (anything with ``to_dict``), dataclasses, mappings, sequences,
        NumPy arrays and scalars, enums, paths, complex numbers.
    strict : bool
        Raise ``TypeError`` for complex numbers and for an object with none of these forms
        instead of encoding it as ``{"real", "imag"}`` or its ``str`` (the writers,
        :func:`selfcal.io.write_json`, use this: such an object in a payload is a programming
        error, not something to guess an encoding for).

    Returns
    -------
    Any
        ``None``, ``bool``, ``int``, ``float`` (finite), ``str``, ``list`` or ``dict`` with
        ``str`` keys, nested. Non-finite floats become ``None``; complex numbers become
        ``{"real": x, "imag": y}``; masked array entries ``None``; enums their value; other
        objects their ``str`` (or ``TypeError`` with ``strict``).

    Notes
    -----
    The one JSON converter of the package: ``Result.to_dict``, :func:`selfcal.io.write_json`
    and the sweep runner's CSV rows all go through it.

    Examples
    --------
    >>> import numpy as np
    >>> jsonable({"x": np.array([1.0, np.nan]), "n": np.int64(3), 2: (np.True_,)})
    {'x': [1.0, None], 'n': 3, '2': [True]}
    """

    def _conv(obj: Any) -> Any:
        if obj is None or isinstance(obj, (bool, str)):
            return obj
        if isinstance(obj, Enum):
            return _conv(obj.value)
        if isinstance(obj, int):  # after bool and Enum (IntEnum is an int)
            return int(obj)
        if isinstance(obj, float):
            return obj if math.isfinite(obj) else None
        if isinstance(obj, np.generic):
            return _conv(obj.item())
        if isinstance(obj, complex) or (isinstance(obj, np.ndarray) and np.iscomplexobj(obj)):
            if strict:  # a writer refuses to guess an encoding: results encode their complex fields
                raise TypeError("complex numbers have no strict JSON form")
            if isinstance(obj, complex):
                return {"real": _conv(obj.real), "imag": _conv(obj.imag)}
        if isinstance(obj, np.ma.MaskedArray):  # masked entries are missing: None
            return _conv(np.ma.filled(obj.astype(complex if np.iscomplexobj(obj) else float), np.nan))
        if isinstance(obj, np.ndarray):
            if np.iscomplexobj(obj):
                return {"real": _conv(obj.real.tolist()), "imag": _conv(obj.imag.tolist())}
            return _conv(obj.tolist())
        if isinstance(obj, Mapping):
            return {str(_conv(k)) if not isinstance(k, str) else k: _conv(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple, set, frozenset)):
            return [_conv(v) for v in obj]
        if isinstance(obj, PurePath):
            return str(obj)
        to_dict = getattr(obj, "to_dict", None)
        if callable(to_dict) and not isinstance(obj, type):
            return _conv(to_dict())
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            return {f.name: _conv(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        if strict:
            raise TypeError(f"an object of type {type(obj).__name__} has no JSON form")
        return str(obj)

    return _conv(obj)


def _short(value: Any, width: int = 48) -> str:
    """One-cell rendering of a field value: arrays by shape, floats to 6 digits."""
    if isinstance(value, np.ndarray):
        if value.ndim == 0:
            return _short(value.item(), width)
        return f"array{tuple(value.shape)} {value.dtype}"
    if isinstance(value, Enum):
        return str(value.value)
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.6g}"
    if isinstance(value, Result):
        return f"{type(value).__name__}({_status_text(value._state()[0])})"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        scalars = [
            f"{f.name}={_short(getattr(value, f.name))}"
            for f in dataclasses.fields(value)
            if isinstance(getattr(value, f.name), (bool, int, float, str, np.generic))
        ]
        text = f"{type(value).__name__}({', '.join(scalars)})"
        return text if len(text) <= 2 * width else text[: 2 * width - 4] + "...)"
    if isinstance(value, Mapping):
        keys = ", ".join(map(str, list(value)[:4]))
        return f"{{{keys}{', ...' if len(value) > 4 else ''}}}" if value else "{}"
    if isinstance(value, (list, tuple)) and value and not all(
        isinstance(v, (int, float, str, bool)) for v in value
    ):
        return f"{type(value).__name__} of {len(value)}"
    text = repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def _status_text(status: Any) -> str:
    """``0 SUCCESS`` for one status; ``3/4 SUCCESS`` style counts for a per-problem array."""
    if np.ndim(status) == 0:
        try:
            return f"{int(status)} {Status(int(status)).name}"
        except ValueError:
            return str(int(status))
    s = np.asarray(status).ravel()
    return f"{int(np.sum(s == 0))}/{s.size} SUCCESS"


def _wrap_to_dict(own: Callable[[Any], Mapping[str, Any]]) -> Callable[[Any], dict[str, Any]]:
    @functools.wraps(own)
    def to_dict(self: Result) -> dict[str, Any]:
        d = dict(own(self))
        status, message = self._state()
        d.setdefault("status", status)
        d.setdefault("success", self.success)
        d.setdefault("message", message)
        out: dict[str, Any] = jsonable(d)
        return out

    to_dict.__name__ = to_dict.__qualname__ = "to_dict"
    to_dict._jsonable = True  # type: ignore[attr-defined]
    return to_dict


class Result:
    """Base of every frozen result dataclass (see the module docstring for the convention).

    Subclasses are ``@dataclass(frozen=True, repr=False)``. ``_repr_fields`` names the
    fields shown by ``repr`` after the status (default: ``method`` and ``residual_rms``
    when present, then the shapes of the first array fields).
    """

    _repr_fields: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        own = cls.__dict__.get("to_dict")
        if own is not None and not getattr(own, "_jsonable", False):
            cls.to_dict = _wrap_to_dict(own)  # type: ignore[method-assign]

    # -- status ------------------------------------------------------------------------
    def _diagnose(self) -> tuple[Status, str]:
        """``(status, message)`` from the conventional fields; override to refine."""
        deg = getattr(self, "degeneracy", None)
        if deg:
            return Status.DEGENERATE, f"degenerate geometry: {getattr(deg, 'value', deg)}"
        conv = getattr(self, "converged", True)
        if conv is not None and not bool(np.all(conv)):
            n_bad = int(np.size(conv) - np.count_nonzero(conv))
            what = "the solver" if np.ndim(conv) == 0 else f"{n_bad} of {np.size(conv)} problems"
            return Status.NOT_CONVERGED, f"{what} stopped before convergence"
        fit = getattr(self, "fit", None)
        if fit is not None and not bool(getattr(fit, "passed", True)):
            chi2, dof, p = (getattr(fit, k, float("nan")) for k in ("chi2", "dof", "p_value"))
            return Status.FAILED_TEST, (
                f"residual test failed: chi2 = {chi2:.4g} on {dof} dof, p = {p:.3g}"
            )
        text = "converged" if hasattr(self, "converged") else "ok"
        if fit is not None:
            text += f"; residual test passed (p = {getattr(fit, 'p_value', float('nan')):.3g})"
        return Status.SUCCESS, text

    def _state(self) -> tuple[Any, str]:
        """``(status, message)``: the class's own fields when it has them, else the diagnosis."""
        names: set[str] = {f.name for f in dataclasses.fields(self)} if dataclasses.is_dataclass(self) else set()
        if "status" in names:
            return self.status, str(getattr(self, "message", ""))
        return self._diagnose()

    @property
    def status(self) -> Status:
        """:class:`~selfcal.errors.Status` of the result (``0`` = success)."""
        return self._diagnose()[0]

    @property
    def message(self) -> str:
        """One line saying why the result has its status."""
        return self._diagnose()[1]

    @property
    def success(self) -> bool:
        """True when the result can be trusted by its own checks (``status == 0``)."""
        return self.status == Status.SUCCESS

    # -- serialisation -------------------------------------------------------------------
    def _fields_dict(self) -> dict[str, Any]:
        """JSON-safe dict of every field plus ``status`` / ``success`` / ``message``."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    to_dict = _wrap_to_dict(_fields_dict)

    # -- display -------------------------------------------------------------------------
    def _field_items(self) -> list[tuple[str, Any]]:
        if not dataclasses.is_dataclass(self):
            return []
        return [(f.name, getattr(self, f.name)) for f in dataclasses.fields(self)]

    def __repr__(self) -> str:
        items = dict(self._field_items())
        names = list(self._repr_fields) or [k for k in ("method", "residual_rms") if k in items]
        if not self._repr_fields:
            names += [k for k, v in items.items() if isinstance(v, np.ndarray) and v.ndim >= 1][:3]
        parts = [f"{k}={_short(items[k], 32)}" for k in names if k in items]
        status, _ = self._state()
        ok = bool(np.all(np.asarray(status) == 0))
        head = f"{type(self).__name__}(success={ok}, status={_status_text(status)}"
        lines = [head + ","]
        line = "    "
        for p in parts:
            if len(line) + len(p) > 96 and line.strip():
                lines.append(line.rstrip())
                line = "    "
            line += p + ", "
        lines.append(line.rstrip(", ") + ")")
        return "\n".join(lines)

    def summary(self) -> str:
        """Text table: status, message, then one row per field (arrays by shape).

        Returns
        -------
        str
            Lines ``name  value``; no array is printed in full.
        """
        status, message = self._state()
        rows = [("status", _status_text(status)), ("message", message)]
        rows += [(k, _short(v)) for k, v in self._field_items() if k not in ("status", "message")]
        width = max(len(k) for k, _ in rows)
        title = type(self).__name__
        body = [f"  {k.ljust(width)}  {v}" for k, v in rows]
        return "\n".join([title, "-" * len(title), *body])


@dataclass(frozen=True, repr=False)
class WrappedResult(Result):
    """A result plus what a later step added to it (base of the frame and recipe results).

    Every attribute of the wrapped ``result`` is readable directly on the wrapper (the
    wrapper's own fields win); ``status`` / ``success`` / ``message`` are the wrapped
    result's, ``summary()`` shows the wrapper's fields then the wrapped result's table.
    Subclasses are ``@dataclass(frozen=True, repr=False)`` and add fields after ``result``.
    """

    result: Any
    _repr_fields: ClassVar[tuple[str, ...]] = ("result",)

    def __getattr__(self, name: str) -> Any:
        # only called when normal lookup fails; own fields (and dunders, e.g. while unpickling
        # before the fields are set) must not recurse into the wrapped result
        if name.startswith("__") or name in type(self).__dataclass_fields__:  # type: ignore[attr-defined]
            raise AttributeError(name)
        return getattr(self.result, name)

    def _diagnose(self) -> tuple[Status, str]:
        inner = self.result
        if isinstance(inner, Result):
            status, message = inner._state()
            return status, message
        return Status.SUCCESS, "ok"

    @property
    def status(self) -> Any:
        """The wrapped result's ``status``."""
        return self.result.status if isinstance(self.result, Result) else Status.SUCCESS

    @property
    def message(self) -> str:
        """The wrapped result's ``message``."""
        return str(self.result.message) if isinstance(self.result, Result) else "ok"

    @property
    def success(self) -> Any:
        """The wrapped result's ``success``."""
        return self.result.success if isinstance(self.result, Result) else True

    def summary(self) -> str:
        """The wrapper's table, then the wrapped result's :meth:`Result.summary`."""
        own = super().summary()
        inner = self.result.summary() if isinstance(self.result, Result) else repr(self.result)
        return own + "\n\n" + inner


def replace_fields(result: Any, **kw: Any) -> Any:
    """:func:`dataclasses.replace` with only the fields the result type has (others dropped).

    Parameters
    ----------
    result : a dataclass instance (a result).
    **kw : new field values; names the type lacks are ignored.

    Returns
    -------
    A copy of ``result`` with the fields it has replaced.

    Examples
    --------
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class R:
    ...     x: int
    >>> replace_fields(R(1), x=2, y=3)
    R(x=2)
    """
    names = {f.name for f in dataclasses.fields(result)}
    return dataclasses.replace(result, **{k: v for k, v in kw.items() if k in names})
