"""Leaf operations that differ between array backends.

The S³ algebra (:mod:`fvin_mpc.s3`), the FVIN step (:mod:`fvin_mpc.fvin`) and the
network evaluation (:mod:`fvin_mpc.networks`) are written once against this small
interface, so the torch model used for training, the NumPy model used by the
control runtime and the symbolic CasADi export are the same code.

Two kinds of values pass through it:

* *components* — one scalar field per quaternion/vector entry. In torch and NumPy a
  component is an array of shape ``(*batch,)``; in CasADi it is a scalar ``SX``/``MX``.
* *vectors* — a stack of components, used only inside the networks. torch/NumPy:
  shape ``(*batch, n)``; CasADi: a column ``(n, 1)``.
"""

from __future__ import annotations

from typing import Any, Protocol, Sequence


class Ops(Protocol):
    """What a backend must provide. Everything else is plain ``+ - * /``."""

    name: str

    def sin(self, x: Any) -> Any: ...
    def cos(self, x: Any) -> Any: ...
    def sqrt(self, x: Any) -> Any: ...
    def atan2(self, y: Any, x: Any) -> Any: ...
    def where(self, condition: Any, if_true: Any, if_false: Any) -> Any: ...
    def tanh(self, x: Any) -> Any: ...
    def softplus(self, x: Any) -> Any: ...
    def stack(self, components: Sequence[Any]) -> Any: ...
    def unstack(self, vector: Any) -> tuple[Any, ...]: ...
    def linear(self, vector: Any, weight: Any, bias: Any) -> Any:
        """``weight @ v + bias`` for ``weight`` of shape ``(out, in)``."""
        ...
    def linear_transpose(self, vector: Any, weight: Any) -> Any:
        """``weightᵀ @ v`` — backpropagation through :meth:`linear`."""
        ...
    def jacobian(self, function: Any, point: Sequence[Any]) -> tuple[tuple[Any, ...], tuple[tuple[Any, ...], ...]]:
        """``function``'s value and Jacobian (rows: outputs, columns: inputs) at ``point``, exact, where the
        backend differentiates: ``function`` maps a tuple of components to a tuple of components."""
        ...


class NumpyOps:
    """NumPy arrays; components ``(*batch,)``, vectors ``(*batch, n)``."""

    name = "numpy"

    def __init__(self) -> None:
        import numpy as np

        self._np = np

    def sin(self, x):
        return self._np.sin(x)

    def cos(self, x):
        return self._np.cos(x)

    def sqrt(self, x):
        return self._np.sqrt(x)

    def atan2(self, y, x):
        return self._np.arctan2(y, x)

    def where(self, condition, if_true, if_false):
        return self._np.where(condition, if_true, if_false)

    def tanh(self, x):
        return self._np.tanh(x)

    def softplus(self, x):
        return self._np.logaddexp(0.0, x)

    def stack(self, components):
        return self._np.stack(self._np.broadcast_arrays(*components), axis=-1)

    def unstack(self, vector):
        return tuple(vector[..., i] for i in range(vector.shape[-1]))

    def linear(self, vector, weight, bias):
        return vector @ weight.T + bias

    def linear_transpose(self, vector, weight):
        return vector @ weight

    def jacobian(self, function, point):
        raise NotImplementedError("the NumPy backend has no derivatives: evaluate the CasADi form numerically")


class TorchOps:
    """torch tensors; components ``(*batch,)``, vectors ``(*batch, n)``."""

    name = "torch"

    def __init__(self) -> None:
        import torch

        self._torch = torch

    def sin(self, x):
        return self._torch.sin(x)

    def cos(self, x):
        return self._torch.cos(x)

    def sqrt(self, x):
        return self._torch.sqrt(x)

    def atan2(self, y, x):
        return self._torch.atan2(y, x)

    def where(self, condition, if_true, if_false):
        return self._torch.where(condition, if_true, if_false)

    def tanh(self, x):
        return self._torch.tanh(x)

    def softplus(self, x):
        return self._torch.nn.functional.softplus(x)

    def stack(self, components):
        torch = self._torch
        tensors = [c if isinstance(c, torch.Tensor) else torch.as_tensor(c, dtype=torch.float64) for c in components]
        return torch.stack(torch.broadcast_tensors(*tensors), dim=-1)

    def unstack(self, vector):
        return tuple(vector.unbind(-1))

    def linear(self, vector, weight, bias):
        return self._torch.nn.functional.linear(vector, weight, bias)

    def linear_transpose(self, vector, weight):
        return vector @ weight

    def jacobian(self, function, point):
        # Reverse mode per output on the batch's sum: the samples are independent, so each row is per sample.
        # create_graph keeps the derivatives differentiable (a Newton step inside a training loss).
        torch = self._torch
        z = self.stack(point)
        if not z.requires_grad:
            z = z.detach().requires_grad_(True)
        value = tuple(function(self.unstack(z)))
        rows = []
        for entry in value:
            entry = entry if isinstance(entry, torch.Tensor) else torch.as_tensor(entry, dtype=z.dtype)
            gradient = None
            if entry.requires_grad:
                gradient = torch.autograd.grad(entry.sum(), z, create_graph=True, allow_unused=True)[0]
            rows.append(self.unstack(torch.zeros_like(z) if gradient is None else gradient))
        return value, tuple(rows)


class CasadiOps:
    """CasADi ``SX``/``MX`` scalars as components, columns as vectors."""

    name = "casadi"

    def __init__(self) -> None:
        import casadi

        self._ca = casadi

    def sin(self, x):
        return self._ca.sin(x)

    def cos(self, x):
        return self._ca.cos(x)

    def sqrt(self, x):
        return self._ca.sqrt(x)

    def atan2(self, y, x):
        return self._ca.atan2(y, x)

    def where(self, condition, if_true, if_false):
        return self._ca.if_else(condition, if_true, if_false)

    def tanh(self, x):
        return self._ca.tanh(x)

    def softplus(self, x):
        ca = self._ca
        # log(1 + e^x) without overflow for large x.
        return ca.fmax(x, 0) + ca.log1p(ca.exp(-ca.fabs(x)))

    def stack(self, components):
        return self._ca.vertcat(*components)

    def unstack(self, vector):
        return tuple(vector[i] for i in range(vector.shape[0]))

    def linear(self, vector, weight, bias):
        return self._ca.mtimes(self._matrix(weight), vector) + self._matrix(bias)

    def linear_transpose(self, vector, weight):
        return self._ca.mtimes(self._matrix(weight).T, vector)

    def jacobian(self, function, point):
        # Symbolic: differentiate at a fresh symbol, then put the point in (SX or MX, as the point is).
        ca = self._ca
        kind = ca.MX if any(isinstance(p, ca.MX) for p in point) else ca.SX
        z = kind.sym("z", len(point))
        value = ca.vertcat(*function(self.unstack(z)))
        value, jacobian = ca.substitute([value, ca.jacobian(value, z)], [z], [kind(ca.vertcat(*point))])
        return self.unstack(value), tuple(tuple(jacobian[i, j] for j in range(len(point)))
                                          for i in range(value.shape[0]))

    def _matrix(self, value):
        # Weights are numbers, or symbols where a model parameter stands in for them (model_parameters).
        ca = self._ca
        return value if isinstance(value, (ca.SX, ca.MX)) else ca.DM(value)


_OPS: dict[str, Ops] = {}


def get_ops(name: str) -> Ops:
    """The shared :class:`Ops` instance for ``"numpy"``, ``"torch"`` or ``"casadi"``."""
    if name not in _OPS:
        factories = {"numpy": NumpyOps, "torch": TorchOps, "casadi": CasadiOps}
        if name not in factories:
            raise ValueError(f"unknown backend {name!r}; expected one of {sorted(factories)}")
        _OPS[name] = factories[name]()
    return _OPS[name]
