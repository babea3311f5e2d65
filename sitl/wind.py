"""Wind: a steady component plus first-order (Dryden-like) turbulence.

Each NED axis carries an independent Gauss-Markov gust ``u`` with the first-order
spectrum of the Dryden longitudinal model,

.. math::

    \\dot u = -\\frac{V}{L} u + \\sigma \\sqrt{\\frac{2V}{L}}\\,\\eta(t),

where ``V`` is the airspeed, ``L`` the turbulence length scale, ``sigma`` the gust
intensity and ``eta`` unit white noise. Its stationary standard deviation is
``sigma`` and its autocorrelation ``exp(-V |tau| / L)`` (Taylor's frozen-turbulence
hypothesis: the vehicle flies through a fixed field at speed ``V``). It is
discretised exactly for a step ``dt``:

.. math::

    u_{k+1} = a u_k + \\sigma \\sqrt{1 - a^2}\\, n_k, \\qquad a = e^{-V\\,dt/L},
    \\quad n_k \\sim N(0, 1),

so the statistics do not depend on the step. Simplifications: the three axes use
the same ``sigma`` and ``L`` (isotropic; real low-altitude Dryden has smaller
vertical intensity and length), and ``V`` is floored at
:data:`MIN_AIRSPEED_M_S` because a hovering vehicle still sees gusts evolve, which
frozen turbulence with ``V = 0`` would not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_AIRSPEED_M_S", "Wind", "WindConfig"]

#: Airspeed floor in the gust time constant ``L / V`` (m/s); see the module docstring.
MIN_AIRSPEED_M_S = 1.0

# Normal deviates are drawn in blocks: one generator call per step would cost more
# than the filter itself, and block draws stay bit-identical for a given seed.
_BLOCK = 3 * 1024


@dataclass(frozen=True)
class WindConfig:
    """Wind parameters.

    Attributes
    ----------
    steady_ned_m_s : tuple of 3 float
        Mean wind velocity in NED (m/s): the velocity of the air, so ``(0, 5, 0)``
        is air moving east (a wind *from* the west).
    gust_sigma_m_s : float
        Turbulence intensity per axis (m/s, standard deviation); 0 disables gusts.
    gust_length_m : float
        Turbulence length scale ``L`` (m).
    """

    steady_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_sigma_m_s: float = 0.0
    gust_length_m: float = 50.0

    def __post_init__(self) -> None:
        if len(self.steady_ned_m_s) != 3 or not all(math.isfinite(v) for v in self.steady_ned_m_s):
            raise ValueError(
                f"steady_ned_m_s: expected three finite numbers, got {self.steady_ned_m_s!r}"
            )
        if not (math.isfinite(self.gust_sigma_m_s) and self.gust_sigma_m_s >= 0.0):
            raise ValueError(f"gust_sigma_m_s: expected >= 0, got {self.gust_sigma_m_s!r}")
        if not (math.isfinite(self.gust_length_m) and self.gust_length_m > 0.0):
            raise ValueError(f"gust_length_m: expected > 0, got {self.gust_length_m!r}")


class Wind:
    """Wind velocity field sampled along the vehicle's path.

    Parameters
    ----------
    config : WindConfig
        Steady wind and gust parameters.
    rng : numpy.random.Generator
        Source of all gust randomness (seeded by the scenario).
    """

    def __init__(self, config: WindConfig, *, rng: np.random.Generator) -> None:
        self.config = config
        self._rng = rng
        self._sigma = float(config.gust_sigma_m_s)
        self._length_m = float(config.gust_length_m)
        self._steady = tuple(float(v) for v in config.steady_ned_m_s)
        self._noise: list[float] = []
        self._i_noise = 0
        # Start in the stationary distribution so gust statistics hold from t = 0.
        if self._sigma > 0.0:
            self._gust = [self._sigma * self._normal() for _ in range(3)]
        else:
            self._gust = [0.0, 0.0, 0.0]

    def _normal(self) -> float:
        if self._i_noise >= len(self._noise):
            self._noise = self._rng.standard_normal(_BLOCK).tolist()
            self._i_noise = 0
        n = self._noise[self._i_noise]
        self._i_noise += 1
        return n

    @property
    def gust_ned_m_s(self) -> tuple[float, float, float]:
        """Current turbulence component (m/s), without the steady wind."""
        return (self._gust[0], self._gust[1], self._gust[2])

    def velocity_ned(
        self, t_s: float, dt_s: float, airspeed_m_s: float
    ) -> tuple[float, float, float]:
        """Advance the turbulence by ``dt_s`` and return the wind velocity (NED, m/s).

        Parameters
        ----------
        t_s : float
            Simulation time (s); kept for the interface, the field is stationary.
        dt_s : float
            Time to advance the gust filters (s); ``<= 0`` returns the current wind.
        airspeed_m_s : float
            Vehicle speed relative to the air (m/s), sets the gust bandwidth ``V/L``.

        Returns
        -------
        tuple of 3 float
            ``steady + gust``.
        """
        del t_s
        sigma = self._sigma
        g = self._gust
        if sigma > 0.0 and dt_s > 0.0:
            v = airspeed_m_s if math.isfinite(airspeed_m_s) else 0.0
            v = max(abs(v), MIN_AIRSPEED_M_S)
            a = math.exp(-v * dt_s / self._length_m)
            b = sigma * math.sqrt(1.0 - a * a)
            g[0] = a * g[0] + b * self._normal()
            g[1] = a * g[1] + b * self._normal()
            g[2] = a * g[2] + b * self._normal()
        s = self._steady
        return (s[0] + g[0], s[1] + g[1], s[2] + g[2])
