"""What every accuracy-vs-time study of ``python -m benchmarks <study>`` returns, and its writer.

Every study returns a :class:`StudyResult`; :func:`write_study` turns it into
``<out>/<study>.json``, ``<out>/<study>.md`` (a Markdown table) and ``<out>/<study>.png``. Times
are medians over repeats, compared as ratios within one run because the machines are shared and noisy.
"""

from __future__ import annotations

import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fvin_mpc.studies.report import markdown_table, write_report


@dataclass
class StudyResult:
    """Rows of one study plus how to draw them.

    Attributes:
        name: study name (the CLI sub-command).
        rows: one dict per configuration; keys are column names.
        columns: the columns shown in the Markdown table, in order.
        plot: draws the study onto a matplotlib ``Figure``.
        notes: Markdown paragraphs printed under the table.
    """

    name: str
    rows: list[dict[str, Any]]
    columns: Sequence[str]
    plot: Callable[[Any, list[dict[str, Any]]], None] | None = None
    notes: list[str] = field(default_factory=list)


class StudySkipped(Exception):
    """A study cannot run here (e.g. its checkpoint is absent); the message says why and what to do."""


def median_time(function: Callable[[], Any], repeats: int, warmup: int = 1) -> tuple[float, float]:
    """Median and 95th percentile wall time (s) of ``function()`` over ``repeats`` calls."""
    for _ in range(warmup):
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), float(np.percentile(times, 95))


def write_study(result: StudyResult, out_dir: Path, argv: Sequence[str]) -> dict[str, Path]:
    """Write the JSON, Markdown and PNG of ``result`` into ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    command = "python -m benchmarks " + " ".join(shlex.quote(a) for a in argv)
    body = [markdown_table(result.rows, result.columns), ""] + [note + "\n" for note in result.notes]
    body += [f"![{result.name}]({result.name}.png)", ""]
    paths = dict(zip(("json", "md"), write_report(out_dir / result.name, f"`{result.name}` study",
                                                   {"study": result.name, "rows": result.rows, "notes": result.notes},
                                                   "\n".join(body), command)))
    paths["png"] = out_dir / f"{result.name}.png"
    if result.plot is not None:
        figure = plt.figure(figsize=(7, 4.5))
        result.plot(figure, result.rows)
        figure.tight_layout()
        figure.savefig(paths["png"], dpi=110)
        plt.close(figure)
    else:
        paths.pop("png")
    return paths
