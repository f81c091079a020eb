"""The single adapter from a pure residual function to a ``gtsam.CustomFactor``.

A residual function takes the current values of the factor's keys (``gtsam.Pose3``
for ``"pose3"`` keys, 1-D ``numpy`` arrays for vector keys) and returns
``(r, jacobians)``: ``r`` of shape ``(m,)`` (unwhitened) and one ``(m, d_k)`` array per
key, where ``d_k`` is the tangent dimension of key k (6 for Pose3). The noise model
whitens both. Alternatively ``jacobians`` may be ONE ``(m, sum_k d_k)`` array with the key
blocks side by side in key order: it is validated once and split into column blocks here,
which saves ~3 us per key for factors with many keys (``factors.landmark``).

GTSAM pitfalls this adapter guards against (see DEVELOPERS.md): a wrong-shaped
Jacobian block crashes or silently corrupts the solve, and an exception raised
inside a callback during ``ISAM2.update`` corrupts the solver. So shapes are
checked and any exception or non-finite number is contained: the factor then
contributes a zero residual and zero Jacobians for that evaluation (it drops out
of the linear system) and the failure is counted in ``FactorHealth``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Sequence, Union

import gtsam
import numpy as np

log = logging.getLogger(__name__)

KeyKind = Union[str, int]
"""``"pose3"`` for a ``gtsam.Pose3`` key, or an ``int`` n for an n-vector key."""

ResidualFn = Callable[[list], tuple[np.ndarray, list[np.ndarray]]]


@dataclass
class FactorHealth:
    """Counts callback evaluations that had to be neutralized."""

    failures: int = 0
    last_error: str = ""
    by_kind: dict = field(default_factory=dict)

    def record(self, kind: str, message: str) -> None:
        if self.failures == 0 or self.by_kind.get(kind, 0) == 0:
            log.warning("custom factor %s: %s (contained; factor zeroed for this evaluation)",
                        kind, message)
        self.failures += 1
        self.by_kind[kind] = self.by_kind.get(kind, 0) + 1
        self.last_error = message


DEFAULT_HEALTH = FactorHealth()


def tangent_dim(kind: KeyKind) -> int:
    """Tangent dimension of a key kind."""
    if kind == "pose3":
        return 6
    if isinstance(kind, int) and kind > 0:
        return kind
    raise ValueError(f"unknown key kind {kind!r}: use 'pose3' or a positive int")


def read_value(values: gtsam.Values, key: int, kind: KeyKind):
    """Read one key as the type a residual function expects."""
    if kind == "pose3":
        return values.atPose3(key)
    return np.asarray(values.atVector(key), dtype=float)


def _same_args(a: list, b: list) -> bool:
    """Bitwise equality of two argument lists of ``custom_factor`` callbacks: poses with
    ``Pose3.equals`` at tolerance 0 (exact; NaN never equal), vectors by their bytes (a
    key's vector keeps its length; 0.3 us against ``np.array_equal``'s 3.5)."""
    for x, y in zip(a, b):
        if isinstance(x, gtsam.Pose3):
            if not x.equals(y, 0.0):
                return False
        elif x.tobytes() != y.tobytes():
            return False
    return True


def custom_factor(noise: gtsam.noiseModel.Base, keys: Sequence[int], kinds: Sequence[KeyKind],
                  fn: ResidualFn, health: FactorHealth | None = None,
                  cache: bool = False, state: Callable[[], object] | None = None) -> gtsam.CustomFactor:
    """Wrap ``fn`` as a ``gtsam.CustomFactor`` over ``keys`` of the given ``kinds``.

    The callback validates every Jacobian's shape ``(noise.dim(), tangent_dim)`` and
    contains exceptions and non-finite output (see module docstring).

    ``cache``: keep the last linearization (a call with Jacobians requested) and return it
    again when the values of all keys are bitwise the same and ``state()`` (a snapshot of
    whatever mutable state ``fn`` reads, taken after the evaluation; None: ``fn`` is pure)
    compares equal. iSAM2 relinearizes EVERY factor at its unchanged linearization point
    whenever an update touches >= 65% of the variables (``ISAM2::recalculateBatch``; a
    sliding window's keyframe update nearly always does, unless padded:
    ``vio.backend.padding``) and again when it marginalizes a factor's keys
    (``marginalizeLeaves``): for a pure ``fn`` the cached answer is the same bits. A factor that refines internal variables at each
    linearization (inverse depths eliminated inside) is then refined only when its keys
    move, as GTSAM's smart factors re-triangulate only when their cameras move.
    """
    keys = [int(k) for k in keys]
    kinds = list(kinds)
    if len(keys) != len(kinds):
        raise ValueError(f"{len(keys)} keys but {len(kinds)} kinds")
    dims = [tangent_dim(k) for k in kinds]
    m = int(noise.dim())
    ends = [0]
    for d in dims:
        ends.append(ends[-1] + d)
    spans, total = list(zip(ends[:-1], ends[1:])), ends[-1]
    key_is_pose = [(k, kind == "pose3") for k, kind in zip(keys, kinds)]
    health = DEFAULT_HEALTH if health is None else health

    def evaluate(args: list) -> tuple[np.ndarray, list[np.ndarray]]:
        r, jacs = fn(args)
        r = np.asarray(r, dtype=float).reshape(-1)
        if r.shape != (m,):
            raise ValueError(f"residual has shape {r.shape}, noise model expects ({m},)")
        if not np.isfinite(r).all():
            raise FloatingPointError("non-finite residual")
        if isinstance(jacs, np.ndarray):
            if jacs.shape != (m, total):
                raise ValueError(f"stacked Jacobian has shape {jacs.shape}, expected {(m, total)}")
            if not np.isfinite(jacs).all():
                raise FloatingPointError("non-finite Jacobian")
            J = np.asfortranarray(jacs, dtype=float)
            return r, [J[:, a:b] for a, b in spans]
        if len(jacs) != len(keys):
            raise ValueError(f"{len(jacs)} Jacobians for {len(keys)} keys")
        out = []
        for J, d in zip(jacs, dims):
            J = np.asarray(J, dtype=float)
            if J.shape != (m, d):
                raise ValueError(f"Jacobian has shape {J.shape}, expected {(m, d)}")
            if not np.isfinite(J).all():
                raise FloatingPointError("non-finite Jacobian")
            out.append(J)
        return r, out

    last: list = []   # [args, state snapshot, r, jacs] of the last linearization (cache)

    def error_func(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        try:
            args = [values.atPose3(k) if is_pose else np.asarray(values.atVector(k), dtype=float)
                    for k, is_pose in key_is_pose]  # inlined read_value: ~0.2 us/key less
            if last and _same_args(args, last[0]) and (state is None or state() == last[1]):
                r, jacs = last[2], last[3]
            else:
                r, jacs = evaluate(args)  # validated: shapes and finiteness
                if cache and H is not None:
                    last[:] = [args, None if state is None else state(), r, jacs]
        except Exception as exc:  # noqa: BLE001 - must never propagate into iSAM2
            health.record(type(exc).__name__, f"{exc}")
            r = np.zeros(m)
            jacs = [np.zeros((m, d)) for d in dims]
        if H is not None:
            for i, J in enumerate(jacs):
                H[i] = np.asfortranarray(J)
        return r

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error_func)
