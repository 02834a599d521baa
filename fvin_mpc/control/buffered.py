"""Calling a CasADi function from Python without its per-call conversions.

``Function.__call__`` converts every NumPy argument to a ``DM`` and every result back; for the
small compiled functions of the real-time MPC that costs far more than the arithmetic (docs/realtime.md
measures both ways). A
:class:`BufferedFunction` keeps one preallocated NumPy array per argument and per result, registered
once with CasADi's buffer interface, so a call is a few array copies and one C call.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np


class BufferedFunction:
    """``function`` called through preallocated buffers: ``outputs = buffered(*arguments)``.

    Arguments are array-likes of the function's input shapes (``(r, c)``; a column ``(r, 1)`` may
    be given as ``(r,)``). Results are fresh NumPy arrays: ``(r, c)`` matrices, ``(r,)`` for
    columns, 0-d arrays for scalars (``float()`` works). Every input must be dense; sparse results
    are scattered into dense arrays.
    """

    def __init__(self, function: ca.Function) -> None:
        self.function = function
        self._buffer, self._evaluate = function.buffer()
        self._inputs: list[np.ndarray] = []
        for index in range(function.n_in()):
            sparsity = function.sparsity_in(index)
            if not sparsity.is_dense():
                raise ValueError(f"{function.name()}: input {function.name_in(index)!r} is sparse; "
                                 "BufferedFunction needs dense inputs")
            # CasADi stores a dense (r, c) column by column: the C-ordered (c, r) array is that memory
            array = np.zeros((sparsity.size2(), sparsity.size1()))
            self._buffer.set_arg(index, memoryview(array))
            self._inputs.append(array)
        self._outputs: list[tuple[np.ndarray, int, int, np.ndarray | None, np.ndarray | None]] = []
        for index in range(function.n_out()):
            sparsity = function.sparsity_out(index)
            data = np.zeros(sparsity.nnz())
            self._buffer.set_res(index, memoryview(data))
            rows, cols = (None, None) if sparsity.is_dense() else map(np.asarray, sparsity.get_triplet())
            self._outputs.append((data, sparsity.size1(), sparsity.size2(), rows, cols))

    def name(self) -> str:
        return self.function.name()

    def __call__(self, *arguments: Any) -> tuple[np.ndarray, ...]:
        if len(arguments) != len(self._inputs):
            raise TypeError(f"{self.function.name()} takes {len(self._inputs)} arguments, got {len(arguments)}")
        for buffer, argument in zip(self._inputs, arguments):
            buffer[...] = np.reshape(np.asarray(argument, dtype=float).T, buffer.shape)
        self._evaluate()
        return tuple(self._result(*output) for output in self._outputs)

    @staticmethod
    def _result(data: np.ndarray, rows: int, cols: int, row_index: np.ndarray | None,
                col_index: np.ndarray | None) -> np.ndarray:
        if row_index is None:
            matrix = data.reshape(cols, rows).T.copy()
        else:
            matrix = np.zeros((rows, cols))
            matrix[row_index, col_index] = data
        if cols == 1:
            return matrix.reshape(rows) if rows > 1 else matrix.reshape(())
        return matrix
