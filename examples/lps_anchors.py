"""Blind calibration of the 6 UWB anchors of the Lund LPS flights from ranges alone.

Usage:  python examples/lps_anchors.py ../shared/data/lps/data5.mat

The ranges are the only input; the motion-capture positions are used at the end to score
the result after a rigid alignment (003 eq. 18a), beside the data set authors' own estimate.
"""

from __future__ import annotations

import sys

import numpy as np

from selfcal import solve_toa
from selfcal.datasets import load_lps
from selfcal.metrics import aligned_rmse
from selfcal.toa.recipes.preprocess import (
    fit_offsets_profile_common,
    observed_columns,
    reject_range_outliers,
)

path = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/lps/data5.mat"
flight = load_lps(path)
ranges = flight.ranges  # (6 anchors, N tag positions), NaN = missing

# 1) plain TOA (003): a few raw ranges are slightly negative (biased UWB), clip them
plain = solve_toa(np.maximum(ranges, 0.0), dim=3, covariance=False, rng=0)

# 2) per-anchor ranging bias + Huber loss, started from the plain solution
biased = solve_toa(ranges, dim=3, offsets="receivers", loss="huber", method="nls",
                   init=(plain.receivers, plain.sources, np.zeros(6), None), covariance=False)

# 3) recommended: reject multipath spikes in time (the tag flies a smooth path, so each
#    anchor's range series is smooth), then per-anchor biases whose common part minimises a
#    robust (trimmed) residual scale; ranges only, no hand-picked bias
clean = reject_range_outliers(ranges)
keep = observed_columns(clean.ranges, 3)  # tag positions left with >= 4 ranges
Y = clean.ranges[:, keep]
start = solve_toa(np.maximum(Y, 0.0), dim=3, covariance=False, rng=0)
profiled = fit_offsets_profile_common(Y, start.receivers, start.sources)
print(f"rejected {clean.n_rejected} spikes; common bias {profiled.common:.3f} m")

for name, res in (("offsets=none", plain), ("offsets=receivers+huber", biased),
                  ("clean + profiled biases", profiled)):
    err = aligned_rmse(res.receivers, flight.anchors_true)
    print(f"{flight.name} {name:24s} anchor RMSE {err.rmse_receivers:.3f} m")
print(f"{flight.name} {'authors (ropt)':24s} anchor RMSE "
      f"{aligned_rmse(flight.authors_anchors, flight.anchors_true).rmse_receivers:.3f} m")
print("estimated anchor biases (m):", np.round(profiled.receiver_offsets, 3))
