"""The client of `mscale serve` (gRPC, mscale.orchestrator.v1), with the CLI's behaviour:
submit uploads the files the scene names (every string value of the scene that names an
existing file relative to the scene's directory, with its SHA-256), watch follows the
numbered events and reconnects after `after_sequence` when the stream breaks, fetch checks
every file against the SHA-256 the server sends and never writes outside the destination."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
import time
from typing import Iterator, Optional, Sequence

import grpc

from mscale.orchestrator.v1 import orchestrator_pb2 as pb
from mscale.orchestrator.v1 import orchestrator_pb2_grpc as pb_grpc

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    tomllib = None

DEFAULT_SERVER = "127.0.0.1:50100"
MAX_MESSAGE = 64 << 20
FINAL_STATES = ("completed", "failed", "cancelled")
# Statuses after which retrying cannot help (as `mscale watch`).
_FINAL_CODES = {
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.OUT_OF_RANGE,
    grpc.StatusCode.UNAUTHENTICATED,
    grpc.StatusCode.PERMISSION_DENIED,
    grpc.StatusCode.FAILED_PRECONDITION,
    grpc.StatusCode.UNIMPLEMENTED,
}


class MscaleError(Exception):
    """A call the server refused or that failed: `code` (a grpc.StatusCode or None) and the
    server's message."""

    def __init__(self, message: str, code: Optional[grpc.StatusCode] = None):
        super().__init__(message)
        self.code = code
        self.message = message


def _refused(e: grpc.RpcError) -> MscaleError:
    code = e.code() if hasattr(e, "code") else None
    details = e.details() if hasattr(e, "details") else str(e)
    name = code.name if code is not None else "ERROR"
    return MscaleError(f"{details} ({name})", code)


def _state(v: int) -> str:
    return pb.JobState.Name(v).removeprefix("JOB_STATE_").lower() if v in pb.JobState.values() else "unknown"


@dataclasses.dataclass(frozen=True)
class Job:
    id: str
    scene: str
    state: str
    priority: int
    step: int
    steps: int
    sim_time_s: float
    error: str
    state_digest: str
    submitted_unix: int
    started_unix: int
    finished_unix: int
    resumes: int
    # The user who submitted it, the workers it asked for (0: every free one) and the MPI ranks
    # its continuum runs over (1: in the orchestrator's process).
    owner: str = ""
    workers: int = 0
    ranks: int = 1

    @classmethod
    def from_pb(cls, j) -> "Job":
        return cls(j.id, j.scene, _state(j.state), j.priority, j.step, j.steps, j.sim_time_s, j.error, j.state_digest,
                   j.submitted_unix, j.started_unix, j.finished_unix, j.resumes, j.owner, j.workers, max(j.ranks, 1))

    @property
    def done(self) -> bool:
        return self.state in FINAL_STATES


@dataclasses.dataclass(frozen=True)
class JobWorker:
    worker_id: str
    address: str
    state: str
    boxes: int
    advertised_atom_steps_per_s: float
    measured_atom_steps_per_s: float


@dataclasses.dataclass(frozen=True)
class Event:
    """One watch event. `kind` is state, progress, checkpoint, workers or not_retained (then
    events `not_retained_from`..`sequence` are no longer kept by the server)."""

    job_id: str
    sequence: int
    kind: str
    state: str
    step: int
    steps: int
    percent: float
    sim_time_s: float
    end_time_s: float
    eta_s: Optional[float]
    energy_drift: float
    message: str
    workers: tuple
    not_retained_from: int
    at_unix: int

    @classmethod
    def from_pb(cls, e) -> "Event":
        kind = pb.JobEventKind.Name(e.kind).removeprefix("JOB_EVENT_KIND_").lower() if e.kind in pb.JobEventKind.values() else "unknown"
        workers = tuple(
            JobWorker(w.worker_id, w.address, pb.WorkerState.Name(w.state).removeprefix("WORKER_STATE_").lower(), w.boxes,
                      w.advertised_atom_steps_per_s, w.measured_atom_steps_per_s)
            for w in e.workers
        )
        return cls(e.job_id, e.sequence, kind, _state(e.state), e.step, e.steps, e.percent, e.sim_time_s, e.end_time_s,
                   e.eta_s if e.eta_s >= 0 else None, e.energy_drift, e.message, workers, e.not_retained_from, e.at_unix)

    @property
    def final(self) -> bool:
        return self.kind != "not_retained" and self.state in FINAL_STATES


def scene_files(scene_path: pathlib.Path) -> list:
    """The files a scene names, as `mscale submit` finds them: every string value of the TOML
    that names an existing file relative to the scene's directory (sorted, each once)."""
    text = scene_path.read_text()
    names = set()

    def walk(v):
        if isinstance(v, str):
            names.add(v)
        elif isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, list):
            for x in v:
                walk(x)

    if tomllib is not None:
        try:
            walk(tomllib.loads(text))
        except tomllib.TOMLDecodeError:
            pass  # the server names the problem
    base = scene_path.parent
    return [n for n in sorted(names) if n and (base / n).is_file()]


class Client:
    """`Client(server, token=..., ca_file=...)`: `server` is HOST:PORT (or http(s)://HOST:PORT);
    `token` defaults to the MSCALE_TOKEN variable, or the contents of `token_file`; with
    `ca_file` (PEM) the connection is TLS trusting that authority (MSCALE_CA_FILE too)."""

    def __init__(self, server: str = DEFAULT_SERVER, token: Optional[str] = None, ca_file=None, token_file=None,
                 timeout: float = 60.0):
        if token is None and token_file is not None:
            token = pathlib.Path(token_file).read_text().strip()
        if token is None:
            token = os.environ.get("MSCALE_TOKEN") or None
        ca_file = ca_file or os.environ.get("MSCALE_CA_FILE") or None
        target = server
        for prefix in ("http://", "https://"):
            if target.startswith(prefix):
                target = target[len(prefix):]
        self.server, self.token, self.timeout = server, token, timeout
        options = [("grpc.max_receive_message_length", MAX_MESSAGE), ("grpc.max_send_message_length", MAX_MESSAGE)]
        if ca_file:
            creds = grpc.ssl_channel_credentials(root_certificates=pathlib.Path(ca_file).read_bytes())
            self._channel = grpc.secure_channel(target, creds, options=options)
        else:
            self._channel = grpc.insecure_channel(target, options=options)
        self._stub = pb_grpc.OrchestratorStub(self._channel)

    def close(self):
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _auth(self, call: str):
        if not self.token:
            raise MscaleError(f"{call} needs the orchestrator's token: pass token= or token_file=, or set MSCALE_TOKEN")
        return [("authorization", f"Bearer {self.token}")]

    def _read_auth(self):
        # Reads carry the token when there is one: with `mscale serve --users` every call needs
        # it (and a user sees only its own jobs); with one token reads work without it.
        return [("authorization", f"Bearer {self.token}")] if self.token else None

    def _call(self, method, request, metadata=None, timeout=None):
        if metadata is None:
            metadata = self._read_auth()
        try:
            return method(request, metadata=metadata, timeout=timeout or self.timeout)
        except grpc.RpcError as e:
            raise _refused(e) from None

    def submit(self, scene_path, overrides: Optional[Sequence[str] | dict] = None, priority: int = 0,
               checkpoint_every: int = 0, workers: int = 0, ranks: int = 1) -> str:
        """Submits a scene with the files it names; `overrides` are `key=value` strings or a dict
        {dotted.key: value} (values written as TOML: 8, 1e-12, "text", [16]); `workers` is the
        number of workers the job runs on (0: every free one); `ranks` the MPI ranks its
        continuum runs over (above 1 the orchestrator needs `mscale serve --mpi-mscale`).
        Returns the job id."""
        scene_path = pathlib.Path(scene_path)
        try:
            text = scene_path.read_text()
        except OSError as e:
            raise MscaleError(f"cannot read {scene_path}: {e}") from None
        files = []
        for name in scene_files(scene_path):
            content = (scene_path.parent / name).read_bytes()
            files.append(pb.InputFile(name=name, sha256=hashlib.sha256(content).hexdigest(), content=content))
        req = pb.SubmitJobRequest(scene_text=text, files=files, overrides=_overrides(overrides), priority=priority,
                                  checkpoint_every_steps=checkpoint_every, scene_file=str(scene_path),
                                  workers=workers, ranks=ranks)
        return self._call(self._stub.SubmitJob, req, self._auth("SubmitJob")).job_id

    def status(self, job: str) -> Job:
        return Job.from_pb(self._call(self._stub.GetJob, pb.GetJobRequest(job_id=job)))

    def jobs(self) -> list:
        return [Job.from_pb(j) for j in self._call(self._stub.ListJobs, pb.ListJobsRequest()).jobs]

    def workers(self) -> list:
        return list(self._call(self._stub.ListWorkers, pb.ListWorkersRequest()).workers)

    def cancel(self, job: str) -> Job:
        return Job.from_pb(self._call(self._stub.CancelJob, pb.CancelJobRequest(job_id=job), self._auth("CancelJob")))

    def watch(self, job: str, after: int = 0, reconnect_for: float = 60.0) -> Iterator[Event]:
        """The job's events after `after`, in sequence order and each once, until the final one.
        As `mscale watch`: a broken stream (the orchestrator restarted, the connection dropped)
        or a gap in the numbers reconnects after the last event received, for up to
        `reconnect_for` seconds since the last event came; then MscaleError."""
        broken, pause = None, 0.1
        while True:
            why = None
            try:
                stream = self._stub.WatchJob(pb.WatchJobRequest(job_id=job, after_sequence=after), metadata=self._read_auth())
                for e in stream:
                    if e.sequence == 0:  # an orchestrator that numbers no events
                        ev = Event.from_pb(e)
                        yield ev
                        if ev.final:
                            return
                        continue
                    if e.sequence <= after:
                        continue
                    ev = Event.from_pb(e)
                    first = e.not_retained_from if ev.kind == "not_retained" else e.sequence
                    if first != after + 1:
                        why = f"event {first} came after event {after}"
                        stream.cancel()
                        break
                    after, broken, pause = e.sequence, None, 0.1
                    yield ev
                    if ev.final:
                        return
                else:
                    why = "the stream ended before the job did"
            except grpc.RpcError as e:
                if e.code() in _FINAL_CODES:
                    raise _refused(e) from None
                why = str(_refused(e))
            if broken is None:
                broken = time.monotonic()
            if time.monotonic() - broken >= reconnect_for:
                raise MscaleError(f"lost the watch of job {job} at {self.server} after event {after} ({why}) and could not "
                                  f"resume it within {reconnect_for:.0f} s")
            time.sleep(pause)
            pause = min(pause * 2, 1.0)

    def wait(self, job: str, reconnect_for: float = 60.0) -> Event:
        """Watches the job to its end; returns the final event."""
        last = None
        for last in self.watch(job, reconnect_for=reconnect_for):
            pass
        return last

    def fetch(self, job: str, dest, file: Optional[str] = None) -> pathlib.Path:
        """Copies one file of the job's run directory to the path `dest`, or without `file`
        every file of it into the directory `dest` (each checked against its SHA-256)."""
        dest = pathlib.Path(dest)
        if file is not None:
            r = self._call(self._stub.FetchResult, pb.FetchResultRequest(job_id=job, path=file))
            if hashlib.sha256(r.content).hexdigest() != r.sha256:
                raise MscaleError(f"{file} arrived damaged (SHA-256 mismatch)")
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(r.content)
            return dest
        dest.mkdir(parents=True, exist_ok=True)
        current, h, out, written = None, None, None, 0
        try:
            for c in self._stub.FetchRun(pb.FetchRunRequest(job_id=job), metadata=self._read_auth()):
                if current != c.path:
                    if current is not None:
                        raise MscaleError(f"the orchestrator sent {c.path} before the end of {current}")
                    rel = pathlib.PurePosixPath(c.path)
                    if not c.path or rel.is_absolute() or any(p in ("..", ".", "") for p in rel.parts):
                        raise MscaleError(f"the orchestrator sent the file name {c.path!r}; refusing to write it")
                    target = dest.joinpath(*rel.parts)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    current, h, out, written = c.path, hashlib.sha256(), open(target, "wb"), 0
                if c.offset != written:
                    raise MscaleError(f"{c.path}: a chunk at byte {c.offset} after {written} bytes")
                out.write(c.data)
                h.update(c.data)
                written += len(c.data)
                if c.last:
                    out.close()
                    if written != c.size or h.hexdigest() != c.sha256:
                        raise MscaleError(f"{c.path} arrived damaged ({written} bytes, SHA-256 {h.hexdigest()}; sent {c.size}, {c.sha256})")
                    current = None
        except grpc.RpcError as e:
            raise _refused(e) from None
        finally:
            if out is not None and not out.closed:
                out.close()
        return dest


def _overrides(o) -> list:
    if o is None:
        return []
    if isinstance(o, dict):
        return [f"{k}={_toml(v)}" for k, v in o.items()]
    return [str(x) for x in o]


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, str):
        # A bare word stays as the CLI would take it (`scheme.method=ugimp`); anything else is quoted.
        return v if v.replace("_", "").replace("-", "").isalnum() else '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    raise MscaleError(f"override value {v!r} is not a number, string, bool or list")
