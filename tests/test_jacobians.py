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
LIN_TOL = 1e-9
DELTA = 1e-5
RANDOM_EXAMPLES = 12
DEGENERATE_SEEDS = (0, 1, 2)

_HERE = Path(__file__).resolve().parent


def _collect_cases() -> list:
    """``(module, case)`` params from every ``cases_*.py``; an import error becomes a failing param."""
    params = []
    for info in sorted(pkgutil.iter_modules([str(_HERE)]), key=lambda i: i.name):
        if not info.name.startswith("cases_"):
            continue
        try:
            mod = importlib.import_module(info.name)
        except Exception as exc:  # noqa: BLE001 - reported as a failing test, not a crash
            params.append(pytest.param(info.name, exc, id=f"{info.name}-IMPORT-ERROR"))
            continue
        for case in getattr(mod, "CASES", []):
            params.append(pytest.param(info.name, case, id=f"{info.name}-{case.name}"))
    return params


ALL = _collect_cases()
RANDOM = [p for p in ALL if isinstance(p.values[1], Exception) or not p.values[1].degenerate]
DEGENERATE = [p for p in ALL if not isinstance(p.values[1], Exception) and p.values[1].degenerate]
WORST = {"numeric": (-1.0, "nothing checked"), "linearize": (-1.0, "nothing checked")}


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


def test_cases_were_collected() -> None:
    """The suite must not silently pass with nothing to check."""
    names = {p.values[0] for p in ALL}
    assert "cases_projection" in names
    assert len(ALL) >= 20
