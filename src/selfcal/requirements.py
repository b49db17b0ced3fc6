"""Paper 004's requirements on a conference system's calibration: the one home of the numbers.

004 sec. 2.1 asks for every position within 10 cm (requirement 1(a)); sec. 2.2 for the
timing offsets (internal delay plus onset of a receiver-sender pair) within 58 us, 2 cm at
343 m/s. The verdict (:mod:`selfcal.acoustics.verdict`), the truth scoring
(:mod:`selfcal.acoustics.scoring`) and the figures (:mod:`selfcal.plotting.conference`) import
them from here; this module imports nothing. It sits at the top of the package, not in
:mod:`selfcal.acoustics`, so that the figures can import it without importing the acoustics
package that imports them (no import circle between subpackages).
"""

from __future__ import annotations

__all__ = ["POSITION_REQUIREMENT", "TIMING_REQUIREMENT", "SIGMAS"]

#: m, 004 sec. 2.1 requirement 1(a)
POSITION_REQUIREMENT = 0.10
#: s, 004 sec. 2.2 (2 cm at 343 m/s)
TIMING_REQUIREMENT = 58e-6
#: a requirement is met when this many standard deviations fit inside it (~95 %)
SIGMAS = 2.0
