"""Torch-side helpers the studies time: a thread-count context and the batched step's time.

The studies layer does not import torch itself (``tests/test_layers.py``); what it measures of
torch lives here.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Callable, Iterator

import numpy as np

from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run torch with ``threads`` intra-op threads, restoring the previous setting afterwards.

    The studies use one thread: on a busy machine two torch threads spin waiting for each other and
    run many times slower than one (docs/training.md)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def batched_step_call(terms_of: Callable[[Any], Any], step_size: float, newton_iters: int, q: np.ndarray,
                      omega: np.ndarray, u: np.ndarray) -> Callable[[], None]:
    """A no-grad call of the torch step on the batch ``q (B, 4)``, ``ω (B, 3)``, ``u (B, m)``;
    ``terms_of(ops)`` builds the rigid-body terms on the torch backend (learned weights as float64
    tensors, or a closed-form body). For timing with :func:`benchmarks.study.median_time` (the repository's studies)."""
    import torch

    ops = get_ops("torch")
    terms = terms_of(ops)
    tq = tuple(torch.as_tensor(q[:, i]) for i in range(4))
    tw = tuple(torch.as_tensor(omega[:, i]) for i in range(3))
    tu = tuple(torch.as_tensor(u[:, i]) for i in range(u.shape[1]))

    def call() -> None:
        with torch.no_grad():
            fvin.fvin_step(tq, tw, tu, terms, step_size, newton_iters, ops)

    return call


def tensor_weights(weights: dict[str, np.ndarray]) -> dict[str, Any]:
    """Checkpoint weights as float64 torch tensors."""
    import torch

    return {name: torch.as_tensor(value, dtype=torch.float64) for name, value in weights.items()}
