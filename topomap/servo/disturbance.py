"""Disturbance observer for appearance servoing (docs/theory.md section 2 "Observer", section 3).

Input: the relative pose reconstructed from the images at each control step and the command applied
over the previous step. Images give the relative heading ``theta`` without scale and the position only
up to the scale ``lambda``; the actuators add unknown disturbances ``u_eff = (1 - slip) u + d``
(docs/theory.md eq. 1.7-1.8). What this makes observable, and what is estimated here:

* ``d_omega`` — the heading obeys ``theta' = omega + d_omega`` with no scale involved, so a Kalman
  filter on ``(theta, d_omega)`` (random-walk disturbance) estimates it: a linear observer, the
  degenerate case of the §2.5 construction where ``Phi`` is linear and its Jacobian constant.
  Multiplicative slip on the turn rate shows up as a slowly varying part of ``d_omega``.
* the scaled effective velocity ``nu = (u_eff)_lin / lambda`` — from consecutive scaled positions,
  modelled as ``nu = kappa u_lin + mu``: ``kappa = (1 - slip) / lambda`` and ``mu = d_lin / lambda``
  cannot be separated from the scale (the scale direction of docs/theory.md section 2), but ``kappa``
  gives the observable ratio ``r = (v + d_v) / e`` of the scale-free law. A Kalman filter over the
  parameters ``(kappa, mu_f, mu_h)``.

The heading's measurement noise is not one number: a view with near texture resolves the heading to
a tenth of a degree, a deep corridor view near its goal scatters it by degrees between two
reconstructions (a small turn and a small sideways step move distant points alike). A filter that
assumes the first noise under the second turns every scatter into a ``d_omega`` that the law then
"compensates", spinning the camera away from the view (docs/servo.md, "Heading noise"). The scaled
positions scatter the same way (by a metre, now and then, at a goal 0.1 m away), and a drift read
from them shifts every pose the servo's window predicts. So each filter's measurement noise is the
larger of the configured one and the noise measured over its last ``noise_window`` images
(:class:`_NoiseMeter`: second differences, so that neither a varying disturbance nor the filter's
lag counts as noise; their median, so that one wrong reconstruction in a few moves it not at all).

The forward disturbance itself is rejected by integral action in the laws.
Hand-written 2- and 3-state Kalman filters (a few lines of numpy; no library needed for this size).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from topomap.config import ObserverConfig
from topomap.motion import Command, wrap_angle

__all__ = ["DisturbanceEstimate", "DisturbanceObserver"]


@dataclass(frozen=True)
class DisturbanceEstimate:
    """What the observer currently believes.

    ``d_omega`` [rad/s] and its standard deviation; ``theta`` filtered relative heading [rad] (NaN
    before the first measurement); ``kappa`` scaled speed per commanded speed [1/m]
    (``(1 - slip) / lambda``); ``mu_f, mu_h`` scaled drift forward / leftward [lambda/s];
    ``rejected``: consecutive heading measurements rejected as outliers.
    """

    d_omega: float = 0.0
    d_omega_std: float = math.inf
    theta: float = math.nan
    kappa: float = math.nan
    mu_f: float = 0.0
    mu_h: float = 0.0
    rejected: int = 0

    @property
    def ready(self) -> bool:
        """At least two consistent headings have been seen (d_omega is estimated)."""
        return math.isfinite(self.d_omega_std) and self.d_omega_std < 0.1


#: Deviation of one measurement per median size of its second differences, a scalar (1 / (0.6745 sqrt 6)) ...
SECOND_DIFFERENCE_TO_STD = 0.6053
#: ... and a 2-D point (per axis; the median length of a 2-D Gaussian is 1.1774 deviations: 1 / (1.1774 sqrt 6)).
SECOND_DIFFERENCE_TO_STD_2D = 0.3467
#: Headings rejected in a row as wrong reconstructions (gated by the filter or by a new goal's prior)
#: before the next one is believed: the reference really moved.
MAX_REJECTED = 3


class _NoiseMeter:
    """The noise of a measured sequence from the median size of its second differences, with the
    commanded motion taken out of each step: a slowly varying disturbance cancels in them, and the
    filter's own lag does not enter (its innovations would count that as noise too, and a filter
    that trusts its measurements less lags more). Hand-written: a few lines over a deque."""

    def __init__(self, window: int, to_std: float):
        self.window, self.to_std = int(window), float(to_std)
        self._last_step: np.ndarray | None = None
        self._sizes: deque[float] = deque(maxlen=max(1, self.window))

    def clear(self) -> None:
        """Another view: another noise."""
        self._last_step = None
        self._sizes.clear()

    def add(self, step: np.ndarray | None) -> None:
        """The next step between consecutive measurements less the commanded motion; None when a
        measurement is missing (the differences restart)."""
        if step is not None and self._last_step is not None:
            self._sizes.append(float(np.linalg.norm(step - self._last_step)))
        self._last_step = None if step is None else np.asarray(step, float)

    def variance(self, floor: float) -> float:
        """``floor`` or the measured variance, whichever is larger (the floor until three second
        differences are held, and always with a window of 0)."""
        if self.window == 0 or len(self._sizes) < 3:
            return floor
        sd = self.to_std * float(np.median(self._sizes))
        return max(floor, sd * sd)


class DisturbanceObserver:
    """Kalman filters over ``(theta, d_omega)`` and ``(kappa, mu_f, mu_h)``; see the module docstring.

    ``kappa0``: prior scaled speed per commanded speed, ``1 / nominal_scale_m``.
    """

    def __init__(self, config: ObserverConfig | None = None, kappa0: float = 1.0 / 3.0):
        self.cfg = config or ObserverConfig()
        self.kappa0 = float(kappa0)
        # heading filter: x = [theta, d_omega]
        self._x = np.array([math.nan, 0.0])
        self._P = np.diag([1.0, 0.2**2])
        self._has_theta = False
        self._prior_only = False  # theta is a prediction for a new goal, not yet measured
        self._rejected = 0
        self._heading_noise = _NoiseMeter(self.cfg.noise_window, SECOND_DIFFERENCE_TO_STD)
        # forward filter: p = [kappa, mu_f, mu_h]
        self._p = np.array([self.kappa0, 0.0, 0.0])
        self._Pp = np.diag([(0.5 * self.kappa0) ** 2, (0.05 * self.kappa0) ** 2, (0.05 * self.kappa0) ** 2])
        self._position_noise = _NoiseMeter(self.cfg.noise_window, SECOND_DIFFERENCE_TO_STD_2D)
        self._last_pos: np.ndarray | None = None
        self._last_theta: float | None = None
        self._last_heading: float | None = None  # the last measured heading (for the noise meter)

    # ------------------------------------------------------------------ lifecycle
    def reset_target(self, theta_prior: float | None = None) -> None:
        """A new goal image: heading and position references jump; the disturbances stay.

        ``theta_prior``: the heading relative to the new goal predicted without its image (e.g. the
        heading relative to the previous goal composed with the two goal images' relative heading).
        It is dead-reckoned like a measured one until the first measurement, which replaces it
        (it never updates d_omega: its error is not the disturbance's) — unless that measurement
        lies beyond ``ObserverConfig.prior_gate_deg`` of it: a wrong reconstruction, until three in
        a row say so."""
        self._has_theta = False
        self._x[0] = math.nan
        self._P[0, :] = self._P[:, 0] = 0.0
        self._P[0, 0] = 1.0
        self._last_pos, self._last_theta, self._last_heading = None, None, None
        self._rejected = 0
        self._heading_noise.clear()
        self._position_noise.clear()
        self._prior_only = False
        if theta_prior is not None and math.isfinite(theta_prior):
            self._x[0] = wrap_angle(float(theta_prior))
            self._has_theta = self._prior_only = True

    # ------------------------------------------------------------------ one step
    def update(
        self,
        dt: float,
        applied: Command | None,
        theta: float | None,
        position_s: np.ndarray | None = None,
    ) -> DisturbanceEstimate:
        """Advance by ``dt`` [s] under the command ``applied`` since the last call, then correct with
        the measured relative heading ``theta`` [rad] and scaled position ``position_s`` (2,) (None
        when the images did not give them)."""
        cfg = self.cfg
        if not self._has_theta or self._prior_only:
            if dt > 0:  # no measured heading to lean on: the disturbance's walk goes on all the same
                self._P[1, 1] += cfg.d_omega_walk**2 * dt
        if self._prior_only and applied is not None and dt > 0:
            # a predicted heading: dead-reckoned, its covariance untouched (the first measurement
            # replaces it and then everything is as if there had been no prior)
            self._x[0] = wrap_angle(self._x[0] + (applied.omega + self._x[1]) * dt)
        elif self._has_theta and applied is not None and dt > 0:
            F = np.array([[1.0, dt], [0.0, 1.0]])
            self._x = F @ self._x + np.array([applied.omega * dt, 0.0])
            Q = np.diag([(0.2 * cfg.heading_noise_rad) ** 2 * dt, cfg.d_omega_walk**2 * dt])
            self._P = F @ self._P @ F.T + Q
        measured = theta is not None and math.isfinite(theta)
        self._heading_noise.add(wrap_angle(theta - self._last_heading) - applied.omega * dt
                                if measured and self._last_heading is not None and applied is not None else None)
        self._last_heading = float(theta) if measured else None
        R = self._heading_noise.variance(cfg.heading_noise_rad**2)
        gate = math.radians(cfg.prior_gate_deg) if cfg.prior_gate_deg is not None else math.inf
        if measured and self._prior_only and abs(wrap_angle(theta - self._x[0])) > gate and self._rejected < MAX_REJECTED:
            self._rejected += 1  # a first reconstruction far from the prediction: wrong, until it persists
        elif measured:
            if not self._has_theta or self._prior_only:
                self._prior_only = False
                self._x[0] = theta
                self._P[0, 0] = R
                self._P[0, 1] = self._P[1, 0] = 0.0
                self._has_theta = True
                self._rejected = 0
            else:
                innov = wrap_angle(theta - self._x[0])
                S = self._P[0, 0] + R
                if innov * innov > 25.0 * S and self._rejected < MAX_REJECTED:
                    self._rejected += 1  # a wrong reconstruction; after MAX_REJECTED in a row, believe it
                else:
                    if innov * innov > 25.0 * S:  # persistent: the reference really moved
                        self._x[0] = theta
                        self._P[0, 0] = R
                        self._P[0, 1] = self._P[1, 0] = 0.0
                    else:
                        K = self._P[:, 0] / S
                        self._x = self._x + K * innov
                        self._P = self._P - np.outer(K, self._P[0, :])
                    self._rejected = 0
            self._x[0] = wrap_angle(self._x[0])
            self._x[1] = max(-cfg.d_omega_max, min(cfg.d_omega_max, self._x[1]))
        # forward parameters from the scaled displacement
        if position_s is not None and np.all(np.isfinite(position_s)) and theta is not None:
            pos = np.asarray(position_s, dtype=float)
            if self._last_pos is not None and applied is not None and dt > 0:
                self._forward_update(pos - self._last_pos, 0.5 * (self._last_theta + theta) if abs(wrap_angle(theta - self._last_theta)) < 1.0 else theta, applied, dt)
            else:
                self._position_noise.add(None)
            self._last_pos, self._last_theta = pos, float(theta)
        else:
            self._position_noise.add(None)
            self._last_pos, self._last_theta = None, None
        return self.estimate

    def age(self, seconds: float) -> None:
        """``seconds`` passed without any :meth:`update` (the robot moved on other commands): the
        disturbances walked on, so their uncertainty grows as the random walks say; estimates kept."""
        if not (math.isfinite(seconds) and seconds > 0):
            return
        self._P[1, 1] += self.cfg.d_omega_walk**2 * seconds
        self._Pp = self._Pp + np.eye(3) * (self.cfg.forward_walk * self.kappa0) ** 2 * seconds

    def observe_turn(self, dt: float, applied: Command | None, turned_rad: float | None) -> DisturbanceEstimate:
        """Correct ``d_omega`` with the turn ``turned_rad`` [rad] measured between two consecutive images
        ``dt`` [s] apart under the command ``applied`` (a visual gyro: the two images need not show
        any goal). Call it after :meth:`update` of the same period; a turn that disagrees with the
        estimate by more than 5 deviations is ignored (a wrong reconstruction)."""
        if turned_rad is None or not math.isfinite(turned_rad) or applied is None or not (dt > 0):
            return self.estimate
        innov = (wrap_angle(turned_rad) / dt - applied.omega) - self._x[1]
        S = self._P[1, 1] + self.cfg.turn_rate_noise_rps**2
        if innov * innov > 25.0 * S:
            return self.estimate
        K = self._P[:, 1] / S  # K[0] = 0 while no heading is held: P's heading row is zero then
        self._x = self._x + K * innov
        self._P = self._P - np.outer(K, self._P[1, :])
        self._x[0] = wrap_angle(self._x[0])  # (a NaN heading stays NaN)
        self._x[1] = max(-self.cfg.d_omega_max, min(self.cfg.d_omega_max, self._x[1]))
        return self.estimate

    def _forward_update(self, step: np.ndarray, theta_mid: float, applied: Command, dt: float) -> None:
        cfg = self.cfg
        self._Pp = self._Pp + np.eye(3) * (cfg.forward_walk * self.kappa0) ** 2 * dt
        c, s = math.cos(theta_mid), math.sin(theta_mid)
        nu = np.array([c * step[0] + s * step[1], -s * step[0] + c * step[1]]) / dt  # body frame
        H = np.array([[applied.v_f, 1.0, 0.0], [applied.v_h, 0.0, 1.0]])
        commanded = np.array([applied.v_f, applied.v_h])
        self._position_noise.add((nu - self._p[0] * commanded) * dt)  # the drift's part cancels in the differences
        innov = nu - H @ self._p
        # a speed is the difference of two positions, each with the measured (or the configured) noise
        r = 2.0 * self._position_noise.variance(cfg.position_noise_s**2) / dt**2
        S_inv = np.linalg.inv(H @ self._Pp @ H.T + np.eye(2) * r)
        if float(innov @ S_inv @ innov) > 25.0:
            return  # a wrong reconstruction: its speed is no evidence of drift
        K = self._Pp @ H.T @ S_inv
        self._p = self._p + K @ innov
        self._Pp = (np.eye(3) - K @ H) @ self._Pp
        self._p[0] = max(0.05 * self.kappa0, self._p[0])  # a positive gain, whatever the noise says

    # ------------------------------------------------------------------ view
    @property
    def estimate(self) -> DisturbanceEstimate:
        return DisturbanceEstimate(
            d_omega=float(self._x[1]),
            d_omega_std=float(math.sqrt(max(self._P[1, 1], 0.0))),
            theta=float(self._x[0]) if self._has_theta else math.nan,
            kappa=float(self._p[0]),
            mu_f=float(self._p[1]),
            mu_h=float(self._p[2]),
            rejected=self._rejected,
        )
