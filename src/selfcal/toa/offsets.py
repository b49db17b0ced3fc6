"""Onset times and internal delays from a TOA matrix: the rank-d method of paper 004 (one import point).

The method lives in one file per job; this module re-exports them so that
``from selfcal.toa.offsets import ...`` keeps working:

- :mod:`.rank3_model`: the model (3.1)-(3.6), its identifiability, :class:`Rank3Result`;
- :mod:`.rank3_thesis`: :func:`rank3_iteration`, the thesis iteration (the reference);
- :mod:`.rank3`: :func:`rank3_lm` (fast variable-projection LM), :func:`fast_offsets`,
  :func:`estimate_offsets` (acceptance test and restarts);
- :mod:`.rank3_joint`: the dense joint LM (small problems, reference of the scalable one);
- :mod:`.offset_positions`: :func:`positions_from_ranges`, :func:`offset_free_positions`;
- :mod:`.offsets_init`: :func:`initialize_offsets`, :func:`initialize_offsets_candidates`,
  :func:`complete_core` (the initialiser of ``solve_toa(offsets="both")``).
"""

from __future__ import annotations

from .offset_positions import (
    _locate_with_offset,
    _range_rms,
    offset_free_positions,
    positions_from_ranges,
)
from .offsets_init import (
    _core_and_grow,
    _early_stop_ok,
    _model_rms,
    _start_from_offsets,
    _two_agree,
    complete_core,
    initialize_offsets,
    initialize_offsets_candidates,
)
from .rank3 import _DENSE_JOINT_MAX, _tail_sub, estimate_offsets, fast_offsets, rank3_lm
from .rank3_joint import _rank1_factors, _rank3_lm_joint, _tail
from .rank3_model import (
    DELAY_MAX,
    ONSET_MAX,
    THESIS_ACCEPT,
    THESIS_LAM_SWITCH,
    THESIS_SPEED,
    THESIS_TOL,
    Rank3Result,
    apply_A,
    apply_Wt,
    check_rank_identifiable,
    double_centre,
    gamma_term,
    offset_matrix,
    thesis_lambda,
    thesis_T,
    thesis_W,
)
from .rank3_thesis import rank3_iteration

__all__ = [
    "THESIS_SPEED",
    "THESIS_TOL",
    "THESIS_LAM_SWITCH",
    "THESIS_ACCEPT",
    "DELAY_MAX",
    "ONSET_MAX",
    "Rank3Result",
    "check_rank_identifiable",
    "double_centre",
    "thesis_T",
    "thesis_W",
    "apply_A",
    "apply_Wt",
    "gamma_term",
    "offset_matrix",
    "rank3_iteration",
    "rank3_lm",
    "fast_offsets",
    "estimate_offsets",
    "positions_from_ranges",
    "initialize_offsets_candidates",
    "initialize_offsets",
    "offset_free_positions",
    "complete_core",
    "thesis_lambda",
]

# private names re-exported for the tests and older callers
_PRIVATE = (_locate_with_offset, _range_rms, _core_and_grow, _early_stop_ok, _model_rms, _start_from_offsets,
            _two_agree, _DENSE_JOINT_MAX, _tail_sub, _rank1_factors, _rank3_lm_joint, _tail)
