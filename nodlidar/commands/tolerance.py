"""``nodlidar tolerance DESIGN``: Monte Carlo of mounting errors and the sensitivity table.

Mounting-error distributions come from the design file's ``[tolerance]`` table (defaults if
absent). Prints, per mirror and range, percentiles of the largest bearing error, the
projected-range error and the elevation over the sampled builds, then d(bearing)/d(parameter)
at D. Results depend only on the seed (and chunk size), not on the number of workers.
"""

from __future__ import annotations

import argparse
import json
import sys

from .._light import MAX_SAMPLES  # (not analysis.tolerance: --help imports no numpy)
from ._args import bounded_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("tolerance", help="Monte Carlo tolerance analysis and sensitivities",
                       description=__doc__)
    p.add_argument("design", help="design TOML file")
    p.add_argument("--samples", type=bounded_int(1, MAX_SAMPLES),
                   help=f"number of sampled builds (1 .. {MAX_SAMPLES})")
    p.add_argument("--seed", type=bounded_int(0, 2**63 - 1), help="random seed (>= 0)")
    p.add_argument("--workers", type=bounded_int(0, 256),
                   help="0: in process; N: local Dask cluster of N workers (<= 256)")
    p.add_argument("--scheduler", metavar="ADDR",
                   help="an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")
    p.set_defaults(func=run)


def check_monte_carlo_options(args: argparse.Namespace) -> None:
    """``--samples``/``--workers``/``--scheduler`` (shared with ``nodlidar report``), checked
    before any work, in the options' own names."""
    from ..errors import ParameterError

    if args.samples is not None and not 1 <= args.samples <= MAX_SAMPLES:
        raise ParameterError("--samples", args.samples, f"an integer in 1 .. {MAX_SAMPLES}")
    if args.workers is not None and args.workers < 0:
        raise ParameterError("--workers", args.workers, "an integer >= 0")
    if args.scheduler is not None and args.workers is not None:  # would be ignored
        raise ParameterError("--workers", args.workers, "not with --scheduler (its workers "
                                                        "run the chunks)")
    if args.scheduler is not None:
        from ..analysis.tolerance import check_scheduler

        try:  # before any work (and the progress bar): one line within a few seconds
            check_scheduler(args.scheduler)
        except ParameterError as exc:
            raise ParameterError("--scheduler", exc.value, exc.allowed) from None


def run(args: argparse.Namespace) -> int:
    from ..analysis.tolerance import (
        DASK_MIN_SAMPLES,
        monte_carlo,
        runner_for,
        sensitivities,
        tolerance_spec,
    )
    from ..errors import ParameterError
    from ..solver import solve
    from ..spec import load_design
    from .report import tqdm_progress

    check_monte_carlo_options(args)
    design = solve(load_design(args.design))
    n_samples = args.samples if args.samples is not None else tolerance_spec(design.spec).samples
    runner = runner_for(n_samples, workers=args.workers, scheduler=args.scheduler)
    progress, close = tqdm_progress("Monte Carlo (in process)" if runner == "in-process"
                                    else "Monte Carlo (Dask)")
    try:
        # only the percentile table is printed: no row per sample is kept (memory flat)
        res = monte_carlo(design, samples=args.samples, seed=args.seed, workers=args.workers,
                          scheduler=args.scheduler, progress=progress, keep_samples=False)
    except ParameterError as exc:
        if exc.field != "scheduler":
            raise
        raise ParameterError("--scheduler", exc.value, exc.allowed) from None
    except KeyboardInterrupt:
        # the CLI prints one 'interrupted' line; Dask's late shutdown messages (at exit,
        # after the cluster is closed) would only bury it
        import logging

        logging.disable(logging.CRITICAL)
        raise
    finally:
        close()
    from ._output import raise_if_interrupted

    raise_if_interrupted()   # a Ctrl-C Dask swallowed after the last chunk: no results
    sens = sensitivities(design)
    if args.json:
        json.dump({"name": design.spec.name, "n_samples": res.n_samples, "seed": res.seed,
                   "tolerance": res.tolerance.to_dict(), "percentiles": res.table(),
                   "sensitivities": sens.table(),
                   "runner": res.runner, "wall_s": res.wall_s,
                   "samples_per_s": res.n_samples / res.wall_s if res.wall_s > 0 else None,
                   "dask_startup_s": res.startup_s, "dask_min_samples": DASK_MIN_SAMPLES},
                  sys.stdout, indent=2)
        print()
        return 0
    qs = res.tolerance.percentiles
    print(f"{design.spec.name}: {res.n_samples} sampled builds, seed {res.seed}, "
          f"{res.tolerance.distribution}")
    head = (f"{'mirror':6} {'R m':>5} " + " ".join(f"{'brg p' + format(q, 'g'):>9}" for q in qs)
            + " " + " ".join(f"{'rng p' + format(q, 'g'):>9}" for q in qs)
            + " " + " ".join(f"{'elv p' + format(q, 'g'):>9}" for q in qs) + "  edge-miss")
    print("bearing [deg], projected range [mm], elevation [deg]")
    print(head)
    for r in res.table():
        print(f"{r['mirror']:6} {r['range_m']:5.2g} "
              + " ".join(f"{r[f'bearing_err_p{q:g}_deg']:9.4f}" for q in qs) + " "
              + " ".join(f"{r[f'range_err_p{q:g}_mm']:9.4f}" for q in qs) + " "
              + " ".join(f"{r[f'elevation_p{q:g}_deg']:9.4f}" for q in qs)
              + f"  {r['edge_miss_fraction']:9.3f}")
    print(f"\nsensitivity of the bearing at D = {sens.design_distance_m:g} m (mean over beams "
          "[min..max])")
    for r in sens.table():
        print(f"  {r['mirror']:4} {r['parameter']:12} {r['mean']:+10.5f} "
              f"[{r['min']:+.5f}..{r['max']:+.5f}] {r['unit']}")
    where = ("in process" if res.runner == "in-process"
             else f"on Dask (cluster start-up {res.startup_s:.1f} s)")
    print(f"\nMonte Carlo {where}: {res.wall_s:.2f} s, "
          f"{res.n_samples / max(res.wall_s, 1e-9):.0f} samples/s (Dask above "
          f"{DASK_MIN_SAMPLES} samples by default)")
    return 0
