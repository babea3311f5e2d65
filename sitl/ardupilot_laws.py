"""ArduCopter's flight laws: what each mode makes of the sticks and targets, to the motors.

The per-mode laws of :class:`sitl.ardupilot.ArduCopter` (which derives from
:class:`CopterLaws`): the pilot's stick maps, angle and yaw hold, the
climb-rate loop, the guided targets' thrust, and the output stage (rate PID,
mixer, thrust curve, ``MOT_SPIN_*``). Which mode, which target, arming and the
failsafes are :class:`~sitl.ardupilot.ArduCopter`'s; the rules are in
:mod:`sitl.ardupilot`'s docstring.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from sitl.ardupilot_config import ArduCopterConfig
from sitl.ardupilot_control import ApRatePid, AttitudeControl, MotorsMatrix, thrust_to_actuator
from sitl.ardupilot_modes import CopterMode
from sitl.ardupilot_params import ArduParams
from sitl.frames import euler_to_quat
from sitl.personality import Personality, clip, stick_unit, throttle_unit

__all__ = ["AngleTarget", "CopterLaws"]


@dataclass
class AngleTarget:
    """A guided SET_ATTITUDE_TARGET as taken: body rates and climb rate or thrust."""

    t_s: float
    rates_rad_s: tuple[float, float, float]
    value: float  # climb rate (m/s, up) or thrust [0, 1]
    use_thrust: bool


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class CopterLaws(Personality[CopterMode]):
    """ArduCopter's per-mode flight laws and output stage (see the module docs).

    State read here is set by :class:`~sitl.ardupilot.ArduCopter`.
    """

    config: ArduCopterConfig
    params: ArduParams
    rate_pid: ApRatePid
    attitude: AttitudeControl
    motors_matrix: MotorsMatrix
    loop_dt_s: float
    hover_throttle: float
    rate_target_rad_s: tuple[float, float, float]
    _target: AngleTarget | None
    _timed_out: bool
    _yaw_hold: float | None
    _limit: list[bool]

    def _run(
        self,
        t_s: float,
        gyro: Sequence[float],
        euler: Sequence[float],
        climb_rate_m_s: float,
        sticks_us: Sequence[int] | None,
    ) -> tuple[float, ...]:
        cfg = self.config
        dt = self.loop_dt_s
        mode = self.mode
        if sticks_us is None or len(sticks_us) < 4:
            # No RC: the pilot's inputs read zero (Mode::get_pilot_desired_*): level,
            # no yaw rate, no climb; a manual throttle reads zero.
            rs, ps, ys = 0.0, 0.0, 0.0
            thr_stick = 0.5 if mode in (CopterMode.ALT_HOLD, CopterMode.LOITER) else 0.0
        else:
            rs, ps = stick_unit(sticks_us[0]), stick_unit(sticks_us[1])
            thr_stick, ys = throttle_unit(sticks_us[2]), stick_unit(sticks_us[3])
        cos_tilt = math.cos(euler[0]) * math.cos(euler[1])
        body_q = euler_to_quat(euler[0], euler[1], euler[2])

        rates: tuple[float, float, float]
        if mode == CopterMode.ACRO:
            rm = cfg.acro_rate_max_rad_s
            # ModeAcro::run: input_rate_bf_roll_pitch_yaw, as GUIDED's body rates.
            rates = self.attitude.input_rate_bf(
                (rs * rm[0], ps * rm[1], ys * rm[2]), body_q, gyro, dt
            )
            return self._output(dt, rates, gyro, self._manual_throttle(thr_stick), cos_tilt, False)
        # Modes below fly angles here; the body-rate attitude target follows the vehicle
        # so that GUIDED and ACRO start from where it is.
        if mode not in (CopterMode.GUIDED, CopterMode.GUIDED_NOGPS) or (
            self._target is None or self._timed_out
        ):
            self.attitude.relax(body_q, gyro)
        if mode == CopterMode.BRAKE:
            rates = self._level_rates(euler, 0.0, 0.0, None)
            if self.landed:
                return self._ground_idle()
            thrust = self._climb_loop(dt, 0.0, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        if mode in (CopterMode.STABILIZE, CopterMode.ALT_HOLD, CopterMode.LOITER):
            amax = cfg.angle_max_rad
            rates = self._level_rates(euler, rs * amax, ps * amax, ys * cfg.pilot_yaw_rate_rad_s)
            if mode == CopterMode.STABILIZE:
                thrust = self._manual_throttle(thr_stick)
                return self._output(dt, rates, gyro, thrust, cos_tilt, False)
            climb_sp = self._pilot_climb_rate(thr_stick)
            if self.landed and climb_sp <= 0.0:
                return self._ground_idle()
            thrust = self._climb_loop(dt, climb_sp, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        if mode in (CopterMode.LAND, CopterMode.RTL):
            # RTL (the radio failsafe's action) flies as LAND: no navigation here.
            if self.landed and not cfg.test_stand:
                self.disarm(t_s, reason="landed")
                return self.motors
            rates = self._level_rates(euler, 0.0, 0.0, 0.0)
            climb_sp = -self.params["LAND_SPEED"] * 0.01
            thrust = self._climb_loop(dt, climb_sp, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        # GUIDED / GUIDED_NOGPS
        tgt = self._target
        if tgt is None or self._timed_out:
            rates = self._level_rates(euler, 0.0, 0.0, None)
            if self.landed:
                return self._ground_idle()
            thrust = self._climb_loop(dt, 0.0, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        self._yaw_hold = None
        positive = tgt.value > 0.0
        if self.landed and not positive:
            return self._ground_idle()
        if tgt.use_thrust:
            # set_throttle_out(thrust, apply_angle_boost=true)
            inverted = clip(10.0 * cos_tilt, 0.0, 1.0)
            boost = 1.0 / clip(cos_tilt, 0.1, 1.0)
            thrust = clip(tgt.value * inverted * boost, 0.0, 1.0)
        else:
            thrust = self._climb_loop(dt, tgt.value, climb_rate_m_s, cos_tilt)
        # ModeGuided::angle_control_run -> input_rate_bf_roll_pitch_yaw: the rates are
        # shaped, integrated into the attitude target, and its error corrected.
        rates = self.attitude.input_rate_bf(tgt.rates_rad_s, body_q, gyro, dt)
        return self._output(dt, rates, gyro, thrust, cos_tilt, not tgt.use_thrust)

    def _manual_throttle(self, stick: float) -> float:
        """``Mode::get_pilot_desired_throttle``: mid stick = hover throttle (expo curve)."""
        mid = self.hover_throttle
        expo = clip(-(mid - 0.5) / 0.375, -0.5, 1.0)
        return stick * (1.0 - expo) + expo * stick**3

    def _pilot_climb_rate(self, stick: float) -> float:
        """ALT_HOLD throttle stick: 10 % dead zone around mid, full stick = PILOT_SPEED_UP."""
        dz = 0.05
        v = self.config.pilot_speed_m_s
        if stick > 0.5 + dz:
            return v * (stick - 0.5 - dz) / (0.5 - dz)
        if stick < 0.5 - dz:
            return v * (stick - 0.5 + dz) / (0.5 - dz)
        return 0.0

    def _level_rates(
        self,
        euler: Sequence[float],
        roll_sp: float,
        pitch_sp: float,
        yaw_rate_sp: float | None,
    ) -> tuple[float, float, float]:
        kp = self.config.angle_p
        if yaw_rate_sp is None:
            if self._yaw_hold is None:
                self._yaw_hold = euler[2]
            r = kp[2] * _wrap_pi(self._yaw_hold - euler[2])
        else:
            r = yaw_rate_sp
        return (kp[0] * (roll_sp - euler[0]), kp[1] * (pitch_sp - euler[1]), r)

    def _climb_loop(self, dt: float, climb_sp: float, climb: float, cos_tilt: float) -> float:
        cfg = self.config
        err = climb_sp - climb
        self._climb_integral = clip(self._climb_integral + err * dt, -3.0, 3.0)
        thrust = self.hover_throttle + cfg.climb_p * err + cfg.climb_i * self._climb_integral
        return clip(thrust / max(cos_tilt, 0.5), 0.0, 1.0)

    def _ground_idle(self) -> tuple[float, ...]:
        """Armed, landed, no climb request: motors at MOT_SPIN_ARM, controllers relaxed."""
        self.rate_pid.reset()
        self._climb_integral = 0.0
        self.last_torque_thrust = (0.0, 0.0, 0.0, 0.0)
        self.motors = (self.params["MOT_SPIN_ARM"],) * self.n_motors
        return self.motors

    def _output(
        self,
        dt: float,
        rates_sp: Sequence[float],
        gyro: Sequence[float],
        thrust: float,
        cos_tilt: float,
        auto_throttle: bool,
    ) -> tuple[float, ...]:
        if self.landed and thrust < self.hover_throttle * 0.5:
            self.rate_pid.reset_integrator()  # ArduPilot relaxes the I terms on the ground
        self.rate_target_rad_s = (rates_sp[0], rates_sp[1], rates_sp[2])
        tq = self.rate_pid.update(dt, rates_sp, gyro, self._limit)
        roll, pitch, yaw = (v if math.isfinite(v) else 0.0 for v in tq)
        thrust = thrust if math.isfinite(thrust) else 0.0
        self.last_torque_thrust = (roll, pitch, yaw, thrust)
        p = self.params
        # Throttle-to-attitude mix (AC_AttitudeControl_Multi::get_throttle_avg_max):
        # ATC_THR_MIX_MAX in the air under an altitude controller, ATC_THR_MIX_MAN with
        # a manual throttle, ATC_THR_MIX_MIN on the ground.
        if self.landed:
            mix = p["ATC_THR_MIX_MIN"]
        elif auto_throttle:
            mix = p["ATC_THR_MIX_MAX"]
        else:
            mix = p["ATC_THR_MIX_MAN"]
        avg_max = max(thrust, thrust * max(0.0, 1.0 - mix) + self.hover_throttle * mix)
        res = self.motors_matrix.output_armed_stabilizing(roll, pitch, yaw, thrust, avg_max)
        self._limit = list(res.limit)
        lo, hi, expo = p["MOT_SPIN_MIN"], p["MOT_SPIN_MAX"], p["MOT_THST_EXPO"]
        span = hi - lo
        self.motors = tuple(lo + span * thrust_to_actuator(m, expo) for m in res.thrust)
        return self.motors
