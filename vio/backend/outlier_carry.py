"""The outlier update held for the next frame (``SolverConfig.outlier_update``).

After a keyframe's update the landmark manager rejects the landmarks whose reprojection
error exceeds ``outlier_px`` (``LandmarkManager.outlier_removals``) and a second smoother
update takes their factors out. With ``"next_frame"`` that second update is held here and
run when the next frame arrives (or before the next keyframe's update, whichever comes
first), so the keyframe's frame does not wait for it: the smoother goes through the same
updates in the same order, only the keyframe's own output is its estimate before the
removal. Deterministic: the hold ends at a frame, not at a time.

Factor slots are positions in the smoother: a rebuild in between (td re-anchoring, the
scale refinement) remaps the held removals (``remap``), a restart forgets them (``clear``);
the held graph is the manager's own, with the slots it recorded for its factors.
"""

from __future__ import annotations

import gtsam


class OutlierCarry:
    """One held outlier update: (graph, timestamps, factor slots to remove)."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self._held: tuple[gtsam.NonlinearFactorGraph, dict, list[int]] | None = None

    def hold(self, g: gtsam.NonlinearFactorGraph, stamps: dict, removals: list[int], n: int) -> int:
        """Hold an outlier check's update (``LandmarkManager.outlier_removals``' tuple) if
        it rejected anything (``n`` landmarks); returns ``n``."""
        if self._held is not None:
            raise RuntimeError("an outlier update is already held (take() it first)")
        if n:
            self._held = (g, dict(stamps), [int(i) for i in removals])
        return n

    def take(self, sm: gtsam.IncrementalFixedLagSmoother
             ) -> tuple[gtsam.NonlinearFactorGraph, dict, list[int]] | None:
        """The held update (None if none), its removals limited to slots of ``sm`` that
        still hold a factor (removing an empty slot is not allowed); clears the hold."""
        held, self._held = self._held, None
        if held is None:
            return None
        g, stamps, removals = held
        fg = sm.getFactors()
        live = [i for i in dict.fromkeys(removals) if i < fg.size() and fg.at(i) is not None]
        return g, stamps, live

    def remap(self, remap: dict[int, int]) -> None:
        """After a smoother rebuild: old -> new factor slots (dropped ones forgotten)."""
        if self._held is not None:
            g, stamps, removals = self._held
            self._held = (g, stamps, [remap[i] for i in removals if i in remap])
