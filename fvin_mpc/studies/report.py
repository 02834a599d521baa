"""The one report writer of the studies.

:func:`write_report` writes every report's pair of files: ``<stem>.json`` (the data, the command
that produced it and the machine) and ``<stem>.md`` (a title, "Produced by `command`", then the
body). The evaluation, the quadrotor study and the research studies of the repository's
``benchmarks/`` folder use it.
"""

from __future__ import annotations

import json
import math
import platform
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np


def json_safe(value: Any) -> Any:
    """``value`` with every number JSON can hold: a NaN or an infinity (a metric that never came, a
    median of nothing) becomes ``null``, NumPy scalars and arrays plain numbers and lists."""
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(float(value)) else None
    return value


def json_text(value: Any, **options: Any) -> str:
    """``json.dumps`` of :func:`json_safe`'s ``value``: valid JSON (no bare ``NaN``), whatever it holds."""
    return json.dumps(json_safe(value), allow_nan=False, default=float, **options)


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
    json_path.write_text(json_text({"command": command, "machine": machine(), **data}, indent=1) + "\n")
    markdown_path.write_text(f"# {title}\n\nProduced by `{command}`\n\n{body.rstrip()}\n")
    return json_path, markdown_path
