"""What differs between flight stacks, in one place.

The companion recognises the stack from the autopilot's HEARTBEAT
(``autopilot`` 12 = PX4, 3 = ArduPilot) and takes from here: which mode it
engages in, how it knows it is engaged, which modes it can hand back to, which
IMU message carries body rates, and whether the stack accepts actuator
setpoints at all.

=========================  ===========================  ==================================
                           PX4                          ArduPilot Copter
=========================  ===========================  ==================================
engage mode                OFFBOARD (main 6), after     GUIDED_NOGPS (20), then arm
                           setpoints stream, then arm
engaged when               main mode 6 and armed        custom mode 20 and armed
safe modes (hand-back)     posctl (3), altctl (2),      alt_hold (2), land (9),
                           stabilized (7), manual (1)   stabilize (0), loiter (5)
default safe mode          posctl                       alt_hold
IMU message                HIGHRES_IMU (rad/s)          ATTITUDE (rad/s body rates)
actuator setpoints         yes (<= 1.13, bundled SITL)  no: body rates only
thrust (rates output)      normalised collective        climb rate unless GUID_OPTIONS
                                                        bit 3: checked at start-up
=========================  ===========================  ==================================
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["ARDUPILOT", "PX4", "FlightStack", "stack_for"]


@dataclass(frozen=True)
class FlightStack:
    """One flight stack's dialect."""

    name: str
    autopilot_id: int
    engage_mode: tuple[float, float]
    """DO_SET_MODE param2, param3 that engage the companion."""
    safe_modes: dict[str, tuple[float, float]] = field(default_factory=dict)
    default_safe_mode: str = ""
    imu_message: str = "highres_imu"
    supports_actuator_output: bool = False
    max_imu_rate_hz: float = 1000.0
    """The fastest IMU stream worth asking for; the stack may still deny it."""

    def is_engage_mode(self, custom_mode: int) -> bool:
        if self.name == "px4":
            return ((custom_mode >> 16) & 0xFF) == int(self.engage_mode[0])
        return custom_mode == int(self.engage_mode[0])

    def mode_params(self, name: str) -> tuple[float, float]:
        """DO_SET_MODE param2, param3 of a safe mode by name.

        Raises
        ------
        ValueError
            Naming the stack and the modes it has, for an unknown name.
        """
        try:
            return self.safe_modes[name]
        except KeyError:
            raise ValueError(
                f"{self.name} has no safe mode {name!r}: expected one of "
                f"{', '.join(sorted(self.safe_modes))}"
            ) from None


PX4 = FlightStack(
    name="px4",
    autopilot_id=12,
    engage_mode=(6.0, 0.0),
    safe_modes={
        "posctl": (3.0, 0.0),
        "altctl": (2.0, 0.0),
        "stabilized": (7.0, 0.0),
        "manual": (1.0, 0.0),
    },
    default_safe_mode="posctl",
    imu_message="highres_imu",
    supports_actuator_output=True,
    max_imu_rate_hz=1000.0,
)

ARDUPILOT = FlightStack(
    name="ardupilot",
    autopilot_id=3,
    engage_mode=(20.0, 0.0),
    safe_modes={
        "alt_hold": (2.0, 0.0),
        "land": (9.0, 0.0),
        "stabilize": (0.0, 0.0),
        "loiter": (5.0, 0.0),
    },
    default_safe_mode="alt_hold",
    imu_message="attitude",
    supports_actuator_output=False,
    # ArduPilot denies intervals shorter than its loop period / 0.8 (~333 Hz at 400 Hz).
    max_imu_rate_hz=400.0,
)

_BY_ID = {PX4.autopilot_id: PX4, ARDUPILOT.autopilot_id: ARDUPILOT}


def stack_for(autopilot_id: int) -> FlightStack | None:
    """The dialect for a HEARTBEAT ``autopilot`` value, or None if unsupported."""
    return _BY_ID.get(int(autopilot_id))
