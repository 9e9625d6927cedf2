"""Estimation error against the truth, as an observer (Khodayi-mehr et al. 2019, Sec. IV).

Strategies never see the true target states. A strategy that estimates the
targets reports, in ``commands.info``, its global estimate ``target_estimate``
((M, 3), m) and the discrete step it refers to, ``target_estimate_step``; at
every reading tick (``observation.target_step`` not None) whose step matches,
this observer computes the localisation error e_g(t) = ||x_g(t) - x(t)||
(m, over all targets stacked) against the frame's true target positions (at
a reading tick the sim time is exactly the step time, so they are x(k)).

It runs before the other observers and writes the latest e_g into the frame's
``info['scalars']['e_g_m']``, so plots and the recording show it; it never
touches the simulation. ``summary()`` gives eq. (13a): the mean and
population standard deviation of e_g over the steps t = 1..t_end (step 0,
the prior plus the first readings, is left out); empty when no strategy
reported an estimate.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.observers import Frame, Observer


class EstimationMetrics(Observer):
    def __init__(self):
        self.steps: list[int] = []
        self.errors: list[float] = []
        self._last: float | None = None

    def reads_info(self, time_s: float) -> bool:
        # Only the metrics keys (target_estimate, target_estimate_step), which
        # strategies always provide; it adds e_g to the scalars when they are there.
        return False

    def on_tick(self, frame: Frame) -> None:
        info = frame.commands.info
        estimate = info.get("target_estimate")
        step = frame.observation.target_step
        if estimate is not None and step is not None and info.get("target_estimate_step") == step:
            truth = np.asarray(frame.target_positions, dtype=float)
            self._last = float(np.linalg.norm(np.asarray(estimate, dtype=float) - truth))
            self.steps.append(int(step))
            self.errors.append(self._last)
        if self._last is not None:
            scalars = info.get("scalars")
            if isinstance(scalars, dict):
                scalars["e_g_m"] = self._last

    def close(self, status: str) -> None:
        pass

    def summary(self) -> dict[str, Any]:
        values = np.array([e for s, e in zip(self.steps, self.errors) if s >= 1])
        if not self.steps:
            return {}
        if values.size == 0:
            return {"e_g_mean_m": None, "e_g_std_m": None}
        return {"e_g_mean_m": float(values.mean()), "e_g_std_m": float(values.std())}
