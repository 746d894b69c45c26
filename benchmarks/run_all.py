"""Run every benchmark and assemble docs/benchmarks.md from their sections.

    .venv/bin/python benchmarks/run_all.py            # all
    .venv/bin/python benchmarks/run_all.py hull       # only bench_hull.py

Each `bench_NAME.py` prints its figures and ratios to the targets and writes its section to
docs/benchmarks_NAME.md; this script runs them one after another (they time themselves, so never
in parallel) and joins the sections into docs/benchmarks.md.
"""

from __future__ import annotations

import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def main(names: list[str]) -> int:
    scripts = sorted((ROOT / "benchmarks").glob("bench_*.py"))
    if names:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in names]
    failed = []
    for script in scripts:
        print(f"== {script.name}", flush=True)
        if subprocess.call([sys.executable, str(script)], cwd=ROOT) != 0:
            failed.append(script.name)
    sections = sorted(DOCS.glob("benchmarks_*.md"))
    cpu = platform.processor() or platform.machine()
    header = ("# Benchmarks\n\nProduced by `.venv/bin/python benchmarks/run_all.py` on the project's reference "
              f"machine (2 CPU cores, 24 GB RAM, no GPU; {cpu}, Python {platform.python_version()}). "
              f"Last assembled {time.strftime('%Y-%m-%d')}. Each section names the script that made it.\n")
    body = "\n".join(s.read_text().strip() + "\n" for s in sections)
    (DOCS / "benchmarks.md").write_text(header + "\n" + body)
    if failed:
        print("failed:", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
