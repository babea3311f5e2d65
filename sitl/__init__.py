"""Bundled software-in-the-loop plant: multirotor physics, IMU and wind."""

from sitl.batch import BatchQuadrotor
from sitl.imu import Imu, ImuSample
from sitl.physics import Quadrotor, VehicleState
from sitl.wind import Wind, WindConfig

__all__ = [
    "BatchQuadrotor",
    "Imu",
    "ImuSample",
    "Quadrotor",
    "VehicleState",
    "Wind",
    "WindConfig",
]
