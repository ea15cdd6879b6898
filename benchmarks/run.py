"""Run every benchmark (``benchmarks/bench_*.py``) in turn: ``make bench``.

Each benchmark prints ratios against a baseline measured in the same run, because
absolute times drift on shared machines. Pass names to run a subset:
``python benchmarks/run.py solver scip``.
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

here = Path(__file__).parent
wanted = sys.argv[1:]
for path in sorted(here.glob("bench_*.py")):
    name = path.stem.removeprefix("bench_")
    if wanted and name not in wanted:
        continue
    print(f"=== {name} ===", flush=True)
    runpy.run_path(str(path), run_name="__main__")
