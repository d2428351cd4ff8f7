"""Loaders of mscale run directories and sweep reports.

A run directory (`mscale run --out DIR`, a job fetched with `mscale fetch JOB --out DIR` or
`Client.fetch`) holds `summary.json`, `snapshots/index.csv` (step,time,file) with one
particle CSV per snapshot, and, when the scene asks for them, LAMMPS text dumps of chosen MD
boxes in `boxes/point-<id>.dump` (which OVITO reads)."""

from __future__ import annotations

import dataclasses
import itertools
import json
import pathlib
from typing import Optional

import numpy as np
import pandas as pd
import xarray as xr


@dataclasses.dataclass
class Run:
    """A loaded run directory.

    - `summary`: summary.json as a dict.
    - `snapshots`: an xarray Dataset with dimensions (time, particle): coordinates `time` (s),
      `step` (along time) and `particle` (the id column); every other column of the particle
      CSVs (x0, x, vx, mass, volume, density, pressure, sxx..syz and any MD columns) as a
      variable, NaN where a value was not finite. None without snapshots.
    - `errors`: summary.json's `errors` (the score against the exact solution or the direct-MD
      reference) or None.
    - `reference`: the direct-MD reference profile the run was scored against, as a DataFrame,
      when the summary names one and it can be read; else None.
    - `dumps`: the OVITO-readable box dumps, {point id: path}.
    """

    path: pathlib.Path
    summary: dict
    snapshots: Optional[xr.Dataset]
    errors: Optional[dict]
    reference: Optional[pd.DataFrame]
    dumps: dict

    def __getitem__(self, key):
        return getattr(self, key)


def load_snapshots(run_dir) -> Optional[xr.Dataset]:
    """The snapshots of a run directory as a (time x particle) Dataset; None without any."""
    run_dir = pathlib.Path(run_dir)
    index_path = run_dir / "snapshots" / "index.csv"
    if not index_path.is_file():
        return None
    index = pd.read_csv(index_path)
    if index.empty:
        return None
    frames = []
    for file in index["file"]:
        f = pd.read_csv(run_dir / "snapshots" / str(file))
        frames.append(f.set_index("id").sort_index())
    particles = frames[0].index.to_numpy()
    for k, f in enumerate(frames):
        if not np.array_equal(f.index.to_numpy(), particles):
            raise ValueError(f"{run_dir}: snapshot {index['file'][k]} has other particles than {index['file'][0]}")
    columns = list(frames[0].columns)
    data = {c: (("time", "particle"), np.stack([f[c].to_numpy(dtype=float) for f in frames])) for c in columns}
    return xr.Dataset(
        data,
        coords={
            "time": ("time", index["time"].to_numpy(dtype=float), {"units": "s"}),
            "step": ("time", index["step"].to_numpy(dtype=np.int64)),
            "particle": ("particle", particles),
        },
        attrs={"run_dir": str(run_dir)},
    )


def _reference(summary: dict, run_dir: pathlib.Path) -> Optional[pd.DataFrame]:
    errors = summary.get("errors") or {}
    if errors.get("reference") != "direct-md" or not errors.get("profile"):
        return None
    p = pathlib.Path(errors["profile"])
    for candidate in (p, run_dir / p, run_dir / p.name):
        if candidate.is_file():
            return pd.read_csv(candidate, comment="#")
    return None


def load_run(path) -> Run:
    """Loads a run directory (see [Run])."""
    path = pathlib.Path(path)
    summary_path = path / "summary.json"
    if not summary_path.is_file():
        raise FileNotFoundError(f"{summary_path} does not exist: is {path} an mscale run directory?")
    summary = json.loads(summary_path.read_text())
    dumps = {}
    for d in sorted((path / "boxes").glob("point-*.dump")):
        try:
            dumps[int(d.stem.removeprefix("point-"))] = d
        except ValueError:
            continue
    return Run(path, summary, load_snapshots(path), summary.get("errors"), _reference(summary, path), dumps)


def load_report(path) -> pd.DataFrame:
    """`report.csv` of `mscale report error-vs-time` (or of [sweep]) as a DataFrame; `path` is
    the CSV or its directory."""
    path = pathlib.Path(path)
    if path.is_dir():
        path = path / "report.csv"
    return pd.read_csv(path)


def summary_row(summary: dict) -> dict:
    """The report.csv columns of one run's summary (method, status, errors, cost)."""
    errors = summary.get("errors") or {}
    row = {
        "method": summary.get("method"),
        "status": summary.get("status"),
        "pressure_l1": errors.get("pressure_l1"),
        "pressure_l2": errors.get("pressure_l2"),
        "pressure_spike": errors.get("pressure_spike"),
        "wall_seconds": summary.get("wall_seconds"),
        "steps": summary.get("steps"),
        "closure_evaluations": summary.get("closure_evaluations"),
        "energy_drift": (summary.get("conservation") or {}).get("energy_drift"),
        "state_digest": summary.get("state_digest"),
    }
    for t in errors.get("times") or []:
        if isinstance(t, dict) and "time_ps" in t:
            row[f"{errors.get('component', 'sxx')}_error_{t['time_ps']:g}ps"] = t.get("error")
    return row


def sweep(client, scene, sweeps: dict, sets=None, out=None, priority: int = 0, reconnect_for: float = 60.0) -> pd.DataFrame:
    """Submits every combination of `sweeps` ({dotted.key: [values]}) of `scene` as a job of
    the service behind `client` (with the overrides `sets` on each), watches each to its end,
    fetches each run into `out`/runs/NNN when `out` is given, and returns one row per run: the
    swept values, job id, state and the report.csv columns of its summary."""
    from .client import _overrides, _toml

    keys = list(sweeps)
    combos = list(itertools.product(*(sweeps[k] for k in keys)))
    base = _overrides(sets)
    jobs = []
    for combo in combos:
        overrides = base + [f"{k}={_toml(v)}" for k, v in zip(keys, combo)]
        jobs.append(client.submit(scene, overrides=overrides, priority=priority))
    rows = []
    for k, (combo, job) in enumerate(zip(combos, jobs)):
        last = client.wait(job, reconnect_for=reconnect_for)
        row = dict(zip(keys, combo))
        row.update({"job_id": job, "state": last.state if last else "unknown"})
        if out is not None and last is not None and last.state == "completed":
            run_dir = client.fetch(job, pathlib.Path(out) / "runs" / f"{k:03}")
            row.update(summary_row(json.loads((run_dir / "summary.json").read_text())))
            row["run_dir"] = str(run_dir)
        elif last is not None and last.state == "completed":
            import tempfile

            with tempfile.TemporaryDirectory() as tmp:
                s = client.fetch(job, pathlib.Path(tmp) / "summary.json", file="summary.json")
                row.update(summary_row(json.loads(s.read_text())))
        rows.append(row)
    frame = pd.DataFrame(rows)
    if out is not None:
        pathlib.Path(out).mkdir(parents=True, exist_ok=True)
        frame.to_csv(pathlib.Path(out) / "report.csv", index=False)
    return frame
