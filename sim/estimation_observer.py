"""Estimation error against the truth, as an observer (Khodayi-mehr et al. 2019, Sec. IV).

Strategies never see the true target states. A strategy that estimates the
targets reports its global estimate in ``commands.estimate``
(:class:`sim.types.TargetEstimate`: the discrete step and the (M, 3) mean);
at every reading tick whose step matches, the loop computes the localisation
error e_g(t) = ||x_g(t) - x(t)|| against the true target positions
(:func:`sim.observers.estimation_error`) and puts it in the frame
(``frame.estimation``; ``frame.scalars['e_g_m']`` holds the latest for the
plots, the recording and progress.json). This observer collects it:
``summary()`` gives eq. (13a), the mean and population standard deviation of
e_g over the steps t = 1..t_end (step 0, the prior plus the first readings,
is left out); empty when no strategy reported an estimate.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.observers import Frame, Observer


class EstimationMetrics(Observer):
    def __init__(self):
        self.steps: list[int] = []
        self.errors: list[float] = []
        self.times: list[float] = []  # sim time of each error, s

    def reads_decorations(self, time_s: float) -> bool:
        return False  # only commands.estimate, which strategies always fill

    def on_tick(self, frame: Frame) -> None:
        estimation = frame.estimation
        if estimation is not None and estimation.fresh:
            self.steps.append(estimation.step)
            self.errors.append(estimation.e_g_m)
            self.times.append(frame.observation.time_s)

    def close(self, status: str) -> None:
        pass

    def around(self, at_s: float) -> dict[str, Any]:
        """Mean e_g (steps >= 1) before ``at_s`` and from it on (a fault's time); null where none."""
        before = [e for s, t, e in zip(self.steps, self.times, self.errors) if s >= 1 and t < at_s]
        after = [e for s, t, e in zip(self.steps, self.times, self.errors) if s >= 1 and t >= at_s]
        return {"e_g_before_fault_m": float(np.mean(before)) if before else None,
                "e_g_after_fault_m": float(np.mean(after)) if after else None}

    def summary(self) -> dict[str, Any]:
        values = np.array([e for s, e in zip(self.steps, self.errors) if s >= 1])
        if not self.steps:
            return {}
        if values.size == 0:
            return {"e_g_mean_m": None, "e_g_std_m": None}
        return {"e_g_mean_m": float(values.mean()), "e_g_std_m": float(values.std())}
