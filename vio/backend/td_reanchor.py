"""td re-anchoring (``CalibConfig.td_reanchor_s``): td information gathered while the
offset still to be estimated was large is biased low, and td is never marginalized, so
it stays in the estimate (large offsets fell 0.7-1.1 ms short on every generator).
Once the td feedback through the sync layer has applied ``td_reanchor_s`` more than at
the window's start, has caught up with the estimate and td is known within
``td_reanchor_sigma_s``, the window restarts once at the current state (its marginal
covariances as priors) and td.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.init import InitialState
from vio.backend.recovery import fresh_window, recover

log = logging.getLogger(__name__)
X, V, B = graph.X, graph.V, graph.B


def maybe_reanchor_td(est) -> None:
    """Restart ``est``'s window (a ``vio.backend.estimator.Estimator``) at the current
    state and td once the sync layer holds ``td_reanchor_s`` more of td than at the last
    (re)start (and has caught up with the estimate) and td's sigma is below
    ``td_reanchor_sigma_s`` (``CalibConfig``)."""
    cc, held = est.cfg.calib, est.rates.td_obs(est.k)
    if (cc.td_reanchor_s <= 0 or abs(held - est._td_anchor) < cc.td_reanchor_s
            or abs(est.td() - est.td_applied_s - held) >= max(cc.td_feedback_s, 1e-4)):
        return     # not moved enough yet, or the feedback still catching up
    k, (T, v, b) = est.k, est.latest()
    cov, noise = est.smoother.marginalCovariance, gtsam.noiseModel.Gaussian.Covariance
    try:
        sigma = float(np.sqrt(cov(graph.TD)[0, 0]))
        if not sigma < cc.td_reanchor_sigma_s:
            return
        g = gtsam.NonlinearFactorGraph()   # the state keeps its marginal, td loses its own
        g.add(gtsam.PriorFactorPose3(X(k), T, noise(cov(X(k)))))
        g.add(gtsam.PriorFactorVector(V(k), v, noise(cov(V(k)))))
        g.add(gtsam.PriorFactorConstantBias(B(k), b, noise(cov(B(k)))))
    except (RuntimeError, ValueError):
        return
    T_b_c, td = est.values.atPose3(graph.EXTRINSIC), float(est.values.atVector(graph.TD)[0])
    t_ns = est.kf_t[k]
    est.td_reanchors += 1
    log.info("t=%d ns: td re-anchored at %.2f ms (sigma %.2f ms; the sync layer applies %.2f ms "
             "more than at the last start): window restarted", t_ns, (est.td_applied_s + td) * 1e3,
             sigma * 1e3, (held - est._td_anchor) * 1e3)
    try:
        fresh_window(est, k, InitialState(t_ns, T, v, b, "td re-anchor"), T_b_c, td, None, priors=g)
    except RuntimeError as exc:
        recover(est, exc, k, k, gtsam.NavState(T, v), b, t_ns)
