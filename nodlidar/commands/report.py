"""``nodlidar report DESIGN``: write the design report (HTML with embedded figures, Markdown).

Solves the design, verifies it by ray trace, runs the drift, interleave, tolerance Monte
Carlo and sensitivity analyses, compares with the paper's published numbers and with the
other placement method, and writes ``report.html``, ``report.md`` (figures in
``figures/``), ``report.json`` and the resolved design TOML to ``--out``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from .._light import MAX_SAMPLES  # (not analysis.tolerance: --help imports no numpy)
from ._args import add_force_arg, bounded_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write the design report (HTML + Markdown)",
                       description=__doc__)
    p.add_argument("design", help="design TOML file, e.g. design/urg04lx-paper.toml")
    p.add_argument("--out", help="output directory (default out/report/<design name>/)")
    p.add_argument("--samples", type=bounded_int(1, MAX_SAMPLES),
                   help=f"Monte Carlo samples, 1 .. {MAX_SAMPLES} (default: [tolerance])")
    p.add_argument("--seed", type=bounded_int(0), help="Monte Carlo seed (default: [tolerance])")
    p.add_argument("--workers", type=bounded_int(0),
                   help="0: in process; N: a local Dask cluster of N worker processes "
                        "(default: in process up to 20000 samples)")
    p.add_argument("--scheduler", metavar="ADDR", help="run the Monte Carlo on this Dask scheduler")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object: the files written and the report's summary")
    p.add_argument("--explore", metavar="JSON",
                   help="add the design-space section from an explore.json of nodlidar explore")
    add_force_arg(p)
    p.set_defaults(func=run)


def tqdm_progress(desc: str) -> tuple[Callable[[int, int], None], Callable[[], None]]:
    """A ``progress(done, total)`` callback drawing a tqdm bar (CLI only), and its closer."""
    from tqdm import tqdm

    from ._output import progress_disable, raise_if_interrupted

    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        raise_if_interrupted()   # a Ctrl-C swallowed inside Dask stops the run here
        if bar is None:
            bar = tqdm(total=total, desc=desc, unit="sample", disable=progress_disable())
        bar.update(done - bar.n)

    def close() -> None:
        if bar is not None:
            bar.close()

    return progress, close


def run(args: argparse.Namespace) -> int:
    from ..analysis.report import compute_report, default_out_dir, write_report
    from ..spec import load_design
    from ._args import check_output_path
    from .tolerance import check_monte_carlo_options

    check_monte_carlo_options(args)  # the same options as nodlidar tolerance
    spec = load_design(args.design)
    if args.out is None:   # the default place: out/report/ is ours to create
        default_out_dir(spec).parent.mkdir(parents=True, exist_ok=True)
    out = check_output_path(args.out or default_out_dir(spec), force=args.force, kind="directory")
    exploration = None
    if getattr(args, "explore", None):
        from ..analysis.explore import load_exploration

        exploration = load_exploration(args.explore)  # before the Monte Carlo
    progress, close = tqdm_progress("Monte Carlo")
    try:
        data = compute_report(spec, samples=args.samples, seed=args.seed, workers=args.workers,
                              scheduler=args.scheduler, progress=progress,
                              exploration=exploration)
    finally:
        close()
    paths = write_report(data, out)
    if args.json:
        import json

        summary = json.loads(paths.json.read_text())
        print(json.dumps({"html": str(paths.html), "markdown": str(paths.markdown),
                          "json": str(paths.json), "toml": str(paths.toml),
                          "figures": [str(f) for f in paths.figures], "summary": summary}, indent=2))
        return 0
    print(f"wrote {paths.html}")
    print(f"wrote {paths.markdown} ({len(paths.figures)} figures in {paths.figures[0].parent})")
    print(f"wrote {paths.json}")
    print(f"wrote {paths.toml}")
    return 0
