"""The docstring Examples of the public API run as doctests (``make test`` and ``make docs``).

The documentation site shows these examples; a changed output or a broken call fails
here, not silently on the site.
"""

from __future__ import annotations

import doctest
import importlib

import numpy as np
import pytest

#: objects whose docstring Examples are part of the documentation (dotted paths)
DOCTESTED = [
    "selfcal._result.jsonable",
    "selfcal.errors.DegenerateGeometryError",
    "selfcal.robust.mad_std",
    "selfcal.robust.loss_rho",
    "selfcal.optim.lm.levenberg_marquardt",
    "selfcal.optim.lm.damping_after_success",
    "selfcal.optim.lm.irls",
    "selfcal.optim.structure.lm_step",
    "selfcal.geometry.align",
    "selfcal.geometry.wrap_angle",
    "selfcal.geometry.fit_plane",
    "selfcal.geometry.rotate_covariances",
    "selfcal.geometry.n_parameters",
    "selfcal.aoa.checks.residual_test",
    "selfcal.plotting.conference.ellipse_magnification",
    "selfcal.acoustics.plausibility.extent_reason",
    "selfcal.acoustics.plausibility.repeats_reason",
]

#: the public solvers: each must show how it is called (an Examples section)
SOLVERS: list[str] = [
    "selfcal.toa.solve.solve_toa",
    "selfcal.acoustics.pipeline.run_pipeline",
    "selfcal.tdoa.farfield.solve_farfield",
    "selfcal.aoa.pose.solve_aoa",
    "selfcal.slac.run.solve_slac",
    "selfcal.slac.ranging.solve_range_slac",
    "selfcal.toa.sparse.solve_toa_sparse",
]


def _resolve(path: str) -> object:
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("path", DOCTESTED + SOLVERS)
def test_docstring_examples_run(path: str) -> None:
    obj = _resolve(path)
    module = importlib.import_module(getattr(obj, "__module__", path.rpartition(".")[0]))
    globs = {**vars(module), "np": np}  # as ``pytest --doctest-modules`` runs them
    finder = doctest.DocTestFinder(recurse=False)
    tests = [t for t in finder.find(obj, path.rpartition(".")[2], globs=globs) if t.examples]
    assert tests, f"{path}: no doctest examples"
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for t in tests:
        runner.run(t)
    assert runner.failures == 0, f"{path}: {runner.failures} doctest example(s) failed (see output)"


@pytest.mark.parametrize("path", SOLVERS)
def test_public_solvers_have_an_examples_section(path: str) -> None:
    doc = _resolve(path).__doc__ or ""
    assert "Examples\n" in doc and ">>>" in doc.split("Examples\n", 1)[1], f"{path}: no Examples section"
