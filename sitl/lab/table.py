"""A campaign's flights as one table: ``flights.parquet``, one row per flight.

The schema (:data:`FLIGHTS_SCHEMA`; docs/campaigns.md has the same table). Every
column but the spec's and ``flight_id`` may be null: a flight that raised has its
``error`` and nulls where it has no figures.

======================== ========= ==============================================
column                   type      meaning
======================== ========= ==============================================
profile                  string    the profile's name (file stem)
damage                   float64   motor 1 thrust/torque efficiency factor
gust_sigma_m_s           float64   wind gust sigma, m/s
seed                     int64     the flight's seed
controller               string    the controller's name (file stem)
controller_kind          string    ``mfc`` or ``pid``
scenario                 string    the scenario's name
duration_s               float64   flown scenario length, s
flight_id                string    digest of the spec (:mod:`sitl.lab.campaign_store`)
mae_roll_deg_s           float64   rate MAE, deg/s (pilot command against measured
mae_pitch_deg_s          float64   rate while airborne; up to a crash)
mae_yaw_deg_s            float64
rms_roll_deg_s           float64   rate RMS error, deg/s, same samples
rms_pitch_deg_s          float64
rms_yaw_deg_s            float64
saturation_any           float64   fraction of airborne time the mixer saturated
crashed                  bool      the flight crashed (null: it raised)
crashed_at_s             float64   when, s
feasible                 bool      False: the oracle that may also set the
                                   collective crashes in this case too; null:
                                   its verdict failed
error                    string    what the flight raised, or null
sim_time_s               float64   simulated time flown, s
wall_time_s              float64   the flight's wall time on its worker, s
mfc_companion_version    string    versions on the worker that flew it
python_version           string
numpy_version            string
oracle_mae_roll_deg_s    float64   the oracle's MAE in this flight's case (the
oracle_mae_pitch_deg_s   float64   limit, sitl/lab/oracle.py); null when not
oracle_mae_yaw_deg_s     float64   flown (``--no-oracle``) or when it raised
======================== ========= ==============================================

``campaign.json``'s records, ``summary.md`` and ``mae.png`` are computed from this
table (:func:`to_records` gives the records back in ``campaign.json``'s shape).

The envelope's flights are a table too, ``envelope.parquet``
(:data:`ENVELOPE_SCHEMA`, :func:`envelope_table`): one row per test flight,
four per case (``mfc``, ``pid_tuned``, ``pid_default`` and, when flown, the
``oracle``), in case order, with the vehicle's figures and the case's
feasibility on every row; docs/campaigns.md gives its columns.

The outer sweep's flights (``python -m sitl.lab.outer_sweep``) are a table too,
its ``flights.parquet`` (:data:`OUTER_SWEEP_SCHEMA`, :func:`outer_sweep_table`):
one row per flight, with the case's feasibility; docs/campaigns.md gives its
columns.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from companion.control import AXES
from sitl.lab.atomic import replacing

__all__ = [
    "ENVELOPE_SCHEMA",
    "FLIGHTS_SCHEMA",
    "OUTER_SWEEP_SCHEMA",
    "SPEC_COLUMNS",
    "envelope_table",
    "outer_sweep_table",
    "read_table",
    "to_records",
    "to_table",
    "write_table",
]

SPEC_COLUMNS = (
    "profile",
    "damage",
    "gust_sigma_m_s",
    "seed",
    "controller",
    "controller_kind",
    "scenario",
    "duration_s",
)
_VERSIONS = ("mfc_companion", "python", "numpy")

FLIGHTS_SCHEMA = pa.schema(
    [
        pa.field("profile", pa.string(), nullable=False),
        pa.field("damage", pa.float64(), nullable=False),
        pa.field("gust_sigma_m_s", pa.float64(), nullable=False),
        pa.field("seed", pa.int64(), nullable=False),
        pa.field("controller", pa.string(), nullable=False),
        pa.field("controller_kind", pa.string(), nullable=False),
        pa.field("scenario", pa.string(), nullable=False),
        pa.field("duration_s", pa.float64(), nullable=False),
        pa.field("flight_id", pa.string(), nullable=False),
        *(pa.field(f"mae_{a}_deg_s", pa.float64()) for a in AXES),
        *(pa.field(f"rms_{a}_deg_s", pa.float64()) for a in AXES),
        pa.field("saturation_any", pa.float64()),
        pa.field("crashed", pa.bool_()),
        pa.field("crashed_at_s", pa.float64()),
        pa.field("feasible", pa.bool_()),
        pa.field("error", pa.string()),
        pa.field("sim_time_s", pa.float64()),
        pa.field("wall_time_s", pa.float64()),
        *(pa.field(f"{v}_version", pa.string()) for v in _VERSIONS),
        *(pa.field(f"oracle_mae_{a}_deg_s", pa.float64()) for a in AXES),
    ],
    metadata={"schema": "mfc-companion campaign flights, version 2"},
)
"""The columns of ``flights.parquet`` (module docstring)."""


def _row(rec: dict[str, Any]) -> dict[str, Any]:
    mae = rec.get("mae_deg_s") or {}
    rms = rec.get("rms_deg_s") or {}
    versions = rec.get("versions") or {}
    return {
        **{k: rec[k] for k in SPEC_COLUMNS},
        "flight_id": rec["flight_id"],
        **{f"mae_{a}_deg_s": mae.get(a) for a in AXES},
        **{f"rms_{a}_deg_s": rms.get(a) for a in AXES},
        **{k: rec.get(k) for k in ("saturation_any", "crashed", "crashed_at_s", "feasible")},
        **{k: rec.get(k) for k in ("error", "sim_time_s", "wall_time_s")},
        **{f"{v}_version": versions.get(v) for v in _VERSIONS},
        **{f"oracle_mae_{a}_deg_s": (rec.get("oracle_mae_deg_s") or {}).get(a) for a in AXES},
    }


def to_table(records: Sequence[dict[str, Any]]) -> pa.Table:
    """Flight records (:func:`sitl.lab.campaign.fly_one`'s, with ``feasible``) as a table."""
    return pa.Table.from_pylist([_row(r) for r in records], schema=FLIGHTS_SCHEMA)


def to_records(table: pa.Table) -> list[dict[str, Any]]:
    """The rows in ``campaign.json``'s record shape: per-axis figures nested
    (``mae_deg_s``, ``rms_deg_s``), the versions left out (they go to its meta)."""
    out = []
    for row in table.to_pylist():
        out.append(
            {
                **{k: row[k] for k in SPEC_COLUMNS[:6]},
                "mae_deg_s": {a: row[f"mae_{a}_deg_s"] for a in AXES},
                **{k: row[k] for k in ("crashed", "crashed_at_s", "saturation_any")},
                **{k: row[k] for k in ("sim_time_s", "feasible", "flight_id")},
                **{k: row[k] for k in ("scenario", "duration_s")},
                "rms_deg_s": {a: row[f"rms_{a}_deg_s"] for a in AXES},
                **{k: row[k] for k in ("error", "wall_time_s")},
                "oracle_mae_deg_s": (
                    None
                    if row["oracle_mae_roll_deg_s"] is None
                    else {a: row[f"oracle_mae_{a}_deg_s"] for a in AXES}
                ),
            }
        )
    return out


ENVELOPE_VEHICLE_COLUMNS = ("mass_kg", "arm_m", "thrust_to_weight", "motor_tau_s")
"""The vehicle's figures each row of ``envelope.parquet`` carries (from its record's
``vehicle_info``)."""

ENVELOPE_SCHEMA = pa.schema(
    [
        pa.field("vehicle", pa.string(), nullable=False),
        pa.field("case", pa.string(), nullable=False),
        pa.field("controller", pa.string(), nullable=False),
        *(pa.field(k, pa.float64()) for k in ENVELOPE_VEHICLE_COLUMNS),
        *(pa.field(f"mae_{a}_deg_s", pa.float64()) for a in AXES),
        pa.field("crashed", pa.bool_()),
        pa.field("crashed_at_s", pa.float64()),
        pa.field("sim_time_s", pa.float64()),
        pa.field("feasible", pa.bool_()),
        pa.field("tune_flights", pa.int64()),
    ],
    metadata={"schema": "mfc-companion envelope flights, version 1"},
)
"""The columns of ``envelope.parquet`` (docs/campaigns.md)."""


def envelope_table(records: Sequence[dict[str, Any]]) -> pa.Table:
    """The envelope's records (:func:`sitl.lab.envelope.run_envelope`'s) as one row per
    test flight: the three controllers' then the oracle's, when it flew."""
    rows = []
    for rec in records:
        info = rec.get("vehicle_info") or {}
        flights = {**rec["flights"], **({"oracle": rec["oracle"]} if rec.get("oracle") else {})}
        for controller, f in flights.items():
            rows.append(
                {
                    "vehicle": rec["vehicle"],
                    "case": rec["case"],
                    "controller": controller,
                    **{k: info.get(k) for k in ENVELOPE_VEHICLE_COLUMNS},
                    **{f"mae_{a}_deg_s": f["mae_deg_s"].get(a) for a in AXES},
                    **{k: f.get(k) for k in ("crashed", "crashed_at_s", "sim_time_s")},
                    "feasible": rec.get("feasible"),
                    "tune_flights": (rec.get("tune") or {}).get("flights"),
                }
            )
    return pa.Table.from_pylist(rows, schema=ENVELOPE_SCHEMA)


OUTER_SWEEP_FIGURES = (
    "lift_off_s", "hover_thrust_estimate", "hover_motor_command",
    "pos_rms_h_m", "pos_max_h_m", "pos_rms_v_m", "est_rms_h_m", "est_rms_v_m",
    "att_mae_deg", "yaw_mae_deg", "rate_sat_s", "thrust_sat_s", "tilt_limited_s",
    "path_rms_m", "path_max_m",
    "est_floor_h_m", "est_floor_v_m", "est_floor_att_deg", "est_floor_yaw_deg",
)  # fmt: skip
"""The float figures of an outer flight (:func:`sitl.lab.outer_flight.outer_metrics`),
one column each; null where the scenario has none (no path in a hold)."""

OUTER_SWEEP_SCHEMA = pa.schema(
    [
        pa.field("vehicle", pa.string(), nullable=False),
        pa.field("damage", pa.string(), nullable=False),
        pa.field("scenario", pa.string(), nullable=False),
        pa.field("law", pa.string(), nullable=False),
        pa.field("true_state", pa.bool_(), nullable=False),
        pa.field("profile", pa.string()),
        pa.field("mode", pa.string()),
        pa.field("seed", pa.int64()),
        pa.field("crashed", pa.bool_()),
        pa.field("crashed_at_s", pa.float64()),
        *(pa.field(k, pa.float64()) for k in OUTER_SWEEP_FIGURES),
        pa.field("step_reach_s", pa.list_(pa.float64())),
        pa.field("feasible", pa.bool_()),
        pa.field("wall_s", pa.float64()),
    ],
    metadata={"schema": "mfc-companion outer sweep flights, version 2"},
)
"""The columns of the outer sweep's ``flights.parquet`` (docs/campaigns.md)."""


def outer_sweep_table(
    records: Sequence[dict[str, Any]],
    feasible: dict[tuple[str, str, str, int | None], bool | None],
) -> pa.Table:
    """The outer sweep's records (:func:`sitl.lab.outer_sweep.fly`'s) as one row per
    flight, each with its case's ``feasible`` (keyed by vehicle, damage, scenario, seed)."""
    keep = [f.name for f in OUTER_SWEEP_SCHEMA if f.name != "feasible"]
    rows = [
        {
            **{k: r.get(k) for k in keep},
            "feasible": feasible.get((r["vehicle"], r["damage"], r["scenario"], r.get("seed"))),
        }
        for r in records
    ]
    return pa.Table.from_pylist(rows, schema=OUTER_SWEEP_SCHEMA)


def write_table(table: pa.Table, path: str | Path) -> Path:
    """Write ``table`` as Parquet at ``path``, whole or not at all."""
    with replacing(Path(path)) as tmp:
        pq.write_table(table, tmp)
    return Path(path)


def read_table(path: str | Path) -> pa.Table:
    """``flights.parquet`` back, checked against :data:`FLIGHTS_SCHEMA`."""
    table = pq.read_table(path)
    if not table.schema.equals(FLIGHTS_SCHEMA, check_metadata=False):
        raise ValueError(f"{path}: not a campaign flights table (its schema differs)")
    return table
