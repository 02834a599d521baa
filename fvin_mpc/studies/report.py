"""The one report writer of the studies, and the accuracy-vs-time studies' results.

:func:`write_report` writes every report's pair of files: ``<stem>.json`` (the data, the command
that produced it and the machine) and ``<stem>.md`` (a title, "Produced by `command`", then the
body). The evaluation, Pendulum-v1 and the ``python -m fvin_mpc.bench <study>`` studies use it.

Every bench study returns a :class:`StudyResult`; :func:`write_study` turns it into
``<out>/<study>.json``, ``<out>/<study>.md`` (a Markdown table) and ``<out>/<study>.png``. Times
are medians over repeats, compared as ratios within one run because the machines are shared and noisy.
"""

from __future__ import annotations

import json
import platform
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np


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


def _format(value: Any) -> str:
    if isinstance(value, float):
        if value == 0 or not np.isfinite(value):
            return str(value)
        return f"{value:.3g}" if (abs(value) >= 1e-3 and abs(value) < 1e4) else f"{value:.2e}"
    return str(value)


def markdown_table(rows: list[dict[str, Any]], columns: Sequence[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_format(row.get(c, "")) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def machine() -> dict[str, Any]:
    """What a report says about where it ran: Python, platform, processor, cores and the load average."""
    import os

    return {"python": sys.version.split()[0], "platform": platform.platform(), "processor": platform.processor(),
            "cores": os.cpu_count(), "load_average_1_5_15_min": list(os.getloadavg())}


def write_report(stem: Path, title: str, data: dict[str, Any], body: str, command: str) -> tuple[Path, Path]:
    """``<stem>.json`` = ``{"command", "machine", **data}`` and ``<stem>.md`` = title, command, body."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    json_path, markdown_path = stem.parent / f"{stem.name}.json", stem.parent / f"{stem.name}.md"
    json_path.write_text(json.dumps({"command": command, "machine": machine(), **data}, indent=1, default=float) + "\n")
    markdown_path.write_text(f"# {title}\n\nProduced by `{command}`\n\n{body.rstrip()}\n")
    return json_path, markdown_path


def write_study(result: StudyResult, out_dir: Path, argv: Sequence[str]) -> dict[str, Path]:
    """Write the JSON, Markdown and PNG of ``result`` into ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    command = "python -m fvin_mpc.bench " + " ".join(shlex.quote(a) for a in argv)
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
