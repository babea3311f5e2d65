"""Re-run a rate controller offline on a recorded control log.

A control log (:class:`companion.records.ControlLog`, in the
:func:`companion.records.columns` layout) holds, for every control
sample, what the controller was given (``t_s``, ``meas_*_rad_s``,
``ref_*_rad_s``, ``thrust``) and what it produced. :func:`replay` feeds the
inputs to a fresh controller, sample by sample, exactly as the live loop did;
:func:`compare` tells how far the outputs moved. The same configuration
reproduces the recorded outputs to rounding (the laws are deterministic);
another configuration shows what it would have commanded on the same
measurements (open loop: the vehicle's response to the new commands is not
simulated).

Conventions, matching the live loop and :func:`sitl.lab.simulate.simulate_flight`:

* ``dt`` is the difference of consecutive ``t_s`` in whole microseconds, as the
  flight core takes it; the first row, and the first
  engaged row after disengaged ones, get ``dt = 0`` (the controller clamps it
  to ``dt_min_s`` and primes its filters).
* Rows with ``engaged == 0``: the controller was not flying then; it is reset
  there and its outputs are NaN. :func:`compare` ignores those rows.
* ``on_ground`` (when the log has it) is given to the controller every row, as
  the autopilot's landed state was live: nothing is learnt while it is 1.
* Rates output to an autopilot that shapes its setpoints
  (:mod:`companion.control.shaping`): where the log's ``law_ref_*`` columns
  hold a reference, the law is given it instead of the pilot's, and taught the
  correction the recorded setpoint (``sent_*``) carried, as it was live; that
  needs the log's ``rates_full_scale_deg_s`` (``meta``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES
from companion.flight_modes import FLIGHT_MODES
from companion.records import read_control_log
from companion.step import law_axes_named, law_share, whole_us

__all__ = ["OUTPUT_PREFIXES", "compare", "output_columns", "replay"]

OUTPUT_PREFIXES = ("err", "f_hat", "u", "torque", "sat")
_JUMP_S = 1.0
"""A step between two rows beyond this is a new clock: the law starts over."""
_AXIS_OUT = (("err", "err_{}_rad_s"), ("f_hat", "f_hat_{}"), ("u", "u_{}"),
             ("torque", "torque_{}"), ("sat", "sat_{}"))  # fmt: skip


def output_columns(n_motors: int) -> list[str]:
    """Names of the controller-output columns :func:`replay` produces."""
    cols = [pat.format(a) for a in AXES for _, pat in _AXIS_OUT]
    return [*cols, "held", "thrust_out", *(f"motor_{i}" for i in range(1, n_motors + 1))]


def _load_inputs(
    log_path: str | Path | Mapping[str, np.ndarray],
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    if isinstance(log_path, Mapping):
        return {k: np.asarray(v, dtype=np.float64) for k, v in log_path.items()}, {}
    return read_control_log(log_path)


def replay(
    log_path: str | Path | Mapping[str, np.ndarray],
    controller_cfg: Any,
    profile: Any,
    *,
    rate_source: str = "meas",
    meta: Mapping[str, str] | None = None,
) -> dict[str, np.ndarray]:
    """Re-run a controller on a recorded log.

    Parameters
    ----------
    log_path
        A control log file, or its columns as returned by
        :func:`companion.records.read_control_log`.
    controller_cfg
        A controller configuration (:class:`companion.config.MfcConfig` or
        ``PidConfig``), or the path of a controller file.
    profile
        The vehicle profile whose geometry makes the mixer
        (:class:`companion.profile.VehicleProfile`), or its file's path.
    rate_source
        Prefix of the measured-rate columns fed to the controller:
        ``"meas"`` uses ``meas_<axis>_rad_s``. A log with other rate columns
        (e.g. a simulation's ``true_<axis>_rad_s``) can be replayed on those.
    meta
        The log's metadata (read from the file when ``log_path`` is one): its
        ``rates_full_scale_deg_s`` teaches a shaped flight's law as it was taught;
        its ``mode`` says whether yaw was offered a share of roll and pitch.

    Returns
    -------
    dict
        ``t_s`` and ``engaged`` (copied, for alignment) and the output columns
        of :func:`output_columns` for the profile's motor count
        (``err_<axis>_rad_s``, ``f_hat_<axis>``, ``u_<axis>``,
        ``torque_<axis>``, ``sat_<axis>``, ``held``, ``thrust_out``,
        ``motor_<i>``); NaN in disengaged rows.

    Raises
    ------
    ValueError
        If the log lacks a column replay needs.
    """
    from companion.config import build_controller, load_controller
    from companion.profile import load_profile

    cfg = (
        load_controller(controller_cfg)
        if isinstance(controller_cfg, str | Path)
        else (controller_cfg)
    )
    prof = load_profile(profile) if isinstance(profile, str | Path) else profile
    cols, file_meta = _load_inputs(log_path)
    meta = dict(meta) if meta is not None else file_meta
    rate_cols = [f"{rate_source}_{a}_rad_s" for a in AXES]
    need = ["t_s", *rate_cols, *(f"ref_{a}_rad_s" for a in AXES), "thrust"]
    missing = [c for c in need if c not in cols]
    if missing:
        where = log_path if not isinstance(log_path, Mapping) else "the given columns"
        raise ValueError(f"{where}: cannot replay, missing columns {missing}")
    n = len(cols["t_s"])
    engaged = cols["engaged"] if "engaged" in cols else np.ones(n)
    ground = (cols["on_ground"] != 0.0).tolist() if "on_ground" in cols else [False] * n
    controller = build_controller(cfg, prof)
    # As the run's flight core fitted it (a log without its mode predates the
    # yaw share: flown as rates, which offers none).
    FLIGHT_MODES.get(meta.get("mode", "rates"), FLIGHT_MODES["rates"]).fit(controller)
    n_motors = controller.mixer.n_motors
    names = output_columns(n_motors)
    out = np.full((n, len(names)), np.nan)

    # Python floats, not numpy scalars: the same arithmetic as the live loop.
    t = cols["t_s"].tolist()
    w = [cols[c].tolist() for c in rate_cols]
    r = [cols[f"ref_{a}_rad_s"].tolist() for a in AXES]
    thrust = cols["thrust"].tolist()
    eng = (engaged != 0.0).tolist()
    shaped = _shaped_reference(cols, meta, n)
    law_axes = _law_axes(meta, cols)
    # As live: the law is taught what it sent only on a sample whose command left.
    sent_roll = cols["sent_roll_rad_s"].tolist() if law_axes is not None else []
    update = controller.update
    learn = controller.learn
    fresh = True
    prev_t = 0.0
    for i in range(n):
        if not eng[i]:
            if not fresh:
                controller.reset()
                fresh = True
            continue
        step = t[i] - prev_t
        # As the core takes it (companion.imu_time): in whole microseconds; a jump
        # beyond a second starts over.
        dt = 0.0 if fresh or step > _JUMP_S else whole_us(step)
        fresh = False
        prev_t = t[i]
        controller.on_ground = ground[i]
        ref = (r[0][i], r[1][i], r[2][i])
        taught: tuple[float, float, float] | None = None
        if shaped is not None and shaped[0][0][i] == shaped[0][0][i]:  # a shaped row
            (l0, l1, l2), (s0, s1, s2), fs = shaped
            ref = (l0[i], l1[i], l2[i])
            if fs is not None and s0[i] == s0[i] and s1[i] == s1[i] and s2[i] == s2[i]:
                taught = (
                    _unit((s0[i] - ref[0]) / fs[0]),
                    _unit((s1[i] - ref[1]) / fs[1]),
                    _unit((s2[i] - ref[2]) / fs[2]),
                )
        o = update(dt, (w[0][i], w[1][i], w[2][i]), ref, thrust[i])
        if taught is None and law_axes is not None and sent_roll[i] == sent_roll[i]:
            taught = law_share(o.torque, law_axes)
        if taught is not None:
            controller.teach_applied(taught)
        learn()
        row = out[i]
        k = 0
        for ax in range(3):
            row[k] = o.error[ax]
            row[k + 1] = o.f_hat[ax]
            row[k + 2] = o.u[ax]
            row[k + 3] = o.torque[ax]
            row[k + 4] = o.saturated_axes[ax]
            k += 5
        row[k] = o.held
        row[k + 1] = o.thrust
        row[k + 2 : k + 2 + n_motors] = o.motors
    result: dict[str, np.ndarray] = {"t_s": np.asarray(cols["t_s"]), "engaged": engaged}
    for j, name in enumerate(names):
        result[name] = np.ascontiguousarray(out[:, j])
    return result


def _unit(x: float) -> float:
    return 1.0 if x > 1.0 else -1.0 if x < -1.0 else x


def _law_axes(
    meta: Mapping[str, str], cols: Mapping[str, np.ndarray]
) -> tuple[bool, bool, bool] | None:
    """The axes the law corrected in a rates flight (``--rates-law-axes``), or None
    where it was taught nothing or corrected all three.

    Raises
    ------
    ValueError
        For a log that sent rates but does not say which axes auto chose.
    """
    named = meta.get("rates_law_axes")
    if named is None or meta.get("output") != "rates" or meta.get("rates_passthrough") == "True":
        return None  # (a log without it predates the option: all three)
    if named == "auto":
        sent = cols.get("sent_roll_rad_s")
        if sent is not None and bool(np.isfinite(sent).any()):
            raise ValueError(
                "cannot replay: the log sent rates with --rates-law-axes auto but holds "
                "no record of the axes chosen (the control log's companion.learnt metadata)"
            )
        return None  # never chosen: the run sent nothing
    on = law_axes_named(named)
    return None if all(on) else on


def _shaped_reference(
    cols: Mapping[str, np.ndarray], meta: Mapping[str, str], n: int
) -> tuple[list[list[float]], list[list[float]], tuple[float, float, float] | None] | None:
    """The law's shaped reference, the setpoints sent and the full scale (rad/s; None
    in pass-through, where the law is taught nothing), or None when the log holds
    no shaped reference."""
    names = [f"law_ref_{a}_rad_s" for a in AXES]
    sent = [f"sent_{a}_rad_s" for a in AXES]
    if meta.get("output") != "rates" or not all(c in cols for c in (*names, *sent)):
        return None  # only rates output shapes the law's reference
    law = [np.asarray(cols[c], dtype=np.float64) for c in names]
    if not np.isfinite(law[0]).any():
        return None
    taught = None
    if meta.get("rates_passthrough") != "True":  # pass-through: nothing the law asked was sent
        fs_deg = meta.get("rates_full_scale_deg_s")
        if fs_deg is None:
            raise ValueError(
                "the log holds a shaped reference (law_ref_*) but no rates_full_scale_deg_s "
                "in its metadata: cannot teach the law as it was taught"
            )
        fs = math.radians(float(fs_deg))
        taught = (fs, fs, fs)
    return [a.tolist() for a in law], [cols[c].tolist() for c in sent], taught


def compare(
    recorded: Mapping[str, np.ndarray], replayed: Mapping[str, np.ndarray]
) -> dict[str, float]:
    """Largest absolute difference per output column present in both.

    Only engaged rows count (``replayed["engaged"]``, else ``recorded["engaged"]``,
    else all rows). Two NaNs at the same place agree; a NaN against a number
    is an infinite difference. A column with no engaged rows gives 0.0.

    Raises
    ------
    ValueError
        If the two have different row counts.
    """
    skip = {"t_s", "engaged", "wall_s", "latency_us"}
    names = [k for k in replayed if k in recorded and k not in skip]
    n = None
    for k in names:
        a = np.asarray(recorded[k], dtype=np.float64)
        if n is None:
            n = len(a)
        if len(a) != len(replayed[k]):
            raise ValueError(f"column {k}: {len(a)} recorded rows, {len(replayed[k])} replayed")
    eng = replayed.get("engaged", recorded.get("engaged"))
    mask = np.ones(n or 0, dtype=bool) if eng is None else np.asarray(eng, dtype=np.float64) != 0.0
    diffs: dict[str, float] = {}
    for k in names:
        a = np.asarray(recorded[k], dtype=np.float64)[mask]
        b = np.asarray(replayed[k], dtype=np.float64)[mask]
        if a.size == 0:
            diffs[k] = 0.0
            continue
        na, nb = np.isnan(a), np.isnan(b)
        d = np.abs(a - b)
        d[na & nb] = 0.0
        d[na ^ nb] = np.inf
        diffs[k] = float(d.max())
    return diffs
