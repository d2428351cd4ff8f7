"""A real `mscale serve` on 127.0.0.1 for the tests: the prebuilt `mscale` from MSCALE_BIN_DIR
(default: the repository's target/debug, then target/release), its state in a temporary
directory, a token file of its own."""

import os
import pathlib
import subprocess
import threading

import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]
TOKEN = "python-test-token-0123456789"


def mscale_bin() -> pathlib.Path:
    dirs = [os.environ["MSCALE_BIN_DIR"]] if os.environ.get("MSCALE_BIN_DIR") else [REPO / "target/debug", REPO / "target/release"]
    for d in dirs:
        p = pathlib.Path(d) / "mscale"
        if p.is_file():
            return p
    raise RuntimeError(f"no mscale program in {', '.join(map(str, dirs))}: build it (cargo build -p orchestrator --bin mscale) "
                       "or set MSCALE_BIN_DIR")


class Server:
    def __init__(self, tmp: pathlib.Path):
        self.token_file = tmp / "token"
        self.token_file.write_text(TOKEN + "\n")
        self.state = tmp / "state"
        self.log = tmp / "serve.log"
        self.proc = subprocess.Popen(
            [str(mscale_bin()), "serve", "--state", str(self.state), "--listen", "127.0.0.1:0", "--token-file", str(self.token_file),
             "--checkpoint-every", "50"],
            stdout=subprocess.PIPE, stderr=open(self.log, "w"), text=True, env={**os.environ, "RUST_LOG": "info"},
        )
        line = self.proc.stdout.readline()
        prefix = "mscale serve: listening on "
        if not line.startswith(prefix):
            self.proc.kill()
            raise RuntimeError(f"mscale serve said {line!r}; log: {self.log.read_text()}")
        self.addr = line[len(prefix):].strip()
        # Keep reading stdout so the server never blocks on a full pipe.
        threading.Thread(target=self.proc.stdout.read, daemon=True).start()

    def stop(self):
        self.proc.terminate()
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    s = Server(tmp_path_factory.mktemp("serve"))
    yield s
    s.stop()


@pytest.fixture
def client(server):
    import mscale

    c = mscale.Client(server.addr, token=TOKEN)
    yield c
    c.close()
