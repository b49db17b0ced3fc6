"""Specification of the result convention (``selfcal._result``) and the diagnostics registry."""

from __future__ import annotations

import ast
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from selfcal._result import Result, jsonable
from selfcal.errors import Degeneracy, DegenerateGeometryError, Flag, Status

SRC = Path(__file__).resolve().parents[1] / "src" / "selfcal"


# ----------------------------------------------------------------------------- jsonable
_leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
    st.floats(allow_nan=True, allow_infinity=True).map(np.float64),
    st.integers(-1000, 1000).map(np.int32),
    st.sampled_from(list(Degeneracy) + list(Status) + list(Flag)),
    arrays(np.float64, st.integers(0, 4), elements=st.floats(allow_nan=True, allow_infinity=True)),
    arrays(np.complex128, st.integers(0, 3), elements=st.complex_numbers(allow_nan=True, allow_infinity=True)),
)
_trees = st.recursive(
    _leaves,
    lambda kids: st.one_of(
        st.lists(kids, max_size=3),
        st.tuples(kids, kids),
        st.dictionaries(st.one_of(st.text(max_size=3), st.integers(0, 9)), kids, max_size=3),
    ),
    max_leaves=12,
)


@settings(max_examples=200, deadline=None)
@given(_trees)
def test_jsonable_is_strict_json_and_keeps_finite_values(tree: object) -> None:
    out = jsonable(tree)
    text = json.dumps(out, allow_nan=False)  # strict JSON: raises on NaN / inf / unknown types
    assert json.loads(text) == out  # nothing that does not survive a round trip

    def finite_leaves_agree(a: object, b: object) -> None:
        if isinstance(a, np.ndarray) and not np.iscomplexobj(a):
            a = a.tolist()
        if isinstance(a, (list, tuple)):
            assert isinstance(b, list) and len(a) == len(b)
            for x, y in zip(a, b, strict=True):
                finite_leaves_agree(x, y)
        elif isinstance(a, (float, np.floating)) and not isinstance(a, bool):
            assert (b is None) if not math.isfinite(float(a)) else b == float(a)

    finite_leaves_agree(tree, out)


def test_jsonable_nested_dataclass_and_enum() -> None:
    @dataclasses.dataclass(frozen=True)
    class Inner:
        x: np.ndarray
        kind: Degeneracy

    out = jsonable({"inner": Inner(np.array([[1.0, np.inf]]), Degeneracy.CONE), Status.SUCCESS: 1})
    assert out == {"inner": {"x": [[1.0, None]], "kind": "cone"}, "0": 1}
    masked = np.ma.masked_array([1, 2, 3], mask=[False, True, False])
    assert jsonable({"m": masked}) == {"m": [1.0, None, 3.0]}


# ----------------------------------------------------------------------------- Result base
@dataclasses.dataclass(frozen=True, repr=False)
class _Toy(Result):
    positions: np.ndarray
    converged: bool
    method: str = "toy"
    residual_rms: float = 0.5
    degeneracy: str | None = None
    fit: object | None = None
    notes: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class _Fit:
    chi2: float
    dof: int
    p_value: float
    passed: bool


@pytest.mark.parametrize(
    ("kwargs", "status"),
    [
        ({}, Status.SUCCESS),
        ({"converged": False}, Status.NOT_CONVERGED),
        ({"fit": _Fit(500.0, 10, 1e-9, False)}, Status.FAILED_TEST),
        ({"fit": _Fit(9.0, 10, 0.5, True)}, Status.SUCCESS),
        ({"degeneracy": "cone", "converged": False}, Status.DEGENERATE),  # degeneracy first
    ],
)
def test_status_follows_the_conventional_fields(kwargs: dict, status: Status) -> None:
    r = _Toy(**{"positions": np.zeros((3, 3)), "converged": True, **kwargs})
    assert r.status == status
    assert r.success == (status == Status.SUCCESS)
    assert isinstance(r.message, str) and r.message and "\n" not in r.message
    d = r.to_dict()
    assert (d["status"], d["success"], d["message"]) == (int(status), r.success, r.message)


def test_repr_and_summary_never_dump_arrays() -> None:
    big = np.arange(30000.0).reshape(10000, 3)
    r = _Toy(big, True, notes={"a": big})
    text = repr(r)
    assert len(text.splitlines()) <= 6 and len(text) < 600
    assert "29999" not in text and "(10000, 3)" in text
    s = r.summary()
    for f in dataclasses.fields(r):
        assert f.name in s
    assert "29999" not in s and "status" in s and "message" in s


def test_to_dict_is_json_safe_by_construction_and_a_copy() -> None:
    @dataclasses.dataclass(frozen=True, repr=False)
    class Own(Result):
        x: np.ndarray
        table: dict

        def to_dict(self) -> dict:  # returns raw arrays and the field's own dict
            return {"x": self.x, "table": self.table}

    r = Own(np.array([1.0, np.nan]), {"k": [np.float32(2.0)]})
    d = r.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["x"] == [1.0, None] and d["status"] == 0
    d["table"]["k"].append(3)  # editing the dict must not reach the frozen result
    assert r.table == {"k": [np.float32(2.0)]}
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.x = np.zeros(2)  # type: ignore[misc]


# ----------------------------------------------------------------------------- real results
def _toa_result():
    from selfcal import solve_toa

    rng = np.random.default_rng(3)
    R, S = rng.uniform(0, 4, (7, 3)), rng.uniform(0, 4, (9, 3))
    D = np.linalg.norm(R[:, None] - S[None], axis=-1) + 1e-3 * rng.standard_normal((7, 9))
    D[0, 0] = np.nan
    return solve_toa(D, dim=3, noise=1e-3, rng=0)


def _farfield_result():
    from selfcal import solve_farfield

    rng = np.random.default_rng(4)
    Z = rng.normal(size=(8, 3))
    N = rng.normal(size=(12, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    return solve_farfield(Z @ N.T + rng.normal(size=12) + 1e-4 * rng.standard_normal((8, 12)))


def _aoa_result():
    from selfcal import solve_aoa

    rng = np.random.default_rng(5)
    b = rng.uniform(-5, 5, (6, 3))
    m = np.array([0.3, -0.2, 0.1])
    U = (b - m) / np.linalg.norm(b - m, axis=1, keepdims=True)
    return solve_aoa(b, U)


def _planarity():
    from selfcal.acoustics.pipeline import planarity

    rng = np.random.default_rng(6)
    return planarity(rng.normal(size=(10, 3)) * [3, 2, 0.01])


@pytest.mark.parametrize("make", [_toa_result, _farfield_result, _aoa_result, _planarity])
def test_solver_results_follow_the_convention(make) -> None:
    r = make()
    assert isinstance(r, Result)
    assert isinstance(r.status, Status) and r.success == (r.status == 0)
    d = r.to_dict()
    json.dumps(d, allow_nan=False)
    assert {"status", "success", "message"} <= set(d)
    assert len(repr(r)) < 600 and len(repr(r).splitlines()) <= 6
    assert type(r).__name__ in r.summary()


def test_aliases_keep_old_names() -> None:
    t = _toa_result()
    assert t.noise_estimate == t.sigma and t.noise == 1e-3
    a = _aoa_result()
    assert a.pose_cov is a.covariance
    assert a.success and a.status == Status.SUCCESS  # six beacons in general position: one pose


# ----------------------------------------------------------------------------- registry
def _kind_literals() -> set[tuple[str, str]]:
    """Every string literal passed as ``kind=`` to DegenerateGeometryError in src/."""
    found = set()
    for path in SRC.rglob("*.py"):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "DegenerateGeometryError":
                for kw in node.keywords:
                    if kw.arg == "kind" and isinstance(kw.value, ast.Constant):
                        found.add((str(path.relative_to(SRC)), kw.value.value))
    return found


def test_every_raised_kind_is_registered() -> None:
    literals = _kind_literals()
    assert len(literals) >= 20  # the scan itself works (it found the raise sites)
    unknown = {(p, k) for p, k in literals if k not in {d.value for d in Degeneracy}}
    assert not unknown, f"register these kinds in selfcal.errors.Degeneracy: {sorted(unknown)}"


def test_farfield_degeneracies_are_registered() -> None:
    from selfcal.tdoa.degeneracy import DEGENERACIES

    assert set(DEGENERACIES) <= {d.value for d in Degeneracy}


def test_degenerate_error_kind_is_backwards_compatible() -> None:
    for d in Degeneracy:
        assert d.explanation and (d.explanation[0].islower() or d.explanation[0].isdigit())
        e = DegenerateGeometryError("msg", kind=d.value)
        assert e.kind is d and e.kind == d.value and str(e) == f"[{d.value}] msg"
        assert e.explanation == d.explanation
        assert DegenerateGeometryError("msg", kind=d).kind is d
    e = DegenerateGeometryError("msg", kind="not-yet-registered")
    assert e.kind == "not-yet-registered" and e.explanation == ""
