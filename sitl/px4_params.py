"""The PX4 personality's parameters: their specs, PX4's defaults, the store, the wire encoding.

``PARAM_REQUEST_READ`` / ``PARAM_REQUEST_LIST`` / ``PARAM_SET`` reach
:class:`Px4Params` through the face (``sitl.px4_face``); the autopilot
(``sitl.autopilot``) owns the store, follows the parameters it models and
refuses values it cannot fly.

Parameters and what the SITL does with them
-------------------------------------------
Defaults are PX4's parameter reference (the ``PARAM_DEFINE_*`` / ``module.yaml``
named beside each spec). Wired: ``COM_OF_LOSS_T`` (the offboard-loss timeout,
the same as ``sitl run --offboard-timeout``), ``COM_RC_LOSS_T``, ``NAV_RCL_ACT``
and ``COM_RCL_EXCEPT`` (``sitl.autopilot``), and ``MC_{ROLL,PITCH,YAW}RATE_K``
and ``_P`` (the rate loop's gain and its proportional term per axis,
``sitl.px4_control``), at boot and on ``PARAM_SET``;
``COM_OBL_RC_ACT`` / ``COM_OBL_ACT`` (the offboard-loss fallback, read when it
acts) and ``COM_RC_IN_MODE`` (whether a joystick is taken);
``MAV_SYS_ID`` / ``MAV_COMP_ID`` (the face's ids) and ``IMU_GYRO_RATEMAX``
(the fastest IMU stream the face accepts) at boot only, as PX4 needs a reboot
for them. Stored only: ``COM_RC_OVERRIDE``, ``NAV_DLL_ACT``,
``COM_DL_LOSS_T``, the ``MPC_*`` stick limits and hover thrust (PX4 v1.16's
defaults: what the companion's flight modes read), the ``RC_MAP_*`` channels
(the SITL radio sends AETR whatever they say), ``MAV_n_MODE`` / ``MAV_n_RATE`` (the SITL's UDP link
streams what is asked, as PX4 SITL's UDP instances, started with their own
rate, do).

The SITL airframe (:func:`px4_sitl_airframe`) sets at boot what a configured
vehicle would have: the radio calibration's ``RC_MAP_*`` (AETR: 1, 2, 3, 4;
PX4's default is 0, unassigned) and ``IMU_GYRO_RATEMAX`` at the simulated
IMU's rate (PX4's default is 400 Hz).

Wire encoding (MAVLink parameter protocol, "bytewise")
------------------------------------------------------
PX4 copies a parameter's four bytes into ``PARAM_VALUE.param_value``: an INT32
travels as its bit pattern read as a float32 (``param_type`` INT32), a FLOAT as
itself (REAL32) (``MavlinkParametersManager::send_param``). ``PARAM_SET`` is
decoded the same way, and only when its ``param_type`` matches the
parameter's (INT32 for INT32, REAL32 for FLOAT); otherwise PX4 logs "param
types mismatch" and neither stores nor answers (``mavlink_parameters.cpp``).
PX4 >= 1.13 says so in ``AUTOPILOT_VERSION.capabilities`` with
``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE`` (PX4 PR #19447, April 2022).
Integers whose bit patterns are float32 signalling NaNs
(2139095041..2143289343 and -8388607..-4194305) do not survive Python's
float conversion (pymavlink's too): none of these parameters takes such values.
"""

from __future__ import annotations

import math
import struct
import zlib

from sitl.personality import FirmwareVersion, ParamSpec, ParamStore

__all__ = [
    "PARAM_INT32",
    "PARAM_REAL32",
    "PARAM_UINT32",
    "PX4_DEFAULT_FIRMWARE",
    "Px4Params",
    "decode_bytewise",
    "encode_bytewise",
    "px4_param_specs",
    "px4_sitl_airframe",
]

PARAM_UINT32 = 5
"""``MAV_PARAM_TYPE_UINT32`` (the ``_HASH_CHECK`` pseudo-parameter)."""
PARAM_INT32 = 6
"""``MAV_PARAM_TYPE_INT32`` (PX4 ``PARAM_TYPE_INT32``)."""
PARAM_REAL32 = 9
"""``MAV_PARAM_TYPE_REAL32`` (PX4 ``PARAM_TYPE_FLOAT``)."""

PX4_DEFAULT_FIRMWARE = FirmwareVersion(1, 13, 3)
"""The last PX4 release that honours ``SET_ACTUATOR_CONTROL_TARGET`` (PX4 PR #20837
removed it for 1.14)."""

_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
_OBL_ACT_REMOVED = (1, 14)
"""PX4 1.14 dropped ``COM_OBL_ACT``: ``COM_OBL_RC_ACT`` acts with or without RC."""


def _i(name: str, default: int, lo: float, hi: float, doc: str) -> ParamSpec:
    return ParamSpec(name, default, PARAM_INT32, lo, hi, doc)


def _f(name: str, default: float, lo: float, hi: float, doc: str) -> ParamSpec:
    return ParamSpec(name, default, PARAM_REAL32, lo, hi, doc)


_PX4_SPECS: tuple[ParamSpec, ...] = (
    # commander_params.c
    _i("COM_DL_LOSS_T", 10, 5, 300, "s without GCS before NAV_DLL_ACT (stored only)"),
    _i("COM_OBL_RC_ACT", 0, 0, 7, "offboard loss: 0 Position ... 4 Land, 5 Hold, 7 Disarm"),
    _f("COM_OF_LOSS_T", 1.0, 0.0, 60.0, "s without offboard setpoints before failsafe"),
    _i("COM_RC_IN_MODE", 3, 0, 4, "0 RC only ... 3 RC or MAVLink, first kept; 4 none"),
    _f("COM_RC_LOSS_T", 0.5, 0.0, 35.0, "s without RC before it counts as lost"),
    _i("COM_RC_OVERRIDE", 1, 0, 3, "stick override: bit 0 auto modes, bit 1 offboard (stored)"),
    _i("COM_RCL_EXCEPT", 0, 0, 7, "RC loss ignored in: bit 0 mission, 1 hold, 2 offboard"),
    _i("NAV_DLL_ACT", 0, 0, 6, "GCS loss: 0 off, 1 Hold, 2 Return, 3 Land (stored only)"),
    _i("NAV_RCL_ACT", 2, 0, 6, "RC loss: 1 Hold, 2 Return, 3 Land, 5 Terminate, 6 Disarm"),
    # imu_gyro_parameters.c: the rate loop's gyro rate (reboot required).
    _i("IMU_GYRO_RATEMAX", 400, 100, 2000, "Hz, the fastest IMU stream (at boot)"),
    # mc_rate_control_params.c: the rate loop's global gain per axis, scaling its P, I
    # and D (followed at boot and on PARAM_SET, as the module's parameters_updated).
    _f("MC_PITCHRATE_K", 1.0, 0.01, 5.0, "pitch rate loop's global gain (P, I, D)"),
    _f("MC_PITCHRATE_P", 0.15, 0.01, 0.6, "pitch rate loop's proportional gain"),
    _f("MC_ROLLRATE_K", 1.0, 0.01, 5.0, "roll rate loop's global gain (P, I, D)"),
    _f("MC_ROLLRATE_P", 0.15, 0.01, 0.5, "roll rate loop's proportional gain"),
    _f("MC_YAWRATE_K", 1.0, 0.01, 5.0, "yaw rate loop's global gain (P, I, D)"),
    _f("MC_YAWRATE_P", 0.2, 0.0, 0.6, "yaw rate loop's proportional gain"),
    # mavlink_params.c (reboot required).
    _i("MAV_COMP_ID", 1, 1, 250, "this autopilot's component id (at boot)"),
    _i("MAV_SYS_ID", 1, 1, 250, "this vehicle's system id (at boot)"),
    # mavlink module.yaml: MAV_${i}_MODE default [0, 2, 0], MAV_${i}_RATE [1200, 0, 0].
    _i("MAV_0_MODE", 0, 0, 13, "instance 0 (TELEM1): 0 Normal (stored only)"),
    _i("MAV_0_RATE", 1200, 0, _INT32_MAX, "B/s, instance 0; 0: baud/20 (stored only)"),
    _i("MAV_1_MODE", 2, 0, 13, "instance 1 (TELEM2): 2 Onboard (stored only)"),
    _i("MAV_1_RATE", 0, 0, _INT32_MAX, "B/s, instance 1; 0: baud/20 (stored only)"),
    # mc_pos_control_params.c / flight_mode_manager (v1.16's defaults): what the
    # sticks may ask in Stabilized, Altitude and Position mode, and the hover thrust
    # (stored only: the companion's flight modes read them).
    _f("MPC_ACC_DOWN_MAX", 3.0, 2.0, 15.0, "m/s^2, climb rate controlled modes' fall"),
    _f("MPC_ACC_HOR", 3.0, 2.0, 15.0, "m/s^2, Position mode (x2 at full stick)"),
    _f("MPC_ACC_UP_MAX", 4.0, 2.0, 15.0, "m/s^2, climb rate controlled modes' rise"),
    _f("MPC_HOLD_DZ", 0.1, 0.0, 1.0, "stick deadzone of the piloted modes"),
    _f("MPC_JERK_AUTO", 4.0, 1.0, 80.0, "m/s^3, missions"),
    _f("MPC_JERK_MAX", 8.0, 0.5, 500.0, "m/s^3, Position/Altitude mode"),
    _f("MPC_MAN_TILT_MAX", 35.0, 1.0, 70.0, "deg, Stabilized and Altitude mode"),
    _i("MPC_POS_MODE", 4, 0, 4, "Position mode: 0 direct velocity, 4 acceleration based"),
    _f("MPC_THR_HOVER", 0.5, 0.1, 0.8, "thrust to hover (the estimator's prior)"),
    _f("MPC_TILTMAX_AIR", 45.0, 20.0, 89.0, "deg, velocity and acceleration modes"),
    _f("MPC_VEL_MANUAL", 10.0, 3.0, 20.0, "m/s, Position mode at full stick"),
    _f("MPC_XY_MAN_EXPO", 0.6, 0.0, 1.0, "Position mode's stick expo"),
    _f("MPC_Z_MAN_EXPO", 0.6, 0.0, 1.0, "throttle's expo (climb rate)"),
    _f("MPC_Z_VEL_MAX_DN", 1.5, 0.5, 4.0, "m/s, zero throttle's descent"),
    _f("MPC_Z_VEL_MAX_UP", 3.0, 0.5, 8.0, "m/s, full throttle's climb"),
    # rc_params.c: channel numbers, 0 unassigned (stored only).
    _i("RC_MAP_FLTMODE", 0, 0, 18, "flight-mode switch channel"),
    _i("RC_MAP_OFFB_SW", 0, 0, 18, "offboard switch channel"),
    _i("RC_MAP_PITCH", 0, 0, 18, "pitch channel"),
    _i("RC_MAP_ROLL", 0, 0, 18, "roll channel"),
    _i("RC_MAP_THROTTLE", 0, 0, 18, "throttle channel"),
    _i("RC_MAP_YAW", 0, 0, 18, "yaw channel"),
)

_COM_OBL_ACT = _i(
    "COM_OBL_ACT", 0, -1, 4, "offboard loss without RC: 0 Land, 1 Hold, 2 Return, 4 Lockdown"
)
"""PX4 <= 1.13 only (commander_params.c of those releases)."""


def px4_param_specs(firmware: FirmwareVersion = PX4_DEFAULT_FIRMWARE) -> tuple[ParamSpec, ...]:
    """The parameters of PX4 ``firmware`` the SITL has (``COM_OBL_ACT`` only before 1.14)."""
    if firmware.at_least(*_OBL_ACT_REMOVED):
        return _PX4_SPECS
    return (*_PX4_SPECS, _COM_OBL_ACT)


PX4_SITL_RC_MAP: tuple[tuple[str, float], ...] = (
    ("RC_MAP_ROLL", 1),
    ("RC_MAP_PITCH", 2),
    ("RC_MAP_THROTTLE", 3),
    ("RC_MAP_YAW", 4),
)
"""The SITL radio's calibration: AETR, ArduPilot's default channel order (``RCMAP_ROLL`` 1,
``RCMAP_PITCH`` 2, ``RCMAP_THROTTLE`` 3, ``RCMAP_YAW`` 4 in
``libraries/AP_RCMapper/AP_RCMapper.cpp``), as QGroundControl's radio setup would store
it (PX4's ``RC_MAP_*`` defaults are 0, unassigned)."""


def px4_sitl_airframe(imu_rate_hz: float) -> tuple[tuple[str, float], ...]:
    """What the SITL vehicle is configured with at boot, before ``--param``:
    :data:`PX4_SITL_RC_MAP` and ``IMU_GYRO_RATEMAX`` at the simulated IMU's rate."""
    return (*PX4_SITL_RC_MAP, ("IMU_GYRO_RATEMAX", round(imu_rate_hz)))


def encode_bytewise(value: float, param_type: int) -> float:
    """``PARAM_VALUE.param_value`` for ``value``: an INT32's (or UINT32's) bytes read
    as a float32; a REAL32 as itself."""
    if param_type == PARAM_INT32:
        return float(struct.unpack("<f", struct.pack("<i", int(value)))[0])
    if param_type == PARAM_UINT32:
        return float(struct.unpack("<f", struct.pack("<I", int(value)))[0])
    return value


def decode_bytewise(wire: float, param_type: int) -> float:
    """The value a bytewise ``param_value`` carries (inverse of :func:`encode_bytewise`)."""
    if param_type == PARAM_INT32:
        return float(struct.unpack("<i", struct.pack("<f", wire))[0])
    if param_type == PARAM_UINT32:
        return float(struct.unpack("<I", struct.pack("<f", wire))[0])
    return wire


class Px4Params(ParamStore):
    """PX4-style parameter store: INT32 kept as an int32, FLOAT as a float32.

    Parameters
    ----------
    firmware
        The PX4 version shown: which parameters exist (:func:`px4_param_specs`).

    Notes
    -----
    A value is stored as PX4's ``param_set`` would: an INT32 truncated to an
    integer (what ``param set NAME 2.7`` gives), a FLOAT rounded to float32.
    The documented range is not enforced (PX4 does not either); values the
    SITL cannot fly are refused by the autopilot's checks.
    """

    def __init__(self, firmware: FirmwareVersion = PX4_DEFAULT_FIRMWARE) -> None:
        self.firmware = firmware
        super().__init__(px4_param_specs(firmware))

    def _coerce(self, spec: ParamSpec, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError(f"{spec.name}: expected a finite value, got {value!r}")
        if spec.param_type == PARAM_INT32:
            if not _INT32_MIN <= value <= _INT32_MAX:
                raise ValueError(f"{spec.name}: {value:g} does not fit an int32")
            return float(int(value))
        return float(struct.unpack("<f", struct.pack("<f", value))[0])

    def hash_check(self) -> int:
        """The ``_HASH_CHECK`` value: a CRC-32 over every name and value, as PX4's
        ``param_hash_check`` (not bit-identical to PX4's)."""
        crc = 0
        for spec in self.specs:
            value = self[spec.name]
            raw = (
                struct.pack("<i", int(value))
                if spec.param_type == PARAM_INT32
                else struct.pack("<f", value)
            )
            crc = zlib.crc32(spec.name.encode() + raw, crc)
        return crc
