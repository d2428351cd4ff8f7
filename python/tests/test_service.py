"""The Python client against a real `mscale serve` (started by conftest.py): submit with the
scene's files, numbered events to the end, fetch and load, errors with the server's message,
cancel, and a sweep submitted, watched and loaded from Python."""

import json
import pathlib
import subprocess
import sys

import grpc
import numpy as np
import pytest

import mscale
from conftest import REPO, mscale_bin

SMALL = REPO / "tests/data/small.toml"
MD_SMALL = REPO / "tests/data/md-small.toml"


def test_a_job_is_watched_to_its_end_fetched_and_loaded(client, tmp_path):
    job = client.submit(MD_SMALL, overrides={"scheme.end_time": 1e-13, "output.dump_points": [0, 3]})
    assert job.startswith("j")
    events = list(client.watch(job))
    assert [e.sequence for e in events] == list(range(1, len(events) + 1)), "events are numbered 1, 2, 3, ... with no gap"
    assert events[0].state == "queued" and events[-1].final and events[-1].state == "completed", events[-1]
    assert any(e.kind == "progress" for e in events)
    final = client.status(job)
    assert final.state == "completed" and final.step == final.steps == events[-1].step
    run_dir = client.fetch(job, tmp_path / "run")
    run = mscale.load_run(run_dir)
    assert run.summary["status"] == "completed"
    assert run.summary["state_digest"] == final.state_digest
    # The md-small scene's potential travelled with it (the CLI's rule: files the scene names).
    assert mscale.scene_files(MD_SMALL) == ["../../md-worker/potentials/Cu_mishin1.eam.alloy"]
    ds = run.snapshots
    assert ds.sizes["particle"] == run.summary["points"]
    assert ds["step"].values[-1] == final.steps
    assert ds["time"].values[-1] == pytest.approx(final.sim_time_s, rel=1e-12)
    assert {"x", "vx", "pressure", "sxx", "density"} <= set(ds.data_vars)
    # The snapshot file as the run wrote it, value for value.
    last = (tmp_path / "run/snapshots/index.csv").read_text().strip().splitlines()[-1].split(",")[2]
    import pandas as pd

    table = pd.read_csv(tmp_path / "run/snapshots" / last).set_index("id").sort_index()
    np.testing.assert_array_equal(ds["sxx"].isel(time=-1).values, table["sxx"].to_numpy(dtype=float))
    # The OVITO box dumps (LAMMPS text dumps, one frame per snapshot).
    assert sorted(run.dumps) == [0, 3]
    assert run.dumps[3].read_text().count("ITEM: TIMESTEP") == ds.sizes["time"]
    assert run.errors is None and run.reference is None  # md-small names no reference
    # One file alone.
    one = client.fetch(job, tmp_path / "summary.json", file="summary.json")
    assert json.loads(one.read_text())["state_digest"] == final.state_digest
    assert any(j.id == job for j in client.jobs())


def test_the_watch_resumes_after_a_sequence_number(client):
    job = client.submit(SMALL)
    all_events = list(client.watch(job))
    later = list(client.watch(job, after=2))
    assert [e.sequence for e in later] == [e.sequence for e in all_events[2:]]
    assert later[-1].final


def test_server_errors_are_exceptions_with_the_message(client, server, tmp_path):
    with pytest.raises(mscale.MscaleError) as e:
        client.status("jnosuchjob")
    assert e.value.code == grpc.StatusCode.NOT_FOUND and 'no job "jnosuchjob"' in e.value.message
    bad = tmp_path / "bad.toml"
    bad.write_text(SMALL.read_text().replace("cfl = 0.2", "cfl = 3"))
    with pytest.raises(mscale.MscaleError) as e:
        client.submit(bad)
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT and "cfl" in e.value.message, e.value.message
    anonymous = mscale.Client(server.addr, token=None)
    with pytest.raises(mscale.MscaleError) as e:
        anonymous.submit(SMALL)
    assert "token" in e.value.message
    wrong = mscale.Client(server.addr, token="not-the-token")
    with pytest.raises(mscale.MscaleError) as e:
        wrong.submit(SMALL)
    assert e.value.code == grpc.StatusCode.UNAUTHENTICATED


def test_a_queued_job_is_cancelled(client):
    # Two long jobs: the second waits behind the first and is cancelled while queued.
    first = client.submit(SMALL, overrides={"scheme.end_time": 5.0})
    second = client.submit(SMALL, overrides={"scheme.end_time": 5.0})
    assert client.cancel(second).state == "cancelled"
    last = client.wait(second)
    assert last.state == "cancelled"
    client.cancel(first)
    assert client.wait(first).state == "cancelled"


def test_a_sweep_from_python_is_watched_to_the_end_and_loaded(client, tmp_path):
    frame = mscale.sweep(client, SMALL, {"scheme.particles_per_cell": [2, 4], "scheme.method": ["ugimp", "cpdi"]}, out=tmp_path / "sweep")
    assert len(frame) == 4 and (frame["state"] == "completed").all(), frame
    assert sorted(zip(frame["scheme.particles_per_cell"], frame["scheme.method"])) == [(2, "cpdi"), (2, "ugimp"), (4, "cpdi"), (4, "ugimp")]
    assert (frame["method"] == frame["scheme.method"]).all()
    assert (frame["pressure_l1"] > 0).all() and (frame["wall_seconds"] > 0).all()
    # Each row is its run as fetched; the report reads back the same.
    for _, row in frame.iterrows():
        run = mscale.load_run(row["run_dir"])
        assert run.summary["errors"]["pressure_l1"] == row["pressure_l1"]
        assert run.summary["state_digest"] == client.status(row["job_id"]).state_digest
    back = mscale.load_report(tmp_path / "sweep")
    assert list(back["job_id"]) == list(frame["job_id"])
    # The same scene through `mscale run` gives the digest the service gave.
    out = tmp_path / "direct"
    subprocess.run([str(mscale_bin()), "run", str(SMALL), "--out", str(out), "--set", "scheme.particles_per_cell=2", "--set",
                    "scheme.method=ugimp"], check=True, capture_output=True)
    want = json.loads((out / "summary.json").read_text())["state_digest"]
    got = frame[(frame["scheme.particles_per_cell"] == 2) & (frame["scheme.method"] == "ugimp")]["state_digest"].iloc[0]
    assert got == want


def test_the_example_draws_the_error_against_cost_figure(server, tmp_path):
    example = pathlib.Path(__file__).resolve().parents[1] / "examples/error_vs_cost.py"
    out = tmp_path / "fig.png"
    r = subprocess.run(
        [sys.executable, str(example), "--server", server.addr, "--token-file", str(server.token_file), "--scene", str(SMALL),
         "--sweep", "scheme.method=ugimp,cpdi", "--sweep", "scheme.particles_per_cell=2,4", "--out", str(tmp_path / "ex"), "--png", str(out)],
        capture_output=True, text=True,
    )
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 1000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "ex/report.csv").is_file()


def test_read_only_calls_need_no_token(server):
    c = mscale.Client(server.addr)
    assert isinstance(c.jobs(), list)
