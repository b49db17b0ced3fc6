"""Success table of the 004 TOA calibration on few-unit 3-D conference scenes (issues 3, 7).

Exact TOAs ``t_ij = |r_i - s_j| / c + tau_j + delta_i`` of ``conference_scene`` layouts
(``stem``: microphones on stems above desk loudspeakers; ``tiered``: amphitheatre rows) plus
optional Gaussian timing noise (``--jitter``), solved by :func:`selfcal.toa.solve_toa` (``offsets="both"``) for
scene seeds 0, 1, 2 and solver seeds 0, 1000. A run succeeds when the largest position
error after the rigid alignment (with reflection) is below 1 cm (with coplanar loudspeakers,
the microphones first put on one side of their plane, the pipeline's convention); a failure is "ambiguous"
when the solver's fit is as good as the refinement started at the truth (the TOAs do not
identify the geometry: 8 units in 3-D leave 7 degrees of freedom) and "wrong-basin" otherwise.

Usage::

    PYTHONPATH=src python benchmarks/stem_basin_table.py [--units 8 10 12] [--noise-arg]

``--noise-arg`` passes the timing-noise std (``--jitter``, at least 1 us) to ``solve_toa(noise=...)`` (residual test and deep
search); without it the solver runs as a caller that does not know the noise level.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from selfcal.acoustics.pipeline import one_side_of_plane, planarity
from selfcal.errors import DegenerateGeometryError
from selfcal.geometry import align
from selfcal.scenarios.conference import conference_scene
from selfcal.toa import solve_toa

C = 343.0
NOISE = 1e-6
ROOM = (12.0, 12.0, 3.0)


def scene_times(units: int, layout: str, seed: int, jitter: float = 0.0,
                room: tuple[float, float, float] = ROOM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(receivers (I, 3) m, senders (J, 3) m, TOA matrix (I, J) s with ``jitter`` s noise) of one scene."""
    sc = conference_scene(units, room, layout=layout, rng=seed)
    d = np.linalg.norm(sc.receivers[:, None] - sc.senders[None], axis=-1)
    T = d / C + sc.sender_onsets[None] + sc.receiver_delays[:, None]
    return sc.receivers, sc.senders, T + np.random.default_rng(seed + 1000).normal(0.0, 1.0, T.shape) * jitter


def run(units: int, layout: str, scene: int, solver_seed: int, noise_arg: bool,
        jitter: float = 0.0, room: tuple[float, float, float] = ROOM) -> tuple[float, str, str]:
    """Largest aligned position error (m), the solver's method label and the verdict.

    Verdict: ``ok`` (max error < 1 cm), ``ambiguous`` (error >= 1 cm but the fit is at least as
    good as the refinement started at the truth: the data do not identify the geometry) or
    ``wrong-basin`` (a worse fit than the truth's: a failure of the solver).
    """
    sc = conference_scene(units, room, layout=layout, rng=scene)
    r, s, T = scene_times(units, layout, scene, jitter, room)
    kw = {"noise": max(jitter, 1e-6)} if noise_arg else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = solve_toa(T, dim=3, offsets="both", speed=C, method="nls", covariance=False,
                        init=(sc.receivers, sc.senders, sc.receiver_delays, sc.sender_onsets))
        try:
            res = solve_toa(T, dim=3, offsets="both", speed=C, rng=solver_seed, **kw)
        except DegenerateGeometryError as exc:
            return float("inf"), f"error: {exc.kind}", "wrong-basin"
    est_r, est_s = np.asarray(res.receivers), np.asarray(res.sources)
    if planarity(est_s).near_planar:
        # coplanar loudspeakers (stem: flat desks): each microphone's side of their plane is not
        # observable; the pipeline's convention puts all microphones on one side
        est_r = one_side_of_plane(est_r, np.zeros((len(est_r), 3, 3)), est_s)[0]
    est, true = np.vstack([est_r, est_s]), np.vstack([r, s])
    err = float(np.abs(align(est, true, reflection=True).apply(est) - true).max())
    if err < 0.01:
        return err, res.method, "ok"
    tol = 1e-12 + 1e-6 * ref.residual_rms  # s
    return err, res.method, "ambiguous" if res.residual_rms <= ref.residual_rms + tol else "wrong-basin"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, nargs="+", default=[8, 10, 12])
    ap.add_argument("--layouts", nargs="+", default=["stem", "tiered"])
    ap.add_argument("--noise-arg", action="store_true", help="pass noise=1e-6 to solve_toa")
    ap.add_argument("--jitter", type=float, default=0.0, help="timing noise added to the exact TOAs, s")
    ap.add_argument("-v", "--verbose", action="store_true")
    ap.add_argument("--room", default="12x12x3", help="room L x W x H, m")
    a = ap.parse_args()
    room = tuple(float(v) for v in a.room.split("x"))
    print(f"room {a.room} m, timing noise added {a.jitter:g} s, noise passed to solve_toa: {a.noise_arg}")
    print(f"{'layout':8s} {'units':>5s}  ok  ambiguous  wrong-basin   (3 scenes x solver seeds 0/1000; "
          "ok: max error < 1 cm)   time")
    for layout in a.layouts:
        for units in a.units:
            count = {"ok": 0, "ambiguous": 0, "wrong-basin": 0}
            t0 = time.perf_counter()
            for scene in (0, 1, 2):
                for seed in (0, 1000):
                    err, method, verdict = run(units, layout, scene, seed, a.noise_arg, a.jitter, room)
                    count[verdict] += 1
                    if a.verbose:
                        print(f"   scene {scene} seed {seed:4d}: max err {err * 100:8.3f} cm  {verdict:11s} {method}")
            print(f"{layout:8s} {units:5d}  {count['ok']}/6 {count['ambiguous']:6d}/6 {count['wrong-basin']:8d}/6"
                  f"      {time.perf_counter() - t0:6.1f} s", flush=True)

if __name__ == "__main__":
    main()
