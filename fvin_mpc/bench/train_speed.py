"""``train-speed``: seconds per training iteration on the reference workload.

The reference implementation (hanyang-hu/S3FVIN, sign-invariant variant) takes ≈ 1.5 s
per full-batch iteration on 3,520 rollout windows of 9 steps with hidden width 10 in
float64 on this kind of 2-core machine (``DESIGN.md``). We time the same workload —
forward rollout, loss, backward and an Adam step — eagerly and with the step compiled,
and time to a fixed loss on real data is reported in ``docs/training.md``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from . import StudyResult, median_time

REFERENCE_SECONDS_PER_ITERATION = 1.5


def run(quick: bool = False, seed: int = 0, repeats: int = 5, **_: Any) -> StudyResult:
    import torch

    from ..model import DTYPE, S3FVIN
    from ..networks import ModelConfig
    from ..train import rollout_loss

    torch.manual_seed(seed)
    windows, steps = (352, 9) if quick else (3520, 9)
    repeats = 2 if quick else repeats
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(windows, steps + 1, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    batch = tuple(torch.as_tensor(a, dtype=DTYPE) for a in (q, rng.normal(size=(windows, steps + 1, 3)),
                                                          rng.uniform(-2, 2, size=(windows, steps, 1))))
    rows = []
    modes = ["eager"] if quick else ["eager", "compiled"]
    for mode in modes:
        for variant in ("sign-invariant", "fixed-inertia"):
            model = S3FVIN(ModelConfig(variant=variant, hidden_width=10), seed=seed)
            optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
            step = None
            compile_s = 0.0
            if mode == "compiled":
                step = torch.compile(model.step, dynamic=False)

            def iteration() -> None:
                optimizer.zero_grad()
                rollout_loss(model, *batch, 0.1, step).backward()
                optimizer.step()

            if mode == "compiled":
                start = time.perf_counter()
                iteration()  # triggers compilation of forward and backward
                compile_s = time.perf_counter() - start
            median, p95 = median_time(iteration, repeats)
            rows.append({"mode": mode, "variant": variant, "windows": windows, "steps": steps,
                         "s_per_iter_median": median, "s_per_iter_p95": p95, "compile_s": compile_s,
                         # Only the full workload is comparable with the reference figure.
                         "speedup_vs_reference": None if quick else REFERENCE_SECONDS_PER_ITERATION / median})

    def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
        axis = figure.add_subplot()
        labels = [f"{r['mode']}\n{r['variant']}" for r in rows]
        axis.bar(labels, [r["s_per_iter_median"] for r in rows], color="tab:blue")
        axis.axhline(REFERENCE_SECONDS_PER_ITERATION, color="tab:red", ls="--", label="reference (DESIGN.md)")
        axis.axhline(REFERENCE_SECONDS_PER_ITERATION / 10, color="tab:green", ls=":", label="10× target")
        axis.set_yscale("log")
        axis.set_ylabel("s / iteration (median)")
        axis.legend()

    notes = [f"Workload: {windows} windows × {steps} steps, hidden width 10, float64, K = 2, full batch; "
             f"reference ≈ {REFERENCE_SECONDS_PER_ITERATION} s/iteration (DESIGN.md, measured on this machine kind). "
             "`compile_s` is the one-off cost of `torch.compile` on the first iteration."]
    return StudyResult("train-speed", rows, ["mode", "variant", "windows", "s_per_iter_median", "s_per_iter_p95",
                                             "compile_s", "speedup_vs_reference"], plot, notes)
