"""TOA self-calibration in a dozen lines: simulate, calibrate blind, compare with the truth.

Run: .venv/bin/python examples/toa_quickstart.py
"""

import numpy as np

import selfcal
from selfcal.metrics import aligned_rmse
from selfcal.toa import toa_crlb, toa_model

rng = np.random.default_rng(0)
mics = rng.uniform([0, 0, 0], [6, 5, 2.5], (8, 3))  # 8 microphones in a 6 x 5 x 2.5 m room
claps = rng.uniform([0, 0, 0], [6, 5, 2.5], (20, 3))  # 20 hand claps at unknown places
c, sigma = 343.0, 0.01  # speed of sound (m/s), range noise (m)
delays = rng.uniform(0, 0.01, 8)  # unknown internal delay of each microphone (s)
onsets = rng.uniform(0, 1, 20)  # unknown emission time of each clap (s)
times = toa_model(mics, claps, c * delays, c * onsets) / c + rng.normal(0, sigma / c, (8, 20))

res = selfcal.solve_toa(times, dim=3, offsets="both", speed=c, rng=0)
err = aligned_rmse(res.receivers, mics, res.sources, claps)
bound = toa_crlb(mics, claps, sigma, offsets="both")
print(f"method {res.method}, converged {res.converged}, residual RMS {res.residual_rms * 1e6:.1f} us")
print(f"microphone RMSE {err.rmse_receivers * 100:.2f} cm (CRLB {bound.rmse_receivers * 100:.2f} cm)")
print(f"clap RMSE       {err.rmse_sources * 100:.2f} cm (CRLB {bound.rmse_sources * 100:.2f} cm)")
print(f"predicted std of mic 0: {np.sqrt(np.trace(res.receiver_cov[0])) * 100:.2f} cm")
