"""Builds the package with the gRPC stubs of mscale.orchestrator.v1 generated from the
repository's proto/ directory (or MSCALE_PROTO_DIR) by grpcio-tools: nothing generated is
committed, so the stubs always match the server's .proto."""

import os
import pathlib

from setuptools import setup
from setuptools.command.build_py import build_py

PROTO = "mscale/orchestrator/v1/orchestrator.proto"


class BuildWithStubs(build_py):
    def run(self):
        super().run()
        import grpc_tools
        from grpc_tools import protoc

        here = pathlib.Path(__file__).resolve().parent
        root = pathlib.Path(os.environ.get("MSCALE_PROTO_DIR") or here.parent / "proto")
        if not (root / PROTO).is_file():
            raise SystemExit(
                f"mscale: cannot find {root / PROTO}: install from the mscale repository "
                "(pip install ./python) or set MSCALE_PROTO_DIR to its proto/ directory"
            )
        out = pathlib.Path(self.build_lib)
        include = pathlib.Path(grpc_tools.__file__).parent / "_proto"
        args = ["grpc_tools.protoc", f"-I{root}", f"-I{include}", f"--python_out={out}", f"--grpc_python_out={out}", PROTO]
        if protoc.main(args) != 0:
            raise SystemExit(f"mscale: grpc_tools.protoc failed on {root / PROTO}")
        # The generated modules import each other as mscale.orchestrator.v1.*: inside this package.
        for d in ("mscale/orchestrator", "mscale/orchestrator/v1"):
            (out / d / "__init__.py").touch()


setup(cmdclass={"build_py": BuildWithStubs})
