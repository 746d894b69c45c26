"""`lookingglass view OUT`: show OUT/report.html in the default browser."""

from __future__ import annotations

import webbrowser
from pathlib import Path
from typing import Callable

from ..errors import LookingGlassError
from .build import REPORT_NAME


def report_path(target: str | Path) -> Path:
    """The report of `target`: OUT/report.html for an output folder (written first when the folder
    has a report.json but no report.html, as folders made before reports existed), or the file."""
    target = Path(target)
    path = target / REPORT_NAME if target.is_dir() else target
    if target.is_dir() and not path.exists() and (target / "report.json").exists():
        from .build import write_report

        write_report(target)
    if not path.exists():
        raise LookingGlassError(f"no {REPORT_NAME} here (a `lookingglass reconstruct` output folder has one)", path)
    if path.suffix.lower() not in (".html", ".htm"):
        raise LookingGlassError("not a report (expected a `lookingglass reconstruct` output folder or its "
                                f"{REPORT_NAME})", path)
    return path


def open_report(target: str | Path, opener: Callable[[str], bool] = webbrowser.open) -> tuple[Path, bool]:
    """Open the report of `target` with `opener` (the default browser); returns its path and
    whether a browser took it (False where there is none, e.g. on a server without a display)."""
    path = report_path(target).resolve()
    try:
        opened = bool(opener(path.as_uri()))
    except webbrowser.Error:
        opened = False
    return path, opened
