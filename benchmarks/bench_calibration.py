"""Calibration fit time: 4 mirrors x 3 walls (issue 7 target: < 2 s on this machine).

Data: one nod sweep per wall (20 URG-04LX scans, 40,920 beams in all) from the closed-form
synthetic generator with the paper's Table I errors and the URG noise model. Reports the
full ``calibrate`` time (plane fits + 4 bounded least-squares fits + uncertainties) and, as
ratios measured in the same run, against two baselines: one evaluation of one mirror's
residual function (the unit of work of the optimiser) and the same calibration with the
paper's eqs 4-8 as the point model, and the single-round fit (no beam-map re-trace).
Since issue 12 the fit is robust (MSAC planes, noise-model gates) and ends with one joint
fit of planes and mirrors (full covariance) plus the ambiguous-beam trace; the last line
times the same calibration in a cluttered scene (``design/scenes/calib-box.toml``, a box
against the wall and the floor in view).
Run: ``.venv/bin/python benchmarks/bench_calibration.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from nodlidar.calibration.fit import CalibrationConfig, _MirrorProblem, calibrate, fit_planes
from nodlidar.calibration.synthetic import synthetic_captures
from nodlidar.paper import TABLE_I_PERTURBATIONS
from nodlidar.solver import solve
from nodlidar.spec import load_design

ROOT = Path(__file__).resolve().parents[1]


def best_of(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    design = solve(load_design(ROOT / "design" / "urg04lx-paper.toml"))
    caps = synthetic_captures(design, dict(TABLE_I_PERTURBATIONS), seed=0)
    cfg = CalibrationConfig()
    t_fit = best_of(lambda: calibrate(design, caps), 5)
    res = calibrate(design, caps)
    nfev = sum(m.nfev for m in res.mirrors.values())

    # one residual evaluation of L1 over all its points (what least_squares calls)
    fits = fit_planes(design, caps, cfg)
    sol = design.mirror("L1")
    parts = [(c, f.plane) for c, f in zip(caps, fits)]
    sel = [np.isin(c.steps, sol.steps) & np.isfinite(c.ranges_m) for c, _ in parts]
    steps = np.concatenate([c.steps[s] for (c, _), s in zip(parts, sel)])
    ranges = np.concatenate([c.ranges_m[s] for (c, _), s in zip(parts, sel)])
    nod = np.concatenate([c.nod_rad[s] for (c, _), s in zip(parts, sel)])
    normals = np.concatenate([np.broadcast_to(p.normal, (s.sum(), 3)) for (_, p), s in zip(parts, sel)])
    offsets = np.concatenate([np.full(s.sum(), p.offset_m) for (_, p), s in zip(parts, sel)])
    prob = _MirrorProblem(design, "L1", steps, ranges, nod, normals, offsets, "exact")
    x = TABLE_I_PERTURBATIONS["L1"].as_array()
    t_eval = best_of(lambda: [prob.residuals(x) for _ in range(100)], 5) / 100

    t_paper = best_of(lambda: calibrate(design, caps, model="paper",
                                        config=CalibrationConfig(min_points=10)), 3)
    print(f"data: 3 walls, {sum(len(c) for c in caps)} beams, {steps.size} L1 points")
    print(f"calibrate (exact model, 4 mirrors x 3 walls): {t_fit * 1e3:8.1f} ms "
          f"({'<' if t_fit < 2 else '>='} 2 s target), {res.rounds} rounds (beam map re-traced), "
          f"{nfev} residual evaluations in the last round (nfev; finite-difference Jacobians "
          "not counted)")
    t_one = best_of(lambda: calibrate(design, caps, config=CalibrationConfig(rounds=1)), 5)
    print(f"calibrate, one round (the design's beam map only):  {t_one * 1e3:8.1f} ms")
    print(f"one residual evaluation (L1, {steps.size} points): {t_eval * 1e6:8.1f} us")
    print(f"calibrate with the paper's eqs 4-8:                {t_paper * 1e3:8.1f} ms")
    print(f"ratio full fit / one residual evaluation: {t_fit / t_eval:8.1f}")
    print(f"ratio exact-model fit / paper-model fit:  {t_fit / t_paper:8.2f}")
    print(f"ratio full fit / one-round fit:           {t_fit / t_one:8.2f}")

    from nodlidar.calibration.synthetic import scene_captures
    from nodlidar.sim.scene import load_scene

    box = scene_captures(design, load_scene(ROOT / "design" / "scenes" / "calib-box.toml"),
                         np.radians([-25.0, 0.0, 25.0]), dict(TABLE_I_PERTURBATIONS))
    t_box = best_of(lambda: calibrate(design, box), 3)
    print(f"calibrate in a cluttered scene (calib-box, {sum(len(c) for c in box)} beams): "
          f"{t_box * 1e3:8.1f} ms")


if __name__ == "__main__":
    main()
