"""Wheel-ground contact of the plants that model it (``plant: {model: mujoco}``).

The equation plants ('paper', 'full') assume rolling without slip on flat ground and take
no contact parameters; a scenario that sets ``plant.contact`` with them is rejected.
Declared here, not beside the MuJoCo plant (wip_sim), because the scenario file is
validated in wip_control, which imports no simulator package.

Defaults: a rubber wheel on dry concrete. Sliding friction of rubber on dry concrete is
0.6-0.85 (engineering handbooks), 0.8 is taken; the rolling resistance coefficient of a
pneumatic or solid rubber tyre on concrete is 0.010-0.015, 0.01 is taken.
"""

from __future__ import annotations

import dataclasses

from wip_runtime.config import ParamError, param


@dataclasses.dataclass(frozen=True)
class ContactParams:
    """Friction of the wheel-ground contact (Coulomb cone and rolling resistance)."""

    friction: float = param(
        0.8, '1', 'sliding friction coefficient mu of the wheel-ground contact: the ground '
        'force along it is at most mu times the normal force '
        '(docs/decisions/sim-parameters.md)', minimum=0.0,
        maximum=2.0, exclusive_minimum=True)
    rolling_resistance: float = param(
        0.01, '1', 'rolling resistance coefficient c_rr: a torque c_rr r N opposes each '
        "wheel's rolling (N its normal force, r its radius); rubber tyre on concrete "
        '0.010-0.015, 0 = lossless rolling', minimum=0.0, maximum=0.2)


@dataclasses.dataclass(frozen=True)
class TerrainParams:
    """Ground along the map's x axis (east), across the whole width.

    A slope that starts at ``slope_start``, a bump whose crest is at ``bump_position``, a
    step up at ``step_position`` and a patch
    of other friction between ``patch_start`` and ``patch_end`` (and, to put it under one
    wheel only, between ``patch_y_min`` and ``patch_y_max``). Defaults: flat, one friction.
    """

    slope_start: float = param(0.0, 'm', 'x where an uphill slope starts (map frame; the '
                               'ground rises for x > slope_start)', minimum=-1e4, maximum=1e4)
    slope_grade: float = param(0.0, '1', 'rise over run of the slope (0.05 = 5 %); 0 = flat',
                               minimum=0.0, maximum=0.3)
    bump_position: float = param(0.0, 'm', 'x of the crest of a bump across the ground',
                                 minimum=-1e4, maximum=1e4)
    bump_height: float = param(0.0, 'm', 'height of the bump (a circular arc across x); '
                               '0 = no bump', minimum=0.0, maximum=0.2)
    bump_length: float = param(0.2, 'm', 'length of the bump along x where it meets the '
                               'ground', minimum=0.0, maximum=5.0, exclusive_minimum=True)
    step_position: float = param(0.0, 'm', 'x of the edge of a kerb-like step up (the ground '
                                 'is step_height higher beyond it)', minimum=-1e4, maximum=1e4)
    step_height: float = param(0.0, 'm', 'height of the step up; 0 = no step', minimum=0.0,
                               maximum=0.2)
    patch_start: float = param(0.0, 'm', 'x where a patch of other friction starts (on the '
                               'flat ground, across the whole width)', minimum=-1e4,
                               maximum=1e4)
    patch_end: float = param(0.0, 'm', 'x where the patch ends; equal to patch_start = no '
                             'patch', minimum=-1e4, maximum=1e4)
    patch_friction: float = param(0.3, '1', 'sliding friction coefficient on the patch '
                                  '(wet polished concrete or packed snow about 0.3, ice '
                                  '0.1)', minimum=0.0, maximum=2.0, exclusive_minimum=True)
    patch_y_min: float = param(-1e4, 'm', 'y where the patch starts across the path (map '
                               'frame; 0 with a path along y = 0: under the left wheel only)',
                               minimum=-1e4, maximum=1e4)
    patch_y_max: float = param(1e4, 'm', 'y where the patch ends across the path',
                               minimum=-1e4, maximum=1e4)

    def validate(self) -> None:
        if self.patch_end < self.patch_start:
            raise ParamError(f'patch_end: must be >= patch_start = {self.patch_start}, '
                              f'got {self.patch_end}')
        if self.patch_y_max <= self.patch_y_min:
            raise ParamError(f'patch_y_max: must be > patch_y_min = {self.patch_y_min}, '
                              f'got {self.patch_y_max}')

    @property
    def has_patch(self) -> bool:
        return self.patch_end > self.patch_start
