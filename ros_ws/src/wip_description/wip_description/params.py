"""Physical parameters of the wheeled inverted pendulum (WIP).

The paper [1]_ gives no numerical parameters; the defaults below are the project's
1.2 m service robot (see docs/paper.md §1), chosen
so that the paper's limits make sense: holding θ = 0.1 rad takes about 7 N·m of the
30 N·m available, and the yaw authority 0.8·g1 ≈ 2 rad/s² exceeds the unit-amplitude
yaw disturbance.

References
----------
.. [1] M. Yue, C. An, Z. Li, "Constrained Adaptive Robust Trajectory Tracking for WIP
   Vehicles Using Model Predictive Control and Extended State Observer", IEEE Trans.
   Syst., Man, Cybern.: Systems, 2016, doi:10.1109/TSMC.2016.2621181.
"""

from __future__ import annotations

import dataclasses
import math

from wip_runtime.config import check_number, param

#: Standard gravity [m/s²].
STANDARD_GRAVITY = 9.81
#: Every quantity of the model is finite and positive (a ParamError, a ValueError, else).
_POSITIVE = {'minimum': 0.0, 'exclusive_minimum': True}


@dataclasses.dataclass(frozen=True)
class ModelParams:
    """Masses, lengths and inertias of a WIP, in SI units.

    Attribute names are descriptive; the paper's symbol is given for each. Derived, set
    at construction (not fields): ``effective_mass`` m_v [kg], ``pitch_inertia`` J_θ
    [kg m²], ``yaw_inertia_total`` J_ϕ [kg m²] (see ``__post_init__``).
    """

    body_mass: float = param(25.0, 'kg', 'm_p, mass of the pendulum body',
                             minimum=0.0, exclusive_minimum=True)
    com_height: float = param(0.6, 'm', 'l, distance from the wheel axle to the centre of '
                              'mass of the body', minimum=0.0, exclusive_minimum=True)
    body_pitch_inertia_com: float = param(4.0, 'kg m^2', 'I_c, pitch inertia of the body '
                                          'about its own centre of mass', minimum=0.0,
                                          exclusive_minimum=True)
    chassis_mass: float = param(5.0, 'kg', 'm_c, mass of the chassis (axle, motors), which '
                                'does not tilt', minimum=0.0, exclusive_minimum=True)
    wheel_mass: float = param(2.5, 'kg', 'm_w, mass of one wheel', minimum=0.0,
                              exclusive_minimum=True)
    wheel_radius: float = param(0.20, 'm', 'r, wheel radius', minimum=0.0,
                                exclusive_minimum=True)
    wheel_inertia: float = param(0.05, 'kg m^2', 'J_w, spin inertia of one wheel about its '
                                 'axle', minimum=0.0, exclusive_minimum=True)
    track_width: float = param(0.5, 'm', 'd, distance between the two wheel contact points',
                               minimum=0.0, exclusive_minimum=True)
    yaw_inertia: float = param(0.5, 'kg m^2', 'J_v, yaw inertia of body and chassis about '
                               'the vertical axis', minimum=0.0, exclusive_minimum=True)
    gravity: float = param(STANDARD_GRAVITY, 'm/s^2', 'g, gravitational acceleration',
                           minimum=0.0, exclusive_minimum=True)

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):   # however the instance is made
            check_number(f'ModelParams.{field.name}', getattr(self, field.name), _POSITIVE,
                         want_int=False)
        # Derived quantities (docs/paper.md §1: the only reading under which (1) is the
        # Euler-Lagrange system of a consistent Lagrangian), computed once (the instance
        # is frozen; the estimator evaluates eq. (1)'s input gains every period). Plain
        # attributes set here, not cached properties: a cached property's cache is an
        # instance dict, which slows every attribute read of the instance (1.5 % of a run).
        # They are not fields: equality, hashing, repr and replace() ignore them.
        derived = {
            # m_v = m_p + m_c + 2 (m_w + J_ω / r²), total translational mass [kg].
            'effective_mass': (self.body_mass + self.chassis_mass
                               + 2.0 * (self.wheel_mass
                                        + self.wheel_inertia / self.wheel_radius ** 2)),
            # J_θ = I_c + m_p l², body pitch inertia about the axle [kg m²].
            'pitch_inertia': self.body_pitch_inertia_com + self.body_mass * self.com_height ** 2,
            # J_ϕ = J_υ + d² (m_w + J_ω / r²) / 2, yaw inertia at θ = 0 [kg m²].
            'yaw_inertia_total': (self.yaw_inertia
                                  + self.track_width ** 2
                                  * (self.wheel_mass + self.wheel_inertia
                                     / self.wheel_radius ** 2) / 2.0),
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)

    def omega_denominator(self, theta: float) -> float:
        """Ω(θ) = m_v J_θ − m_p² l² cos²θ, the determinant of the pitch/forward mass matrix."""
        c = math.cos(theta)
        return (self.effective_mass * self.pitch_inertia
                - (self.body_mass * self.com_height * c) ** 2)

    def replace(self, **overrides: float) -> 'ModelParams':
        """Return a copy with some fields changed; unknown names raise ``TypeError``."""
        return dataclasses.replace(self, **overrides)
