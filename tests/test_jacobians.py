"""One parametrized Jacobian suite over the ``CASES`` of every ``tests/cases_*.py`` module.

For every case and every key it checks, at random (hypothesis-drawn seeds) and
degenerate (fixed seeds) states:

* shapes: residual ``(m,)`` with ``m = noise.dim()``, block k ``(m, d_k)``;
* analytic vs ``gtsam.utils.numerical_derivative.numericalDerivative11`` (central
  differences on the retraction ``T * Exp(xi)`` for Pose3, ``x + dx`` for vectors,
  ``delta = 1e-5``): ``max|A - N| <= TOL * max(1, max|N|)`` per block (combined
  absolute/relative criterion, ``TOL = 1e-6``);
* analytic vs ``factor.linearize(values)``: the JacobianFactor's whitened blocks and
  right-hand side equal the noise-whitened analytic ones (``gtsam.noiseModel.Robust``
  included: ``sqrt(w)`` times the base whitening) to ``1e-9`` relative.

Factors with variables eliminated inside (``REDUCED_CASES``, ``jacobian_case.ReducedCase``:
their residual is a square root of the reduced quadratic) are checked instead against the
full point-wise problem: ``A^T A`` and ``-A^T b`` of ``linearize`` equal its Schur
complement (``REDUCED_TOL`` relative), and that gradient equals central differences of the
energy minimized over the eliminated variables (``REDUCED_GRAD_TOL``).

The worst normalized errors seen are printed at the end of the module (``-s``/``-rA``).
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

TOL = 1e-6
REDUCED_TOL = 1e-6
REDUCED_GRAD_TOL = 1e-4
LIN_TOL = 1e-9
DELTA = 1e-5
RANDOM_EXAMPLES = 12
DEGENERATE_SEEDS = (0, 1, 2)

_HERE = Path(__file__).resolve().parent


def _collect_cases(attr: str = "CASES") -> list:
    """``(module, case)`` params from every ``cases_*.py``'s ``attr``; an import error becomes
    a failing param (reported once, under ``CASES``)."""
    params = []
    for info in sorted(pkgutil.iter_modules([str(_HERE)]), key=lambda i: i.name):
        if not info.name.startswith("cases_"):
            continue
        try:
            mod = importlib.import_module(info.name)
        except Exception as exc:  # noqa: BLE001 - reported as a failing test, not a crash
            if attr == "CASES":
                params.append(pytest.param(info.name, exc, id=f"{info.name}-IMPORT-ERROR"))
            continue
        for case in getattr(mod, attr, []):
            params.append(pytest.param(info.name, case, id=f"{info.name}-{case.name}"))
    return params


ALL = _collect_cases()
REDUCED = _collect_cases("REDUCED_CASES")
RANDOM = [p for p in ALL if isinstance(p.values[1], Exception) or not p.values[1].degenerate]
DEGENERATE = [p for p in ALL if not isinstance(p.values[1], Exception) and p.values[1].degenerate]
WORST = {"numeric": (-1.0, "nothing checked"), "linearize": (-1.0, "nothing checked"),
         "reduced": (-1.0, "nothing checked")}


@pytest.fixture(scope="module", autouse=True)
def _report_worst():
    yield
    for kind, (err, where) in WORST.items():
        print(f"\nworst {kind} Jacobian error (normalized): {err:.3e} at {where}")


def _note(kind: str, err: float, where: str) -> None:
    if err >= WORST[kind][0]:
        WORST[kind] = (err, where)


def _tangent_dim(kind) -> int:
    return 6 if kind == "pose3" else int(kind)


def _read(values: gtsam.Values, key: int, kind):
    return values.atPose3(key) if kind == "pose3" else np.asarray(values.atVector(key), float)


def _whitened(noise, r: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a JacobianFactor from ``linearize`` should hold: (b, A) = (-W r, W J)."""
    if isinstance(noise, gtsam.noiseModel.Robust):
        base = noise.noise()
        e = base.whiten(r)
        sw = np.sqrt(noise.robust().weight(float(np.linalg.norm(e))))
        return -sw * e, sw * base.Whiten(J)
    return -noise.whiten(r), noise.Whiten(J)


def check_case(name: str, case, seed: int) -> None:
    if isinstance(case, Exception):
        raise AssertionError(f"{name} failed to import: {case!r}")
    rng = np.random.default_rng(seed)
    factor, values, residual, kinds = case.build(rng)
    keys = list(factor.keys())
    assert len(keys) == len(kinds)
    noise = factor.noiseModel()
    m = int(noise.dim())
    r, jacs = residual(values)
    r = np.asarray(r, float)
    assert r.shape == (m,), f"{case.name}: residual shape {r.shape} != ({m},)"
    assert len(jacs) == len(keys)
    for J, kind in zip(jacs, kinds):
        assert np.shape(J) == (m, _tangent_dim(kind)), f"{case.name}: block shape {np.shape(J)}"
        assert np.all(np.isfinite(J)) and np.all(np.isfinite(r))

    lin = factor.linearize(values)
    assert list(lin.keys()) == keys
    A, b = lin.jacobian()
    b_exp, A_exp = _whitened(noise, r, np.hstack([np.asarray(J, float) for J in jacs]))
    lin_err = max(np.abs(A - A_exp).max() / max(1.0, np.abs(A_exp).max()),
                  np.abs(b - b_exp).max() / max(1.0, np.abs(b_exp).max()))
    _note("linearize", lin_err, f"{case.name} seed={seed}")
    assert lin_err <= LIN_TOL, f"{case.name}: linearize differs from analytic by {lin_err:.2e}"

    for key, kind, J in zip(keys, kinds, jacs):
        x0 = _read(values, key, kind)

        def h(x, key=key):
            v = gtsam.Values(values)
            v.update(key, x)
            return np.asarray(residual(v)[0], float)

        N = numericalDerivative11(h, x0, DELTA)
        err = np.abs(np.asarray(J) - N).max() / max(1.0, np.abs(N).max())
        where = f"{case.name} key={gtsam.DefaultKeyFormatter(key)} seed={seed}"
        _note("numeric", err, where)
        assert err <= TOL, f"{where}: analytic vs numeric Jacobian error {err:.2e}\n" \
                           f"analytic=\n{np.asarray(J)}\nnumeric=\n{N}"


@pytest.mark.parametrize(("module", "case"), RANDOM)
@settings(max_examples=RANDOM_EXAMPLES, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(seed=st.integers(min_value=0, max_value=2**32 - 1))
def test_random_state(module: str, case, seed: int) -> None:
    check_case(module, case, seed)


@pytest.mark.parametrize(("module", "case"), DEGENERATE)
@pytest.mark.parametrize("seed", DEGENERATE_SEEDS)
def test_degenerate_state(module: str, case, seed: int) -> None:
    check_case(module, case, seed)


def _schur(H: np.ndarray, g: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Eliminate the last n variables of the quadratic (H, g)."""
    m = H.shape[0] - n
    K = np.linalg.solve(H[m:, m:], H[m:, :m])
    return H[:m, :m] - H[:m, m:] @ K, g[:m] - K.T @ g[m:]


def check_reduced_case(name: str, case, seed: int) -> None:
    """A ``jacobian_case.ReducedCase``: ``linearize`` equals the Schur complement of the
    full problem (``REDUCED_TOL`` relative), its gradient the central differences of the
    minimized energy on the retraction (``REDUCED_GRAD_TOL``)."""
    rng = np.random.default_rng(seed)
    factor, values, kinds, full, energy = case.build(rng)
    keys = list(factor.keys())
    assert len(keys) == len(kinds)
    A, b = factor.linearize(values).jacobian()
    H, g = A.T @ A, -A.T @ b
    Hf, gf, n = full(values)
    Hs, gs = _schur(Hf, gf, n)
    err = max(np.abs(H - Hs).max() / np.abs(Hs).max(), np.abs(g - gs).max() / max(1.0, np.abs(gs).max()))
    _note("reduced", err, f"{case.name} seed={seed}")
    assert err <= REDUCED_TOL, f"{case.name}: reduced information/gradient differ by {err:.2e}"
    num, c = np.zeros_like(g), 0
    for key, kind in zip(keys, kinds):
        x0 = _read(values, key, kind)
        for j in range(_tangent_dim(kind)):
            out = []
            for s in (DELTA, -DELTA):
                v = gtsam.Values(values)
                dx = np.zeros(_tangent_dim(kind))
                dx[j] = s
                v.update(key, x0.retract(dx) if kind == "pose3" else x0 + dx)
                out.append(energy(v))
            num[c] = (out[0] - out[1]) / (2 * DELTA)
            c += 1
    err = np.abs(g - num).max() / max(1.0, np.abs(num).max())
    _note("reduced", err, f"{case.name} seed={seed} (gradient)")
    assert err <= REDUCED_GRAD_TOL, f"{case.name}: gradient vs central differences {err:.2e}"


@pytest.mark.parametrize(("module", "case"), REDUCED)
@pytest.mark.parametrize("seed", DEGENERATE_SEEDS)
def test_reduced_case(module: str, case, seed: int) -> None:
    check_reduced_case(module, case, seed)


def test_cases_were_collected() -> None:
    """The suite must not silently pass with nothing to check."""
    names = {p.values[0] for p in ALL}
    assert "cases_projection" in names
    assert {p.values[0] for p in REDUCED} >= {"cases_landmark_schur"}
    assert len(ALL) >= 20
