"""Interactive 3D reports of what the jaw commands wrote: ``report.html`` in their output folder.

The report reads the files a command wrote (``occlusion.json`` and its contact map,
``wafer.json`` and ``wafer.stl``, ``closure_ist.json``, a cohort's ``cohort.csv``) and the scene
or meshes they name; it knows nothing of how the results were found, so an old output folder
can be rebuilt (``mjist view OUT_DIR --rebuild``). One self-contained HTML file, no network:
plotly's offline bundle draws the arches (``page``); ``read`` turns each kind of output into
layers, views and tables; ``cohort`` writes the cohort's table page.
"""
from __future__ import annotations

from pathlib import Path

from .cohort import write_cohort
from .page import write_page
from .read import read_output

__all__ = ["build", "build_or_say", "write_cohort", "read_output", "write_page", "show"]


def build(out_dir) -> Path:
    """Write ``report.html`` for the command output in ``out_dir``; return its path.

    Raises ``FileNotFoundError`` naming what the folder lacks when it holds no known output.
    """
    out_dir = Path(out_dir)
    return write_page(read_output(out_dir), out_dir / "report.html")


def build_or_say(out_dir) -> str:
    """``build``'s path, or a line saying why there is no page (the command's results stand
    without it: a report never fails the command that wrote them)."""
    try:
        return str(build(out_dir))
    except Exception as exc:
        return f"no report.html in {out_dir} ({type(exc).__name__}: {exc})"


def show(out_dir, rebuild: bool = False) -> tuple[Path, bool]:
    """The report of ``out_dir`` (built when missing or ``rebuild``), opened in a browser when
    this machine has a display; returns its path and whether a browser was asked to open it."""
    import os
    import webbrowser

    out_dir = Path(out_dir)
    if out_dir.suffix == ".html":
        path, out_dir = out_dir, out_dir.parent
    else:
        path = out_dir / ("cohort.html" if (out_dir / "cohort.csv").exists() else "report.html")
    if rebuild or not path.exists():
        path = write_cohort(out_dir) if path.name == "cohort.html" else build(out_dir)
    opened = False
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or os.name == "nt" or os.uname().sysname == "Darwin":
        try:
            opened = webbrowser.open(path.resolve().as_uri())
        except Exception:  # no usable browser: the path is printed instead
            opened = False
    return path, opened
