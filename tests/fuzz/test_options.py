"""Every float option of every command has a stated range (selfcal.commands._options).

The click tree is walked, so a new command's float option is covered (and a plain
``type=float`` is caught) without editing this file. Values that are never a measurement
(NaN, +-inf, beyond double precision, not a strict decimal) and values just outside each
option's own range are refused while the command line is parsed: exit 2, one line naming
the option, nothing written.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from selfcal.cli import main
from selfcal.commands._options import Quantity
from selfcal.slac.ranging import RangeModelConfig

from .test_cli import check_contract, snapshot


def _commands(group: click.Group, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], click.Command]]:
    out = []
    for name, cmd in sorted(group.commands.items()):
        if isinstance(cmd, click.Group):
            out += _commands(cmd, (*prefix, name))
        else:
            out.append(((*prefix, name), cmd))
    return out


COMMANDS = _commands(main)
FLOAT_OPTIONS = [(path, p) for path, cmd in COMMANDS for p in cmd.params
                 if isinstance(p, click.Option) and isinstance(p.type, Quantity)]


def test_no_float_option_without_a_range() -> None:
    """A plain ``type=float`` would take NaN / inf / 1e308 unchecked: every float option is a Quantity."""
    plain = [f"{' '.join(path)} {p.opts[0]}" for path, cmd in COMMANDS for p in cmd.params
             if isinstance(p.type, click.types.FloatParamType) or isinstance(p.type, click.FloatRange)]
    assert plain == []
    assert len(FLOAT_OPTIONS) >= 20  # toa, farfield, pipeline, conference, demo, slac, aoa, units, jitter


def _outside(q: Quantity) -> list[str]:
    """Values just outside each bound of ``q`` plus the never-valid ones."""
    vals = ["nan", "NaN", "inf", "-inf", "+Infinity", "1e400", "-1e400", "1_0", "0x10", "", "x", "1,5"]
    for b, side in ((q.gt, -1), (q.ge, -1), (q.lt, +1), (q.le, +1)):
        if b is None:
            continue
        if side < 0:
            vals.append(repr(b if q.gt is not None and b == q.gt else b - max(1.0, abs(b)) * 1e-3))
        else:
            vals.append(repr(b if q.lt is not None and b == q.lt else b + max(1.0, abs(b)) * 1e-3))
    if q.ge is None and q.gt is None:
        vals.append("-1e308")
    if q.le is None and q.lt is None:
        vals.append("1e309")
    return vals


CASES = [(path, p.opts[0], v) for path, p in FLOAT_OPTIONS for v in _outside(p.type)]  # type: ignore[arg-type]


@pytest.mark.parametrize("path,opt,value", CASES, ids=[f"{' '.join(c[0])}{c[1]}={c[2]}" for c in CASES])
def test_float_options_refuse_values_outside_their_range(tmp_path: Path, monkeypatch, path: tuple[str, ...],  # type: ignore[no-untyped-def]
                                                         opt: str, value: str) -> None:
    # only the bad option: click converts it before it looks for the (missing) required
    # arguments, so nothing runs; in an empty folder, so nothing could be written unseen
    monkeypatch.chdir(tmp_path)
    args = [*path, f"{opt}={value}"]
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, args, catch_exceptions=True)
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and opt in err, err


@pytest.mark.parametrize("path,opt", [(c[0], c[1]) for c in {(p, o.opts[0]): 0 for p, o in FLOAT_OPTIONS}])
def test_float_options_accept_their_bounds(path: tuple[str, ...], opt: str) -> None:
    """The closed bounds themselves (and a value inside) convert: the ranges refuse nothing legitimate."""
    q = next(p.type for pa, p in FLOAT_OPTIONS if pa == path and p.opts[0] == opt)
    assert isinstance(q, Quantity)
    inside = [b for b in (q.ge, q.le) if b is not None]
    lo = q.gt if q.gt is not None else q.ge
    hi = q.lt if q.lt is not None else q.le
    if lo is not None and hi is not None:
        inside.append(0.5 * (lo + hi))
    elif lo is not None:
        inside.append(lo + 1.0)
    elif hi is not None:
        inside.append(hi - 1.0)
    for v in inside:
        assert q.convert(repr(v), None, None) == v
        assert q.convert(f" {v!r} ", None, None) == v


@pytest.mark.parametrize("args,match", [
    (["simulate", "conference", "--room", "nanx3x3", "--out", "{d}/rec"], "L x W x H"),
    (["simulate", "conference", "--room", "infx3x3", "--out", "{d}/rec"], "L x W x H"),
    (["simulate", "conference", "--rt60", "400", "--out", "{d}/rec"], "milliseconds"),
    (["pipeline", "{d}", "--speed-of-sound", "1e6", "-o", "{d}/r.json"], "physical bound"),
    (["calibrate", "toa", "{d}/m.csv", "--speed", "3e9", "-o", "{d}/r.json"], "light"),
    (["demo", "--snr", "1e308", "--out", "{d}/demo"], "--snr"),
    (["pipeline", "{d}", "--humidity", "101", "-o", "{d}/r.json"], "humidity"),
])
def test_named_physical_ranges(tmp_path: Path, args: list[str], match: str) -> None:
    before = snapshot(tmp_path)
    res = CliRunner().invoke(main, [a.format(d=tmp_path) for a in args], catch_exceptions=True)
    code, _, err = check_contract(res, before, snapshot(tmp_path))
    assert code == 2 and match in err, err


# ----------------------------------------------------------------------------- RangeModelConfig

@pytest.mark.parametrize("field,value", [
    ("noise_rounds", -1), ("noise_rounds", 1.5), ("noise_rounds", True), ("noise_rounds", "8"),
    ("noise_rounds", math.nan), ("noise_tol", 0.0), ("noise_tol", -0.1), ("noise_tol", math.nan),
    ("noise_tol", math.inf), ("noise_tol", "0.05"), ("noise_tol", None), ("max_iter", 0), ("max_iter", 2.0),
    ("noise_window", 0), ("gate_quantile", "x"), ("gate_quantile", 0.5), ("odo_turn", "x"), ("huber", True),
    ("estimate_noise", "yes"), ("heading_noise_grid", (1.0, -0.3)), ("heading_noise_grid", (1.0, math.nan)),
    ("heading_noise_grid", ("a",)), ("heading_noise_grid", ((1.0, 2.0),)),
])
def test_range_model_config_refuses_by_name(field: str, value: object) -> None:
    from selfcal.errors import InputError

    with pytest.raises(InputError, match=f"RangeModelConfig.{field}"):
        RangeModelConfig(**{field: value})  # type: ignore[arg-type]


@pytest.mark.parametrize("field,value", [("noise_rounds", 0), ("noise_rounds", 20), ("noise_tol", 1e-6),
                                         ("noise_tol", 1.0), ("heading_noise_grid", ()), ("max_iter", 1)])
def test_range_model_config_accepts_the_edges(field: str, value: object) -> None:
    assert getattr(RangeModelConfig(**{field: value}), field) == value  # type: ignore[arg-type]


SEED_OPTIONS = [(path, p) for path, cmd in COMMANDS for p in cmd.params if p.name == "seed"]


def test_every_seed_option_is_a_non_negative_int64() -> None:
    from selfcal.commands._options import SEED

    assert len(SEED_OPTIONS) >= 10
    assert all(p.type is SEED for _, p in SEED_OPTIONS), [" ".join(path) for path, p in SEED_OPTIONS
                                                          if p.type is not SEED]


@pytest.mark.parametrize("path", [path for path, _ in SEED_OPTIONS], ids=[" ".join(p) for p, _ in SEED_OPTIONS])
@pytest.mark.parametrize("value", ["-1", str(2**63), "99999999999999999999", "1.5", "nan", ""])
def test_seed_refused_while_parsing(tmp_path: Path, monkeypatch, path: tuple[str, ...], value: str) -> None:  # type: ignore[no-untyped-def]
    """A negative seed was an internal error of numpy's SeedSequence (reproduce aoa)."""
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, [*path, f"--seed={value}"], catch_exceptions=True)
    code, _, err = check_contract(res, {}, snapshot(tmp_path))
    assert code == 2 and "--seed" in err, err


# ----------------------------------------------------------------------------- SlacConfig

@pytest.mark.parametrize("field,value", [
    ("T", 0.0), ("T", -0.1), ("T", math.nan), ("T", "0.1"), ("bandwidth", math.inf), ("gtol", 0), ("bias_std", 0.0),
    ("g_rel_std", -1.0), ("sigma_v", -1e-3), ("sigma_omega", math.nan), ("g_order_decay", -1), ("max_iter", 0),
    ("max_iter", 2.5), ("smoother_lag", -1), ("smoother_lag", True), ("anchor_biases", 1), ("first_estimates", "no"),
    ("covariance", "exact"), ("optimizer", "lbfgs"),
])
def test_slac_config_refuses_by_name(field: str, value: object) -> None:
    from selfcal.errors import InputError
    from selfcal.slac.filter import SlacConfig

    with pytest.raises(InputError, match=f"SlacConfig.{field}"):
        SlacConfig(**{field: value})  # type: ignore[arg-type]


def test_slac_config_edges_accepted() -> None:
    from selfcal.slac.filter import SlacConfig

    c = SlacConfig(sigma_v=0.0, sigma_omega=0.0, g_order_decay=0.0, smoother_lag=0, max_iter=1, covariance="fd",
                   optimizer="bfgs")
    assert c.sigma_v == 0.0 and c.max_iter == 1
