"""The growing feature bank psi: S x A -> R^q of Gaussian kernels (paper section 2.2).

Feature j is ``psi_j(z) = exp(-||z - c_j||^2 / (2 h_j^2))`` on the normalised state-action
``z = (z_s, z_a)`` (a joint atom, the paper's), or, with control-affine atoms
(``feature_selection.control_affine``), the state kernel alone,
``exp(-||z_s - c_s,j||^2 / (2 h_j^2))`` (an atom that ignores the action), or the state kernel
times one action coordinate, ``exp(-||z_s - c_s,j||^2 / (2 h_j^2)) z_a[i]`` (an atom linear in
the action): together these represent a feature change affine in the action,
``f(s) + G(s) a``, the form of most physical control systems, and extend it from the actions
tried to all others. Every atom factorises, ``psi_j(s, a) = S_j(s) A_j(a)``. The bank only ever
grows by appending, which is what lets the smoothed Q weights be zero-padded instead of
keeping a history (docs/design.md, "Q needs no history").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import nn

CUTOFF_EXPONENT = -30.0
"""Kernel values at or below exp(-30) ~ 9e-14 are set to exactly 0. A float32 sum of kernel
values cannot see them (its rounding is ~1e-7 of the largest), and the cut keeps every value,
every product of two values (the factorised psi) and their products with the model's weights
clear of denormal floats, on which ``exp``, elementwise products and GEMMs run 10-30x slower."""
_CUTOFF_VALUE = math.exp(CUTOFF_EXPONENT)

JOINT = -1
"""``action_basis`` code of a joint Gaussian atom on (z_s, z_a), the paper's."""
STATE_ONLY = -2
"""``action_basis`` code of an atom that is the state kernel alone (A_j(a) = 1)."""
# a code i >= 0: the state kernel times the action coordinate z_a[i] (A_j(a) = z_a[i])


def gaussian_kernel(
    x: torch.Tensor, centres: torch.Tensor, inv_two_sq_bandwidth: torch.Tensor, out: torch.Tensor | None = None
) -> torch.Tensor:
    """Gaussian kernel values between points and centres, one bandwidth per centre.

    The exponent ``-a_j ||x - c_j||^2`` with ``a_j = 1 / (2 h_j^2)`` expands to
    ``[x, ||x||^2, 1] . [2 a_j c_j, -a_j, -a_j ||c_j||^2]``, so the whole (N, q) exponent is
    one GEMM; clamping, ``exp`` and the cut-off (:data:`CUTOFF_EXPONENT`)
    then run in place on that one buffer (no (N, q) temporaries).

    :param x: (N, d) points
    :param centres: (q, d) centres
    :param inv_two_sq_bandwidth: (q,) values a_j = 1 / (2 h_j^2)
    :param out: (N, q) buffer to write into (reused memory: no fresh pages to fault in), or None
    :return: (N, q) kernel values in [0, 1] (0 at or below exp(CUTOFF_EXPONENT))
    """
    return kernel_from_points(kernel_points(x), kernel_parameters(centres, inv_two_sq_bandwidth), out)


def kernel_parameters(centres: torch.Tensor, inv_two_sq_bandwidth: torch.Tensor) -> torch.Tensor:
    """The GEMM operand of :func:`gaussian_kernel` that depends on the centres only.

    :param centres: (q, d) centres
    :param inv_two_sq_bandwidth: (q,) values a_j
    :return: the (d + 2, q) matrix ``[2 a_j c_j, -a_j, -a_j ||c_j||^2]^T``
    """
    a = inv_two_sq_bandwidth[:, None]
    return torch.cat([2 * a * centres, -a, -a * (centres * centres).sum(1, keepdim=True)], dim=1).T.contiguous()


def kernel_points(x: torch.Tensor) -> torch.Tensor:
    """The operand of :func:`gaussian_kernel` that depends on the points: (N, d) -> (N, d + 2) ``[x, ||x||^2, 1]``."""
    return torch.cat([x, (x * x).sum(1, keepdim=True), torch.ones_like(x[:, :1])], dim=1)


def kernel_from_points(points: torch.Tensor, weights: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`gaussian_kernel` from the operands of :func:`kernel_points` and :func:`kernel_parameters`.

    :param points: (N, d + 2)
    :param weights: (d + 2, q)
    :param out: (N, q) buffer to write into, or None
    :return: (N, q) kernel values
    """
    exponent = torch.mm(points, weights) if out is None else torch.mm(points, weights, out=out)
    if torch.is_grad_enabled() and exponent.requires_grad:  # a caller differentiates through psi (out-of-place)
        return torch.nn.functional.threshold(exponent.clamp(CUTOFF_EXPONENT, 0.0).exp(), _CUTOFF_VALUE, 0.0)
    return torch.nn.functional.threshold_(exponent.clamp_(CUTOFF_EXPONENT, 0.0).exp_(), _CUTOFF_VALUE, 0.0)


class KernelBank(nn.Module):
    """psi as an ``nn.Module`` whose size q grows by :meth:`append`.

    Each atom has a centre, a bandwidth and an action basis code (:data:`JOINT`,
    :data:`STATE_ONLY`, or i >= 0 for the state kernel times z_a[i]). Loading a state dict
    resizes the bank to the saved q, so a bank always loads whole.

    :param state_dim: width of the normalised state part z_s
    :param action_dim: width of the normalised action part z_a
    """

    def __init__(self, state_dim: int, action_dim: int) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.register_buffer("centres", torch.zeros(0, state_dim + action_dim))
        self.register_buffer("inv_two_sq_bandwidth", torch.ones(0))
        self.register_buffer("action_basis", torch.zeros(0, dtype=torch.long))
        self.version = 0  # changes whenever the features' tensors change (append, load, to): caches key on it
        self._parameters_cache: dict[str, tuple[int, torch.Tensor]] = {}

    @property
    def q(self) -> int:
        """q, the number of features."""
        return int(self.inv_two_sq_bandwidth.numel())

    def forward(self, z: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """psi at normalised state-actions.

        :param z: (N, state_dim + action_dim) normalised state-actions (z_s, z_a)
        :param out: (N, q) buffer to write into, or None
        :return: (N, q)
        """
        return self.from_points(self.points(z), out)

    def points(self, z: torch.Tensor) -> torch.Tensor:
        """The operand of psi's GEMM that depends on the points, (N, d) -> (N, d + 3),
        ``[z_s, ||z_s||^2, z_a, ||z_a||^2, 1]`` (the two norms apart: an atom that ignores the
        action weighs the second by 0)."""
        z_s, z_a = z[:, : self.state_dim], z[:, self.state_dim :]
        squares = [(part * part).sum(1, keepdim=True) for part in (z_s, z_a)]
        return torch.cat([z_s, squares[0], z_a, squares[1], torch.ones_like(z[:, :1])], dim=1)

    def from_points(self, points: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """psi from :meth:`points`: one GEMM with :meth:`weights`, ``exp``, then the atoms linear
        in the action times their coordinate.

        :param points: (N, d + 3)
        :param out: (N, q) buffer to write into, or None
        :return: (N, q)
        """
        psi = kernel_from_points(points, self.weights(), out)
        linear = self._linear_atoms()
        if linear is None:
            return psi
        columns, coordinates = linear
        if psi.requires_grad:  # exp's backward reads its output: multiply a copy
            psi = psi.clone()
        psi[:, columns] *= points[:, self.state_dim + 1 + coordinates]
        return psi

    def state_factor(self, z_state: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """S (N, q): the state factor of psi, psi_j(s, a) = S[n, j] * A[k, j] (a Gaussian on a
        concatenation factorises).

        :param z_state: (N, state_dim) normalised states
        :param out: (N, q) buffer to write into, or None
        """
        return kernel_from_points(kernel_points(z_state), self.state_weights(), out)

    def state_weights(self) -> torch.Tensor:
        """The (state_dim + 2, q) operand of the state factor (:func:`kernel_parameters`), kept until the bank changes."""
        return self._cached("state", lambda: kernel_parameters(self.centres[:, : self.state_dim], self.inv_two_sq_bandwidth))

    def weights(self) -> torch.Tensor:
        """The (state_dim + action_dim + 3, q) operand of psi for :meth:`points`, kept until the bank changes:
        ``[2 a c_s; 2 a m c_a; -a; -a m; -a (||c_s||^2 + m ||c_a||^2)]``, m = 1 for a joint atom, else 0."""

        def build() -> torch.Tensor:
            a, joint = self.inv_two_sq_bandwidth, self._joint()
            state, action = self.centres[:, : self.state_dim], self.centres[:, self.state_dim :]
            rows = [
                2 * a[:, None] * state,
                -a[:, None],
                2 * (a * joint)[:, None] * action,
                -(a * joint)[:, None],
                (-a * ((state * state).sum(1) + joint * (action * action).sum(1)))[:, None],
            ]
            return torch.cat(rows, dim=1).T.contiguous()

        return self._cached("full", build)

    def _joint(self) -> torch.Tensor:
        """(q,) 1.0 for a joint atom, 0.0 for the others (whose action part is not a Gaussian)."""
        return (self.action_basis == JOINT).to(self.inv_two_sq_bandwidth)

    def _cached(self, name: str, build: Callable[[], torch.Tensor]) -> torch.Tensor:
        cached = self._parameters_cache.get(name)
        if cached is None or cached[0] != self.version:
            cached = (self.version, build())
            self._parameters_cache[name] = cached
        return cached[1]

    def _linear_atoms(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The columns of the atoms linear in the action and their action coordinates, or None if there are none."""

        def build() -> torch.Tensor:
            return torch.nonzero(self.action_basis >= 0).flatten()

        columns = self._cached("linear", build)
        if len(columns) == 0:
            return None
        return columns, self.action_basis[columns]

    def action_factor(self, z_action: torch.Tensor) -> torch.Tensor:
        """A (K, q): the action factor of psi (a Gaussian for a joint atom, 1 for an atom that
        ignores the action, z_a[i] for one linear in it). :param z_action: (K, action_dim) normalised actions."""
        factor = gaussian_kernel(z_action, self.centres[:, self.state_dim :], self.inv_two_sq_bandwidth * self._joint())
        linear = self._linear_atoms()
        if linear is None:
            return factor
        columns, coordinates = linear
        if factor.requires_grad:
            factor = factor.clone()
        factor[:, columns] = z_action[:, coordinates]
        return factor

    def append(self, centres: torch.Tensor, bandwidths: torch.Tensor, action_basis: torch.Tensor | None = None) -> None:
        """Append features.

        :param centres: (l, state_dim + action_dim) new centres in normalised units
        :param bandwidths: (l,) their bandwidths h
        :param action_basis: (l,) their action basis codes (None: all :data:`JOINT`)
        """
        basis = torch.full((len(centres),), JOINT, dtype=torch.long) if action_basis is None else action_basis
        self.centres = torch.cat([self.centres, centres.to(self.centres)])
        self.inv_two_sq_bandwidth = torch.cat([self.inv_two_sq_bandwidth, (1 / (2 * bandwidths**2)).to(self.centres)])
        self.action_basis = torch.cat([self.action_basis, basis.to(self.action_basis)])
        self.version += 1

    def move_states(self, scale: torch.Tensor, shift: torch.Tensor) -> None:
        """Re-express the state part of the centres in new normalised coordinates,
        ``z_s <- scale * z_s + shift`` (the same env-unit centres after the box changed);
        bandwidths stay in normalised units.

        :param scale: (state_dim,) old half-range / new half-range
        :param shift: (state_dim,) (old centre - new centre) / new half-range
        """
        self.centres[:, : self.state_dim].mul_(scale.to(self.centres)).add_(shift.to(self.centres))
        self.version += 1

    def _apply(self, fn: Any, recurse: bool = True) -> KernelBank:
        """``to()``, ``double()``, ...: the tensors change, so do the caches built from them."""
        self.version += 1
        return super()._apply(fn, recurse)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        centres = state_dict.get(prefix + "centres")
        if isinstance(centres, torch.Tensor) and prefix + "action_basis" not in state_dict:  # saved before the codes
            state_dict[prefix + "action_basis"] = torch.full((len(centres),), JOINT, dtype=torch.long)
        resize_buffers(self, state_dict, prefix, {"centres": 0, "inv_two_sq_bandwidth": 0, "action_basis": 0})
        self.version += 1
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def resize_buffers(module: nn.Module, state_dict: dict[str, Any], prefix: str, growing: dict[str, int]) -> None:
    """Give the growing buffers of ``module`` the length they have in ``state_dict`` along
    their growing axis, so ``load_state_dict`` then copies them whole. A buffer whose other
    axes differ, or a missing key, is left for the strict load to report.

    :param module: the module being loaded
    :param state_dict: the state dict being loaded
    :param prefix: the module's key prefix in ``state_dict``
    :param growing: buffer name -> the axis along which it grows with q
    """
    for name, axis in growing.items():
        saved = state_dict.get(prefix + name)
        current = getattr(module, name)
        if not isinstance(saved, torch.Tensor) or saved.ndim != current.ndim:
            continue
        fixed_saved = [n for i, n in enumerate(saved.shape) if i != axis % saved.ndim]
        fixed_current = [n for i, n in enumerate(current.shape) if i != axis % current.ndim]
        if fixed_saved == fixed_current:
            setattr(module, name, current.new_zeros(saved.shape))
