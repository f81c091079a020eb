"""Several residual functions as one factor: one Python callback instead of one each.

Each iSAM2 callback of a ``gtsam.CustomFactor`` costs far more than the residual itself
(pybind11 copies the whole ``Values`` for it, then the arguments are read and the
Jacobians handed back: ~50-70 us on a 300-key window, against ~15-25 us for a landmark's
residual). Factors that iSAM2 always linearizes together gain from being one factor:
the farewell factors and depth transfers of the landmarks re-anchored at one keyframe
(``vio.backend.tracks``) enter the graph in one update and are marginalized with the
leaving keyframe in that same update, twice linearized, ~66 callbacks a keyframe on real
MH_05 mono.

The stack's residual is the members' whitened residuals one after another (each member
has an isotropic sigma), its Jacobian the members' whitened blocks scattered into the
columns of the union of their keys, zero elsewhere, and its noise model the unit one: the
same quadratic as the members summed. Only stack factors whose keys are few or shared:
the Jacobian is dense over the union, so a stack of members over disjoint keys costs
``rows x union`` where the members cost ``rows x own keys``.

A member whose evaluation fails (exception, wrong shape, non-finite output) contributes
zero rows for that evaluation and is counted in ``health``; the others are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import gtsam
import numpy as np

from factors.adapter import FactorHealth, KeyKind, ResidualFn, custom_factor, tangent_dim


@dataclass(frozen=True)
class Member:
    """One residual function of a stack: its keys and kinds (in its own order), ``fn``
    returning ``(r (m,), jacobians)`` (one ``(m, total)`` array or one block per key, as
    for ``factors.adapter.custom_factor``), ``m`` rows and isotropic ``sigma``. ``fn``
    must be pure: the stack keeps its last linearization (the adapter's cache)."""

    keys: tuple[int, ...]
    kinds: tuple[KeyKind, ...]
    fn: ResidualFn
    m: int
    sigma: float


def _union(members: Sequence[Member]) -> tuple[list[int], list[KeyKind]]:
    """The keys of all members in first-seen order, with their kinds (checked consistent)."""
    keys: list[int] = []
    kinds: dict[int, KeyKind] = {}
    for mem in members:
        if len(mem.keys) != len(mem.kinds) or len(set(mem.keys)) != len(mem.keys):
            raise ValueError(f"member keys {mem.keys} and kinds {mem.kinds} do not match")
        if not (mem.m > 0 and mem.sigma > 0):
            raise ValueError(f"member needs m > 0 and sigma > 0, got {mem.m}, {mem.sigma}")
        for k, kind in zip(mem.keys, mem.kinds):
            if k not in kinds:
                keys.append(k)
                kinds[k] = kind
            elif kinds[k] != kind:
                raise ValueError(f"key {k} is {kinds[k]!r} in one member and {kind!r} in another")
    return keys, [kinds[k] for k in keys]


def _member_blocks(mem: Member, args: list) -> tuple[np.ndarray, np.ndarray]:
    """A member's residual (m,) and stacked Jacobian (m, total), validated."""
    r, jacs = mem.fn(args)
    r = np.asarray(r, dtype=float).reshape(-1)
    J = np.asarray(jacs, dtype=float) if isinstance(jacs, np.ndarray) else np.hstack(
        [np.asarray(j, dtype=float).reshape(mem.m, -1) for j in jacs])
    total = sum(tangent_dim(kind) for kind in mem.kinds)
    if r.shape != (mem.m,) or J.shape != (mem.m, total):
        raise ValueError(f"member returned r {r.shape}, J {J.shape}; expected ({mem.m},), ({mem.m}, {total})")
    if not (np.isfinite(r).all() and np.isfinite(J).all()):
        raise FloatingPointError("non-finite member output")
    return r, J


def stacked_factor(members: Sequence[Member], health: FactorHealth | None = None) -> gtsam.CustomFactor:
    """One ``gtsam.CustomFactor`` (unit noise) over the union of ``members``' keys whose
    quadratic is the sum of theirs (module docstring)."""
    members = list(members)
    if not members:
        raise ValueError("a stack needs at least one member")
    keys, kinds = _union(members)
    dims = [tangent_dim(kind) for kind in kinds]
    start = np.concatenate([[0], np.cumsum(dims)]).astype(np.int64)
    pos = {k: i for i, k in enumerate(keys)}
    plan = []   # (member, argument positions, Jacobian columns, first row)
    row = 0
    for mem in members:
        idx = [pos[k] for k in mem.keys]
        cols = np.concatenate([np.arange(start[i], start[i + 1]) for i in idx])
        plan.append((mem, idx, cols, row))
        row += mem.m
    n_rows, n_cols = row, int(start[-1])
    health = FactorHealth() if health is None else health

    def fn(args: list) -> tuple[np.ndarray, np.ndarray]:
        r = np.zeros(n_rows)
        J = np.zeros((n_rows, n_cols))
        for mem, idx, cols, r0 in plan:
            try:
                rm, Jm = _member_blocks(mem, [args[i] for i in idx])
            except Exception as exc:  # noqa: BLE001 - one member must not sink the others
                health.record(type(exc).__name__, f"stack member: {exc}")
                continue
            r[r0:r0 + mem.m] = rm / mem.sigma
            J[r0:r0 + mem.m, cols] = Jm / mem.sigma
        return r, J

    return custom_factor(gtsam.noiseModel.Unit.Create(n_rows), keys, kinds, fn, health, cache=True)
