"""sitl/linalg.py: what the simulation derives from a vehicle's geometry is the
same, bit for bit, whatever CPU kernel numpy's LAPACK would have picked."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sitl.linalg import inverse, pseudo_inverse

ROOT = Path(__file__).resolve().parents[2]

_DERIVED = """
import glob
from companion.profile import load_profile
from sitl.px4_control import ControlAllocator
from sitl.vehicle_params import VehicleParams
for f in sorted(glob.glob("vehicle_profiles/*.yaml")):
    p = load_profile(f)
    a = ControlAllocator.from_profile(p)
    print(f, a._roll, a._pitch, a._yaw, a._thrust_z, tuple(a._scale.tolist()),
          VehicleParams.from_profile(p).inertia_inv)
"""

# OpenBLAS's kernels any x86-64 machine of the last decade runs; under these,
# np.linalg.pinv gave three different allocators for the same F450.
_KERNELS = ("Prescott", "Sandybridge", "Haswell") if platform.machine() == "x86_64" else ()


def _derived(kernel: str | None) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    if kernel is not None:
        env["OPENBLAS_CORETYPE"] = kernel
    out = subprocess.run(
        [sys.executable, "-c", _DERIVED], cwd=ROOT, env=env, capture_output=True, text=True,
        check=True, timeout=120,
    )  # fmt: skip
    return out.stdout


@pytest.mark.parametrize("kernel", _KERNELS)
def test_the_allocator_and_the_inertia_do_not_depend_on_the_blas_kernel(kernel: str) -> None:
    assert _derived(kernel) == _derived(None)


def test_the_inverse_and_pseudo_inverse_are_those_of_numpy_to_rounding() -> None:
    rng = np.random.default_rng(7)
    a = rng.normal(size=(4, 4)) + 4.0 * np.eye(4)
    np.testing.assert_allclose(np.array(inverse(a.tolist())), np.linalg.inv(a), rtol=1e-12)
    eff = np.zeros((6, 6))
    eff[[0, 1, 2, 5]] = rng.normal(size=(4, 6))  # two rows zero, as a multirotor's
    np.testing.assert_allclose(
        np.array(pseudo_inverse(eff.tolist())), np.linalg.pinv(eff), rtol=1e-9, atol=1e-12
    )


def test_a_singular_matrix_is_refused() -> None:
    with pytest.raises(ValueError, match="singular"):
        inverse([[1.0, 2.0], [2.0, 4.0]])
    with pytest.raises(ValueError, match="square"):
        inverse([[1.0, 2.0]])
